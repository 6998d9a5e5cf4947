"""The Warp side of psao.scene.skinning: linear blend skinning of vertices (SkinDeformer) and AO points kept
on moving triangles (SurfacePoints), kernels at module level, buffers uploaded once, per call only what
moves. Imported on first use (psao.scene.skinning), so that loading a scene without skins, or a server
before its first skinned frame, does not import Warp (half a second or more at start-up)."""
from __future__ import annotations

import numpy as np
import warp as wp


@wp.func
def blended_matrix(j: wp.vec4i, w: wp.vec4d, mats: wp.array(dtype=wp.mat44d)):
    # the point's 4 joint matrices blended by its weights (skinning.blended_matrices is the numpy reference)
    return w[0] * mats[j[0]] + w[1] * mats[j[1]] + w[2] * mats[j[2]] + w[3] * mats[j[3]]


@wp.kernel
def skin_points_kernel(rest: wp.array(dtype=wp.vec3d), joints: wp.array(dtype=wp.vec4i),
                       weights: wp.array(dtype=wp.vec4d), mats: wp.array(dtype=wp.mat44d),
                       out_pos: wp.array(dtype=wp.vec3d)):
    i = wp.tid()
    m = blended_matrix(joints[i], weights[i], mats)
    p = rest[i]
    out_pos[i] = wp.vec3d(m[0, 0] * p[0] + m[0, 1] * p[1] + m[0, 2] * p[2] + m[0, 3],
                          m[1, 0] * p[0] + m[1, 1] * p[1] + m[1, 2] * p[2] + m[1, 3],
                          m[2, 0] * p[0] + m[2, 1] * p[1] + m[2, 2] * p[2] + m[2, 3])


@wp.kernel
def skin_normals_kernel(rest_nrm: wp.array(dtype=wp.vec3d), joints: wp.array(dtype=wp.vec4i),
                        weights: wp.array(dtype=wp.vec4d), mats: wp.array(dtype=wp.mat44d),
                        out_nrm: wp.array(dtype=wp.vec3d)):
    i = wp.tid()
    m = blended_matrix(joints[i], weights[i], mats)
    a = wp.mat33d(m[0, 0], m[0, 1], m[0, 2], m[1, 0], m[1, 1], m[1, 2], m[2, 0], m[2, 1], m[2, 2])
    # cofactor matrix = det * inverse transpose: the normal transform without dividing by det
    c0 = wp.cross(wp.vec3d(a[1, 0], a[1, 1], a[1, 2]), wp.vec3d(a[2, 0], a[2, 1], a[2, 2]))
    c1 = wp.cross(wp.vec3d(a[2, 0], a[2, 1], a[2, 2]), wp.vec3d(a[0, 0], a[0, 1], a[0, 2]))
    c2 = wp.cross(wp.vec3d(a[0, 0], a[0, 1], a[0, 2]), wp.vec3d(a[1, 0], a[1, 1], a[1, 2]))
    n = rest_nrm[i]
    r = wp.vec3d(wp.dot(c0, n), wp.dot(c1, n), wp.dot(c2, n))
    det = wp.dot(wp.vec3d(a[0, 0], a[0, 1], a[0, 2]), c0)
    if det < wp.float64(0.0):  # a mirroring blend: keep the normal on the same side of the surface
        r = -r
    length = wp.length(r)
    if length > wp.float64(0.0):
        r = r / length
    out_nrm[i] = r


