"""The scene at time t for the server tick: instance transforms, skinned geometry, world bounds, and the
world geometry split into a static part (traced in one Embree scene built once) and a moving part
(rebuilt every tick).

Instances are of three kinds:
    static   no animation and no skin: geometry and points never change
    rigid    a RigidAnimation and no skin: points stay in the instance's local space, only the
             transform changes (the client applies it; no point is re-sent for the motion itself)
    skinned  a mesh with a Skin (possibly also moved rigidly): the mesh deforms; the grid keeps its AO
             points in the mesh's rest pose (the client looks fragments up by their rest-pose place), and
             the tick traces them from where they are on the deformed mesh

Skinned AO points follow their triangles exactly: a posed point is the same barycentric combination of its
triangle's skinned corners (Warp skinning of the mesh vertices, psao.scene.skinning_kernels) as its rest-pose
point is of the rest corners, and its normal is the skinned triangle's normal on the side the point was
generated on. So points stay on the deformed surface, which blending per-point skin weights would not
guarantee, and the client finds a posed fragment's rest-pose place the same way (same triangle, same
barycentrics).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from psao.scene.rigid import instance_transform
from psao.scene.model import Scene
from psao.scene.skinning import SceneSkinner, surface_points
from psao.server.geometry import scene_world_geometry
from psao.server.points.generate import PointSet

@dataclass
class InstanceKinds:
    static: list[int]
    rigid: list[int]
    skinned: list[int]

    @property
    def moving(self) -> list[int]:
        return sorted(self.rigid + self.skinned)


def classify_instances(scene: Scene) -> InstanceKinds:
    kinds = InstanceKinds([], [], [])
    for i, inst in enumerate(scene.instances):
        if scene.meshes[inst.mesh].skin is not None:
            kinds.skinned.append(i)
        elif inst.animation is not None:
            kinds.rigid.append(i)
        else:
            kinds.static.append(i)
    return kinds


@dataclass
class Frame:
    """The moving part of the scene at one time."""
    t: float
    transforms: np.ndarray  # (n_instances, 4, 4) float64 local-to-world
    mesh_vertices: dict[int, np.ndarray]  # skinned mesh index -> (V, 3) mesh-local vertices at t
    bounds: dict[int, tuple[np.ndarray, np.ndarray]]  # moving instance -> world (lo, hi) at t
    spheres: dict[int, tuple[np.ndarray, float]]  # moving instance -> world bounding sphere (centre, radius)
    dynamic_vertices: np.ndarray  # (V, 3) world, all moving instances merged
    dynamic_faces: np.ndarray  # (F, 3) int64
    seconds_skinning: float = 0.0
    skinned_vertices: np.ndarray | None = None  # (V, 3) world, skinned instances merged (None: none)
    skinned_faces: np.ndarray | None = None  # (F, 3) int64
    skinned_parts: list[int] = field(default_factory=list)  # vertices of each skinned instance in skinned_vertices
    posed: np.ndarray | None = None  # (S, 3) the skinned meshes' local vertices at t, merged (mesh_vertices: views)
    layout: "MovingLayout | None" = None  # where each moving instance and skinned mesh sits in the merged arrays


def changed_meshes(frame: Frame, last: Frame | None) -> set[int]:
    """The skinned meshes whose vertices differ between `last` and `frame` (all of frame's without `last`), in
    one comparison of their merged vertices."""
    if last is None or last.posed is None or frame.posed is None or last.posed.shape != frame.posed.shape:
        return set(frame.mesh_vertices)
    if last.posed is frame.posed or not len(frame.posed):
        return set()
    layout = frame.layout
    differs = np.logical_or.reduceat(frame.posed.reshape(-1) != last.posed.reshape(-1), 3 * layout.posed_starts)
    return {m for m, d in zip(layout.skinned_meshes, differs.tolist()) if d}


def affine(points: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """(P, 3) points through a 4x4 transform. einsum, not `@`: OpenBLAS threads on (P, 3) x (3, 3)
    cost ~10x more than the arithmetic when the cores are busy with tracer workers."""
    m = np.asarray(transform, np.float64)
    return np.einsum("pj,ij->pi", np.asarray(points, np.float64), m[:3, :3]) + m[:3, 3]


def to_world_points(transforms: np.ndarray, which: np.ndarray, local_pos: np.ndarray,
                    local_normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """geometry.to_world without BLAS (see affine), each point through its own transform (`which`: per point,
    its index into the (T, 4, 4) `transforms`; each transform's inverse worked out once): positions float64,
    unit normals float32."""
    t = np.asarray(transforms, np.float64)
    m = t[which]  # (P, 4, 4)
    pos = np.einsum("pij,pj->pi", m[:, :3, :3], np.asarray(local_pos, np.float64)) + m[:, :3, 3]
    used, back = np.unique(which, return_inverse=True)
    inverse = np.linalg.inv(t[used][:, :3, :3])[back]
    nrm = np.einsum("pj,pji->pi", np.asarray(local_normal, np.float64), inverse)
    nrm /= np.maximum(np.sqrt(np.einsum("pi,pi->p", nrm, nrm))[:, None], 1e-300)
    return pos, nrm.astype(np.float32)


def world_box(vertices_local: np.ndarray, transform: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact world AABB of local vertices under a 4x4 transform."""
    w = affine(vertices_local, transform)
    return w.min(axis=0), w.max(axis=0)


def bounds_of(world_vertices: np.ndarray) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, float]]:
    """World AABB (lo, hi) and bounding sphere (centre, radius) of world vertices. Worked on the
    coordinates as three rows: numpy reduces a (V, 3) array along its long axis several times slower
    than a (3, V) one along its rows, and this runs for every moving instance every tick."""
    rows = np.ascontiguousarray(np.asarray(world_vertices, np.float64).reshape(-1, 3).T)
    lo, hi = rows.min(axis=1), rows.max(axis=1)
    centre = 0.5 * (lo + hi)
    d = rows - centre[:, None]
    d *= d
    return (lo, hi), (centre, float(np.sqrt((d[0] + d[1] + d[2]).max())))


