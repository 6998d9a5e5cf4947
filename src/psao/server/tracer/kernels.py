"""Warp kernels shared by the tracer back-ends: the per-ray direction of directions.py, compiled.

`ray_direction` is the one definition of a point's j-th ray in Warp; `rays_kernel` fills the ray buffers
the Embree workers trace (numpy temporaries cost as much as Embree's own traversal), and
`visibility_kernel` traces in Warp itself; `reach_kernel` finds the rays that can reach a mover's bounding
sphere (the only ones the Embree back-end traces against the movers). tests/test_tracer.py checks the ray
and reach kernels against their numpy references, and the Warp back-end's answers against Embree's where
that back-end runs.
"""
from __future__ import annotations

import numpy as np
import warp as wp

from psao.server.tracer.directions import OFFSET_AO, OFFSET_REL, slice_count

wp.config.quiet = True

GOLDEN = 0.6180339887498949


@wp.func
def tangent(n: wp.vec3) -> wp.vec3:
    sign = 1.0
    if n[2] < 0.0:
        sign = -1.0
    a = -1.0 / (sign + n[2])
    return wp.vec3(1.0 + sign * n[0] * n[0] * a, sign * n[0] * n[1] * a, -sign * n[0])


@wp.func
def bitangent(n: wp.vec3) -> wp.vec3:
    sign = 1.0
    if n[2] < 0.0:
        sign = -1.0
    a = -1.0 / (sign + n[2])
    return wp.vec3(n[0] * n[1] * a, sign + n[1] * n[1] * a, -n[1])


@wp.func
def ray_direction(n: wp.vec3, j: int, rays: int, rot_a: float, rot_b: float) -> wp.vec3:
    u1 = (float(j) + 0.5) / float(rays) + rot_a
    u1 = u1 - wp.floor(u1)
    u2 = float(j) * GOLDEN
    u2 = u2 - wp.floor(u2) + rot_b
    u2 = u2 - wp.floor(u2)
    r = wp.sqrt(u1)
    phi = 6.283185307179586 * u2
    return tangent(n) * (r * wp.cos(phi)) + bitangent(n) * (r * wp.sin(phi)) + n * wp.sqrt(wp.max(0.0, 1.0 - u1))


@wp.func
def ray_origin(p: wp.vec3, n: wp.vec3, offset_rel: float, offset_ao: float, ao_distance: float) -> wp.vec3:
    mag = wp.max(wp.max(wp.abs(p[0]), wp.abs(p[1])), wp.abs(p[2]))
    return p + n * (offset_rel * mag + offset_ao * ao_distance)


@wp.kernel
def rays_kernel(
    positions: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    rot_a: wp.array(dtype=float),
    rot_b: wp.array(dtype=float),
    phase: wp.array(dtype=wp.vec2),
    rays: int,
    first: wp.array(dtype=int),
    step: int,
    count: int,
    ao_distance: float,
    offset_rel: float,
    offset_ao: float,
    out_origins: wp.array(dtype=wp.vec3),
    out_dirs: wp.array(dtype=wp.vec3),
):
    # One thread per point looping over its rays: a thread per ray costs ~5x more on Warp's CPU device.
    # The azimuth 2 pi (frac(j * golden) + b) is the table's angle rotated by the point's 2 pi b, so the
    # loop needs no trigonometry (same directions as ray_direction up to float rounding). It writes the
    # slice j = first[i] + k * step (k < count) of the point's `rays`-ray set.
    i = wp.tid()
    n = normals[i]
    o = ray_origin(positions[i], n, offset_rel, offset_ao, ao_distance)
    t = tangent(n)
    bt = bitangent(n)
    cb = wp.cos(6.283185307179586 * rot_b[i])
    sb = wp.sin(6.283185307179586 * rot_b[i])
    for k in range(count):
        j = first[i] + k * step
        u1 = (float(j) + 0.5) / float(rays) + rot_a[i]
        u1 = u1 - wp.floor(u1)
        r = wp.sqrt(u1)
        cs = phase[j]
        c = cs[0] * cb - cs[1] * sb
        sn = cs[1] * cb + cs[0] * sb
        out_origins[i * count + k] = o
        out_dirs[i * count + k] = t * (r * c) + bt * (r * sn) + n * wp.sqrt(wp.max(0.0, 1.0 - u1))