class SkinDeformer:
    """Skins a fixed set of points (vertices or AO points) again and again for new joint matrices."""

    def __init__(self, rest_pos: np.ndarray, joints: np.ndarray, weights: np.ndarray,
                 rest_nrm: np.ndarray | None = None, device: str | None = None):
        self.device = wp.get_device(device)
        self.count = len(rest_pos)
        d = self.device
        self.joints = wp.array(np.ascontiguousarray(joints, dtype=np.int32), dtype=wp.vec4i, device=d)
        self.weights = wp.array(np.ascontiguousarray(weights, dtype=np.float64), dtype=wp.vec4d, device=d)
        self.rest_pos = wp.array(np.ascontiguousarray(rest_pos, dtype=np.float64), dtype=wp.vec3d, device=d)
        self.out_pos = wp.empty(self.count, dtype=wp.vec3d, device=d)
        self.rest_nrm = self.out_nrm = None
        if rest_nrm is not None:
            self.rest_nrm = wp.array(np.ascontiguousarray(rest_nrm, dtype=np.float64), dtype=wp.vec3d, device=d)
            self.out_nrm = wp.empty(self.count, dtype=wp.vec3d, device=d)
        self.mats: wp.array | None = None

    def _upload(self, matrices: np.ndarray) -> None:
        m = np.ascontiguousarray(matrices, dtype=np.float64)
        if self.mats is None or self.mats.shape[0] != len(m):
            self.mats = wp.empty(len(m), dtype=wp.mat44d, device=self.device)
            inputs = [self.rest_pos, self.joints, self.weights, self.mats]
            # recorded once: a launch's argument packing costs more than the kernel on a small mesh
            self._launches = [wp.launch(skin_points_kernel, dim=self.count, inputs=inputs, outputs=[self.out_pos],
                                        device=self.device, record_cmd=True)]
            if self.rest_nrm is not None:
                self._launches.append(wp.launch(skin_normals_kernel, dim=self.count, inputs=[self.rest_nrm, *inputs[1:]],
                                                outputs=[self.out_nrm], device=self.device, record_cmd=True))
        _write(self.mats, m)

    def deform(self, matrices: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Skinned positions (P, 3) and, when rest normals were given, unit normals (P, 3)."""
        self._upload(matrices)
        for launch in self._launches if self.count else ():  # Warp records no launch of no threads
            launch.launch()
        return self.out_pos.numpy(), None if self.rest_nrm is None else self.out_nrm.numpy()


def _write(array: wp.array, values: np.ndarray) -> None:
    """Copy numpy values into a Warp array: through its numpy view on the CPU (no temporary Warp array)."""
    if array.device.is_cpu:
        array.numpy()[...] = values.reshape(array.numpy().shape)
    else:
        array.assign(wp.array(values, dtype=array.dtype, device="cpu"))


@wp.kernel
def face_normals_kernel(vertices: wp.array(dtype=wp.vec3d), corners: wp.array(dtype=wp.vec3i),
                        out_nrm: wp.array(dtype=wp.vec3d)):
    # surface_points' unit normal of one triangle, or (0, 0, 0) where the skinned triangle has none
    f = wp.tid()
    c = corners[f]
    a = vertices[c[0]]
    n = wp.cross(vertices[c[1]] - a, vertices[c[2]] - a)
    n = n / wp.max(wp.length(n), wp.float64(1e-300))
    if wp.length(n) > wp.float64(0.5):
        out_nrm[f] = n
    else:
        out_nrm[f] = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))


@wp.kernel
def surface_points_kernel(vertices: wp.array(dtype=wp.vec3d), corners: wp.array(dtype=wp.vec3i),
                          face: wp.array(dtype=wp.int32), face_nrm: wp.array(dtype=wp.vec3d),
                          bary: wp.array(dtype=wp.vec3d), side: wp.array(dtype=wp.float64),
                          rest_nrm: wp.array(dtype=wp.vec3d),
                          out_pos: wp.array(dtype=wp.vec3d), out_nrm: wp.array(dtype=wp.vec3f)):
    # surface_points for one point, with SurfacePoints' side and fallback: its triangle's unit normal
    # (face_normals_kernel) times the point's side, or its rest normal where the skinned triangle has none
    i = wp.tid()
    c = corners[face[i]]
    w = bary[i]
    out_pos[i] = vertices[c[0]] * w[0] + vertices[c[1]] * w[1] + vertices[c[2]] * w[2]
    n = face_nrm[face[i]]
    if n[0] == wp.float64(0.0) and n[1] == wp.float64(0.0) and n[2] == wp.float64(0.0):
        n = rest_nrm[i]
    else:
        n = n * side[i]
    out_nrm[i] = wp.vec3f(wp.float32(n[0]), wp.float32(n[1]), wp.float32(n[2]))


class SurfacePoints:
    """Points fixed to triangles of a mesh whose vertices move (skinned AO points): positions and unit normals
    for new vertices in two kernel passes, one over the triangles that hold points (their normals: many
    points share a triangle), one over the points. The points' triangles, barycentrics, sides (+1 / -1: the
    normal along or against the triangle's) and rest normals (kept where a triangle is skinned flat) are
    uploaded once. surface_points() is the numpy reference."""

    def __init__(self, faces: np.ndarray, face_index: np.ndarray, bary: np.ndarray, side: np.ndarray,
                 rest_nrm: np.ndarray, device: str | None = "cpu"):
        self.device = d = wp.get_device(device)
        self.count = len(face_index)
        used, face = np.unique(np.asarray(face_index, np.int64), return_inverse=True)
        corners = np.asarray(faces, np.int64).reshape(-1, 3)[used]
        self.corners = wp.array(np.ascontiguousarray(corners, np.int32), dtype=wp.vec3i, device=d)
        self.face = wp.array(np.ascontiguousarray(face.reshape(-1), np.int32), dtype=wp.int32, device=d)
        self.face_nrm = wp.empty(len(used), dtype=wp.vec3d, device=d)
        self.bary = wp.array(np.ascontiguousarray(bary, np.float64), dtype=wp.vec3d, device=d)
        self.side = wp.array(np.ascontiguousarray(side, np.float64), dtype=wp.float64, device=d)
        self.rest_nrm = wp.array(np.ascontiguousarray(rest_nrm, np.float64), dtype=wp.vec3d, device=d)
        self._own = (wp.empty(self.count, dtype=wp.vec3d, device=d), wp.empty(self.count, dtype=wp.vec3f, device=d))
        self._vertices: wp.array | None = None  # the mesh's vertices of the last call
        self._launched_on = None  # (vertex count, output arrays) the recorded launches were made for

    def follow(self, vertices: np.ndarray, out: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Positions (P, 3) float64 and unit normals (P, 3) float32 on the mesh with `vertices`: written into
        `out` (C-contiguous (P, 3) float64 and float32 arrays; on the CPU the kernel writes them in place)
        and returned, or without it views of buffers this object reuses, valid until the next call."""
        own = out is None or not (self.device.is_cpu and _writable_in_place(out, self.count))
        if self.count:
            v = np.ascontiguousarray(vertices, np.float64)
            key = (len(v), None if own else tuple(a.__array_interface__["data"][0] for a in out))
            if self._launched_on != key:
                targets = self._own if own else (wp.array(out[0], dtype=wp.vec3d, device=self.device, copy=False),
                                                 wp.array(out[1], dtype=wp.vec3f, device=self.device, copy=False))
                if self._vertices is None or self._vertices.shape[0] != len(v):
                    self._vertices = wp.empty(len(v), dtype=wp.vec3d, device=self.device)
                # recorded once: a launch's argument packing costs more than the kernel on a few points
                self._launches = [
                    wp.launch(face_normals_kernel, dim=self.face_nrm.shape[0], device=self.device,
                              inputs=[self._vertices, self.corners], outputs=[self.face_nrm], record_cmd=True),
                    wp.launch(surface_points_kernel, dim=self.count, device=self.device,
                              inputs=[self._vertices, self.corners, self.face, self.face_nrm, self.bary, self.side,
                                      self.rest_nrm], outputs=list(targets), record_cmd=True)]
                self._launched_on = key
            _write(self._vertices, v)
            for launch in self._launches:
                launch.launch()
        if not own:
            return out
        pos, nrm = (a.numpy().reshape(-1, 3)[: self.count] for a in self._own)
        if out is not None:
            out[0][...], out[1][...] = pos, nrm
            return out
        return pos, nrm


def _writable_in_place(out: tuple[np.ndarray, np.ndarray], count: int) -> bool:
    """Whether a kernel can write (count, 3) float64 positions and float32 normals straight into `out`."""
    return all(a.shape == (count, 3) and a.dtype == t and a.flags.c_contiguous and a.flags.writeable
               for a, t in zip(out, (np.float64, np.float32)))