class SceneAnimator:
    """Evaluates a scene's animation at time t; built once, reused every tick."""

    def __init__(self, scene: Scene, device: str | None = "cpu"):
        self.scene = scene
        self.kinds = classify_instances(scene)
        self.skinner = SceneSkinner(scene, device=device)
        self._rest_transforms = np.array([inst.transform for inst in scene.instances], dtype=np.float64).reshape(-1, 4, 4)
        self.placed: dict[int, np.ndarray] = {}  # instance -> transform a scene edit gave it (replaces its animation)
        self._moving_layout: MovingLayout | None = None

    def place(self, instance: int, transform: np.ndarray) -> bool:
        """A scene edit: instance `instance` is at `transform` (local-to-world) from now on, whatever its
        animation said. A static instance becomes a rigid mover (returns True: the caller moves its
        geometry out of the static part); its bounds before the edit are in `static_bounds`."""
        self.placed[instance] = np.asarray(transform, np.float64).reshape(4, 4)
        if instance not in self.kinds.static:
            return False
        self.kinds.static.remove(instance)
        self.kinds.rigid = sorted(self.kinds.rigid + [instance])
        return True

    # ------------------------------------------------------------------ static part
    def static_geometry(self) -> tuple[np.ndarray, np.ndarray]:
        """World triangles of the static instances (rest transforms), for the tracer's static scene."""
        return scene_world_geometry(self.scene, self.kinds.static)

    def static_bounds(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """World AABB of every static instance."""
        out = {}
        for i in self.kinds.static:
            inst = self.scene.instances[i]
            out[i] = world_box(self.scene.meshes[inst.mesh].vertices, inst.transform)
        return out

    # ------------------------------------------------------------------ moving part
    def transforms(self, t: float) -> np.ndarray:
        """(n, 4, 4) float64 local-to-world transforms at time t."""
        out = self._rest_transforms.copy()
        for i in self.kinds.moving:
            out[i] = self.placed[i] if i in self.placed else instance_transform(self.scene, i, t)
        return out

    def frame(self, t: float, bind_pose: bool = False) -> Frame:
        """The scene at time t; with `bind_pose`, its skinned meshes in their bind pose (as a bake traces
        them) instead of deformed at t."""
        transforms = self.transforms(t)
        layout = self._layout()
        t0 = time.perf_counter()
        posed = layout.bind_pose.copy() if bind_pose else self.skinner.posed(layout.skinned_meshes, t)
        seconds_skinning = time.perf_counter() - t0
        world = layout.world(posed, transforms)
        bounds, spheres = layout.bounds(world)
        sv = np.take(world, layout.skinned_rows, axis=0) if len(layout.skinned_parts) else None
        return Frame(float(t), transforms, {m: posed[rows] for m, rows in layout.mesh_rows.items()}, bounds, spheres,
                     world, layout.faces, seconds_skinning, sv, layout.skinned_faces, list(layout.skinned_parts),
                     posed, layout)

    def _layout(self) -> "MovingLayout":
        """The moving instances' layout in a frame's merged arrays, made again when the kinds change (an edit
        made a static instance move)."""
        if self._moving_layout is None or self._moving_layout.moving != self.kinds.moving:
            self._moving_layout = MovingLayout.of(self.scene, self.kinds)
        return self._moving_layout


@dataclass
class MovingLayout:
    """Where the moving instances' vertices and triangles sit in a Frame's merged arrays (dynamic_vertices:
    the moving instances in order, each its mesh's vertices), and what stays the same every frame: the
    merged faces, the skinned instances' rows, faces and vertex counts, the rigid ones' mesh vertices."""
    moving: list[int]
    starts: np.ndarray  # (n + 1,) each moving instance's first row in dynamic_vertices, and the total
    skinned_meshes: list[int]  # the skinned meshes, as SceneSkinner.posed concatenates them
    mesh_rows: dict[int, slice]  # skinned mesh -> its rows in SceneSkinner.posed's vertices
    posed_starts: np.ndarray  # each skinned mesh's first row there
    bind_pose: np.ndarray  # (S, 3) the skinned meshes' own vertices, concatenated as posed
    rigid_vertices: np.ndarray  # (R, 3) the rigid movers' mesh vertices, concatenated
    sources: list[tuple[bool, int]]  # per moving instance: (skinned, its first row in posed / rigid_vertices)
    faces: np.ndarray  # (F, 3) int64 merged faces (read-only)
    skinned_rows: np.ndarray  # rows of the skinned instances in dynamic_vertices
    skinned_faces: np.ndarray  # (Fs, 3) int64 their faces into those rows (read-only)
    skinned_parts: tuple[int, ...]  # vertices of each skinned instance

    @classmethod
    def of(cls, scene: Scene, kinds: InstanceKinds) -> "MovingLayout":
        moving = list(kinds.moving)
        meshes = [scene.meshes[scene.instances[i].mesh] for i in moving]
        skinned = [i in kinds.skinned for i in moving]
        skinned_meshes = list(dict.fromkeys(scene.instances[i].mesh for i, s in zip(moving, skinned) if s))
        first = _starts([len(scene.meshes[m].vertices) for m in skinned_meshes])
        mesh_rows = {m: slice(int(a), int(b)) for m, a, b in zip(skinned_meshes, first[:-1], first[1:])}
        rigid = [m for m, s in zip(meshes, skinned) if not s]
        rigid_first = _starts([len(m.vertices) for m in rigid])
        rigid_at = iter(rigid_first.tolist())
        sources = [(True, mesh_rows[scene.instances[i].mesh].start) if s else (False, next(rigid_at))
                   for i, s in zip(moving, skinned)]
        starts = _starts([len(m.vertices) for m in meshes])
        skinned_first = _starts([len(m.vertices) for m, s in zip(meshes, skinned) if s])
        return cls(moving, starts, skinned_meshes, mesh_rows, first[:-1],
                   _merged([scene.meshes[m].vertices for m in skinned_meshes], np.float64),
                   _merged([m.vertices for m in rigid], np.float64), sources,
                   _read_only(_merged([m.faces + a for m, a in zip(meshes, starts)], np.int64)),
                   np.concatenate([np.arange(a, b) for a, b, s in zip(starts[:-1], starts[1:], skinned) if s]
                                  or [np.zeros(0, np.int64)]),
                   _read_only(_merged([m.faces + a for m, a in zip([m for m, s in zip(meshes, skinned) if s],
                                                                    skinned_first)], np.int64)),
                   tuple(len(m.vertices) for m, s in zip(meshes, skinned) if s))

    def world(self, posed: np.ndarray, transforms: np.ndarray) -> np.ndarray:
        """(V, 3) dynamic_vertices: each moving instance's mesh vertices (skinned: as posed) through its
        transform (affine's arithmetic, written in place)."""
        world = np.empty((int(self.starts[-1]), 3))
        for k, (i, (skinned, at)) in enumerate(zip(self.moving, self.sources)):
            a, b = int(self.starts[k]), int(self.starts[k + 1])
            m = transforms[i]
            np.einsum("pj,ij->pi", (posed if skinned else self.rigid_vertices)[at:at + b - a], m[:3, :3], out=world[a:b])
            world[a:b] += m[:3, 3]
        return world

    def bounds(self, world: np.ndarray) -> tuple[dict, dict]:
        """bounds_of each moving instance's rows of `world`, all at once: (bounds, spheres) by instance."""
        if not self.moving:
            return {}, {}
        rows = np.ascontiguousarray(world.T)
        at = self.starts[:-1]
        lo, hi = np.minimum.reduceat(rows, at, axis=1), np.maximum.reduceat(rows, at, axis=1)
        centre = 0.5 * (lo + hi)
        d = rows - np.repeat(centre, np.diff(self.starts), axis=1)
        d *= d
        radius = np.sqrt(np.maximum.reduceat(d[0] + d[1] + d[2], at))
        lo, hi, centre = lo.T.copy(), hi.T.copy(), centre.T.copy()
        return ({i: (lo[k], hi[k]) for k, i in enumerate(self.moving)},
                {i: (centre[k], float(radius[k])) for k, i in enumerate(self.moving)})


def _starts(counts: list[int]) -> np.ndarray:
    """(n + 1,) int64 first row of each of n consecutive blocks of `counts` rows, and the total."""
    return np.concatenate([[0], np.cumsum(counts, dtype=np.int64)]).astype(np.int64)


def _merged(arrays: list[np.ndarray], dtype) -> np.ndarray:
    """(sum of rows, 3) `arrays` concatenated (none: no rows)."""
    return np.concatenate(arrays).astype(dtype, copy=False) if arrays else np.zeros((0, 3), dtype)


def _read_only(a: np.ndarray) -> np.ndarray:
    """`a`, no longer writeable: arrays every Frame shares."""
    a.flags.writeable = False
    return a


# ---------------------------------------------------------------------------------- skinned points

@dataclass
class SkinnedPoints:
    """The AO points of one skinned instance, tied to their triangles (from the instance's PointSet)."""
    faces: np.ndarray  # (P,) triangle of each point
    bary: np.ndarray  # (P, 3) float64
    side: np.ndarray  # (P,) +1 / -1: the point's normal along / against its triangle's normal
    rest_normals: np.ndarray = field(repr=False, default=None)  # (P, 3) fallback for degenerate triangles

    @classmethod
    def from_pointset(cls, mesh, ps: PointSet) -> "SkinnedPoints":
        faces = np.asarray(ps.faces, np.int64)
        face_n = mesh.face_normals()[faces]
        side = np.where(np.einsum("ij,ij->i", face_n, ps.normals) >= 0, 1.0, -1.0)
        return cls(faces, np.asarray(ps.barycentrics, np.float64), side, np.asarray(ps.normals, np.float64))

    def follow(self, mesh_faces: np.ndarray, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Local positions (P, 3) float64 and unit normals (P, 3) float32 on the deformed mesh (the mesh's
        faces must be the same every call): Warp's SurfacePoints, valid until the next call."""
        if getattr(self, "_kernel", None) is None:
            from psao.scene.skinning_kernels import SurfacePoints  # (Warp: imported at the first skinned frame)

            self._kernel = SurfacePoints(mesh_faces, self.faces, self.bary, self.side, self.rest_normals)
        return self._kernel.follow(vertices)

    def follow_numpy(self, mesh_faces: np.ndarray, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """follow() in numpy (the reference the kernel is tested against)."""
        pos, n = surface_points(vertices, mesh_faces, self.faces, self.bary)
        ok = np.linalg.norm(n, axis=1) > 0.5  # a triangle skinned flat keeps the point's rest normal
        nrm = np.where(ok[:, None], n * self.side[:, None], self.rest_normals)
        return pos, nrm.astype(np.float32)


class PlacedPoints:
    """The AO points of every skinned instance placed on their deformed triangles together: one SurfacePoints
    over a Frame's merged skinned-mesh vertices (Frame.posed), writing each point's local position and normal
    into the tick's arrays (in place where the instances' ids are one run)."""

    def __init__(self, scene: Scene, points: dict[int, SkinnedPoints], ids_of: list[np.ndarray], layout: MovingLayout):
        insts = list(points)
        meshes = [scene.meshes[scene.instances[i].mesh] for i in insts]
        face_base = np.concatenate([[0], np.cumsum([len(m.faces) for m in meshes])]).astype(np.int64)
        faces = np.concatenate([m.faces + layout.mesh_rows[scene.instances[i].mesh].start for i, m in zip(insts, meshes)]
                               or [np.zeros((0, 3), np.int64)])
        pick = lambda name: np.concatenate([getattr(points[i], name) for i in insts])  # noqa: E731
        from psao.scene.skinning_kernels import SurfacePoints  # (Warp: imported at the first skinned frame)

        self.kernel = SurfacePoints(faces, np.concatenate([points[i].faces + b for i, b in zip(insts, face_base)]),
                                    pick("bary"), pick("side"), pick("rest_normals"))
        ids = np.concatenate([ids_of[i] for i in insts])
        run = len(ids) and np.array_equal(ids, np.arange(ids[0], ids[0] + len(ids)))
        self.rows = slice(int(ids[0]), int(ids[0]) + len(ids)) if run else ids

    def place(self, posed: np.ndarray, local_pos: np.ndarray, local_nrm: np.ndarray) -> None:
        """The points on the skinned meshes with merged vertices `posed` into local_pos / local_nrm."""
        if isinstance(self.rows, slice):
            self.kernel.follow(posed, out=(local_pos[self.rows], local_nrm[self.rows]))
        else:
            local_pos[self.rows], local_nrm[self.rows] = self.kernel.follow(posed)