@wp.func
def occluded(mesh: wp.uint64, o: wp.vec3, d: wp.vec3, tmax: float) -> int:
    if mesh == wp.uint64(0):
        return 0
    q = wp.mesh_query_ray(mesh, o, d, tmax)
    if q.result:
        return 1
    return 0


@wp.kernel
def visibility_kernel(
    static_mesh: wp.uint64,
    dynamic_mesh: wp.uint64,
    positions: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    rot_a: wp.array(dtype=float),
    rot_b: wp.array(dtype=float),
    rays: int,
    first: wp.array(dtype=int),
    step: int,
    count: int,
    ao_distance: float,
    offset_rel: float,
    offset_ao: float,
    out_visibility: wp.array(dtype=float),
):
    # the slice j = first[i] + k * step (k < count) of the point's `rays`-ray set
    i = wp.tid()
    n = normals[i]
    o = ray_origin(positions[i], n, offset_rel, offset_ao, ao_distance)
    free = int(0)
    for k in range(count):
        d = ray_direction(n, first[i] + k * step, rays, rot_a[i], rot_b[i])
        if occluded(static_mesh, o, d, ao_distance) == 0:
            if occluded(dynamic_mesh, o, d, ao_distance) == 0:
                free += 1
    out_visibility[i] = float(free) / float(count)


@wp.kernel
def reach_kernel(
    origins: wp.array(dtype=wp.vec3),
    dirs: wp.array(dtype=wp.vec3),
    hit: wp.array(dtype=wp.uint8),
    count: int,
    tmax: float,
    centres: wp.array(dtype=wp.vec3),
    radii: wp.array(dtype=float),
    spheres: int,
    out: wp.array(dtype=wp.uint32),
):
    # One thread per point (its `count` rays share an origin): per ray not hit yet, bit s % 32 set for each
    # sphere s its segment o + t d, t in [0, tmax], comes within radii[s] of (embree.segments_reach_sphere,
    # whose numpy form is the reference); a sphere out of the point's reach is skipped for all its rays.
    i = wp.tid()
    o = origins[i * count]
    for k in range(count):
        out[i * count + k] = wp.uint32(0)
    for s in range(spheres):
        c = centres[s] - o
        r = radii[s]
        reach = tmax + r
        if wp.dot(c, c) <= reach * reach:
            bit = wp.uint32(1) << wp.uint32(s % 32)
            for k in range(count):
                j = i * count + k
                if hit[j] == wp.uint8(0):
                    d = dirs[j]
                    t = wp.clamp(wp.dot(d, c) / wp.max(wp.dot(d, d), 1e-30), 0.0, tmax)
                    g = c - d * t
                    if wp.dot(g, g) <= r * r:
                        out[j] = out[j] | bit


def spheres_reached(origins: np.ndarray, dirs: np.ndarray, hit: np.ndarray, rays_per_point: int, tmax: float,
                    centres: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """(R,) uint32: per ray (runs of `rays_per_point` sharing an origin) not `hit` yet, bit s % 32 for each
    sphere s (centres (S, 3), radii (S,), already grown by any slack) its segment reaches; 0 for hit rays.
    (One-off buffers; a thread that asks again and again keeps a RayBuffers and calls its `reached`.)"""
    return RayBuffers().reached(origins, dirs, hit, rays_per_point, tmax, centres, radii)


def _grown(held: "wp.array | None", n: int, dtype) -> "wp.array":
    """`held` when it has room for n entries, else a new Warp array (CPU) of at least n (and 1)."""
    return held if held is not None and held.shape[0] >= n else wp.empty(max(n, 1), dtype=dtype, device="cpu")


class RayBuffers:
    """Ray buffers allocated once and grown on demand, with the kernels' launches recorded on them: a
    call copies its inputs in and replays the launch (a launch's argument packing and the Warp array
    wrappers of its inputs cost more than the kernels themselves at a tick's few thousand rays). CPU."""

    def __init__(self, device: str = "cpu"):
        self.device = device
        self.ray_capacity = 0
        self.point_capacity = 0
        self._rays_launch = None  # rays_kernel recorded on the buffers (made again when they are replaced)
        self._reach: dict[str, wp.array] = {}  # reach_kernel's buffers
        self._reach_launch = None

    def _ensure(self, points: int, count: int, rays: int) -> None:
        if points * count > self.ray_capacity:
            self.ray_capacity = points * count
            self.origins = wp.empty(self.ray_capacity, dtype=wp.vec3, device=self.device)
            self.dirs = wp.empty(self.ray_capacity, dtype=wp.vec3, device=self.device)
            self._rays_launch = None
        if getattr(self, "phase_rays", None) != rays:
            j = np.arange(rays, dtype=np.float64)
            angle = 2.0 * np.pi * np.mod(j * GOLDEN, 1.0)
            self.phase = wp.array(np.stack([np.cos(angle), np.sin(angle)], axis=1).astype(np.float32),
                                  dtype=wp.vec2, device=self.device)
            self.phase_rays = rays
            self._rays_launch = None
        if points > self.point_capacity:
            self.point_capacity = points
            self.positions = wp.empty(points, dtype=wp.vec3, device=self.device)
            self.normals = wp.empty(points, dtype=wp.vec3, device=self.device)
            self.rot_a = wp.empty(points, dtype=float, device=self.device)
            self.rot_b = wp.empty(points, dtype=float, device=self.device)
            self.first = wp.empty(points, dtype=int, device=self.device)
            self._rays_launch = None

    def rays(self, positions, normals, rot_a, rot_b, rays: int, ao_distance: float, first=0, step: int = 1):
        """(origins, directions), each (P * K', 3) float32 numpy views valid until the next call: the slice
        j = first, first + step, ... (K' rays) of each point's K-ray set (`first`: one int, or one per point
        with `step` dividing `rays`)."""
        p = len(normals)
        count = slice_count(first, rays, step)
        self._ensure(p, count, rays)
        self.positions.numpy()[:p] = positions
        self.normals.numpy()[:p] = normals
        self.rot_a.numpy()[:p] = rot_a
        self.rot_b.numpy()[:p] = rot_b
        self.first.numpy()[:p] = first
        if p:
            inputs = [self.positions, self.normals, self.rot_a, self.rot_b, self.phase, rays, self.first, step, count,
                      float(ao_distance), float(OFFSET_REL), float(OFFSET_AO)]
            if self._rays_launch is None:
                self._rays_launch = wp.launch(rays_kernel, dim=p, inputs=inputs, outputs=[self.origins, self.dirs],
                                              device=self.device, record_cmd=True)
            _replay(self._rays_launch, p, {5: rays, 7: step, 8: count, 9: float(ao_distance)})
        n = p * count
        return (self.origins.numpy()[:n].view(dtype="float32").reshape(-1, 3),
                self.dirs.numpy()[:n].view(dtype="float32").reshape(-1, 3))

    def reached(self, origins: np.ndarray, dirs: np.ndarray, hit: np.ndarray, rays_per_point: int, tmax: float,
                centres: np.ndarray, radii: np.ndarray) -> np.ndarray:
        """spheres_reached through reach_kernel recorded on this object's buffers (a new array each call)."""
        n, spheres = len(origins), len(radii)
        out = np.empty(n, np.uint32)
        if n == 0:
            return out
        b = self._reach
        sizes = {"origins": (n, wp.vec3), "dirs": (n, wp.vec3), "hit": (n, wp.uint8), "out": (n, wp.uint32),
                 "centres": (spheres, wp.vec3), "radii": (spheres, float)}
        for name, (size, dtype) in sizes.items():
            grown = _grown(b.get(name), size, dtype)
            if grown is not b.get(name):
                b[name] = grown
                self._reach_launch = None
        b["origins"].numpy()[:n] = origins
        b["dirs"].numpy()[:n] = dirs
        b["hit"].numpy()[:n] = np.asarray(hit).view(np.uint8)
        b["centres"].numpy()[:spheres] = centres
        b["radii"].numpy()[:spheres] = radii
        points = n // rays_per_point
        if self._reach_launch is None:
            self._reach_launch = wp.launch(reach_kernel, dim=points, device="cpu", record_cmd=True, inputs=[
                b["origins"], b["dirs"], b["hit"], int(rays_per_point), float(tmax), b["centres"], b["radii"],
                spheres, b["out"]])
        _replay(self._reach_launch, points, {3: int(rays_per_point), 4: float(tmax), 7: spheres})
        out[:] = b["out"].numpy()[:n]
        return out


def _replay(launch, dim: int, scalars: dict[int, int | float]) -> None:
    """Run a recorded launch over `dim` threads with its scalar arguments (by index) set anew."""
    launch.set_dim(dim)
    for index, value in scalars.items():
        launch.set_param_at_index(index, value)
    launch.launch()
