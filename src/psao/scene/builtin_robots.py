"""`builtin:robots`: a lab room with several procedural skinned robots walking their rounds.

Each robot is a mesh with a Skin (11 joints: pelvis, chest, head, hips, knees, shoulders, elbows;
smooth weights across the knees, elbows and waist, so the surface really deforms) driven by a
procedural walk cycle, and an instance moved along a closed or back-and-forth path (RigidAnimation
kind "path"). Every robot has its own mesh so that each walks with its own phase. Metres; the robot
faces +Z in its model space and stands on y = 0.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from psao.scene import builtin_shapes as shapes
from psao.scene.meshfile import clean_geometry
from psao.scene.model import Mesh, Scene
from psao.scene.rigid import PathAnimation, Polyline
from psao.scene.scene_builder import SceneBuilder
from psao.scene.skin import Skin, compose_hierarchy, hierarchy_order
from psao.scene.transforms import trs

# (name, parent, rest position in model space)
SKELETON = (
    ("pelvis", -1, (0.0, 0.90, 0.0)),
    ("chest", 0, (0.0, 1.15, 0.0)),
    ("head", 1, (0.0, 1.45, 0.0)),
    ("hip_l", 0, (0.10, 0.88, 0.0)),
    ("knee_l", 3, (0.10, 0.48, 0.0)),
    ("hip_r", 0, (-0.10, 0.88, 0.0)),
    ("knee_r", 5, (-0.10, 0.48, 0.0)),
    ("shoulder_l", 1, (0.27, 1.38, 0.0)),
    ("elbow_l", 7, (0.27, 1.10, 0.0)),
    ("shoulder_r", 1, (-0.27, 1.38, 0.0)),
    ("elbow_r", 9, (-0.27, 1.10, 0.0)),
)
JOINT = {name: k for k, (name, _, _) in enumerate(SKELETON)}
STRIDE_PER_CYCLE = 1.3  # metres the body advances per walk cycle (two steps) at these swing angles


@dataclass
class WalkCycle:
    """Joint matrices of a walking robot at time t: legs and arms swing in opposition, knees bend on
    the forward swing, the pelvis bobs twice per cycle and the chest counter-twists."""
    frequency: float  # walk cycles per second
    phase: float = 0.0  # radians
    hip_swing: float = math.radians(28)
    knee_bend: float = math.radians(45)
    arm_swing: float = math.radians(25)
    parents: np.ndarray = field(default_factory=lambda: np.array([p for _, p, _ in SKELETON]))
    rest: np.ndarray = field(default_factory=lambda: np.array([pos for _, _, pos in SKELETON]))

    @property
    def duration(self) -> float:
        """Seconds of one walk cycle: the joint matrices repeat with this period."""
        return 1.0 / self.frequency

    def __post_init__(self):
        self.order = hierarchy_order(self.parents)
        self.offsets = np.array([self.rest[k] - (self.rest[p] if p >= 0 else 0.0)
                                 for k, p in enumerate(self.parents)])

    @property
    def batch_key(self) -> tuple:
        """Walk cycles with equal keys are posed together by joint_matrices_of."""
        return type(self), self.parents.tobytes()

    def joint_matrices(self, t: float) -> np.ndarray:
        return self.joint_matrices_of([self], t)[0]

    @staticmethod
    def joint_matrices_of(walks: list["WalkCycle"], t: float) -> np.ndarray:
        """(len(walks), J, 4, 4) joint matrices of several walk cycles at time t, in one batched pass (a
        scene of many walkers poses them all each tick; walks of one batch_key, the same joint tree): legs and arms swing in opposition,
        knees bend on the forward swing, the pelvis bobs twice per cycle and the chest counter-twists. A
        positive angle about x swings a limb backwards."""
        w = walks[0]
        frequency, phase, hip, knee, arm = (np.array([getattr(v, a) for v in walks], np.float64) for a in
                                            ("frequency", "phase", "hip_swing", "knee_bend", "arm_swing"))
        phi = 2 * np.pi * frequency * t + phase
        s, c = np.sin(phi), np.cos(phi)
        local = np.zeros((len(walks), len(w.parents), 4, 4))
        local[..., [0, 1, 2, 3], [0, 1, 2, 3]] = 1.0
        local[..., :3, 3] = np.stack([v.offsets for v in walks])
        local[:, w.parents < 0, 1, 3] += (0.03 * np.cos(2 * phi))[:, None]
        about_x = {"hip_l": -hip * s, "hip_r": hip * s, "knee_l": knee * np.maximum(0.0, -c),
                   "knee_r": knee * np.maximum(0.0, c), "shoulder_l": arm * s, "shoulder_r": -arm * s,
                   "elbow_l": -0.35 - 0.25 * np.maximum(0.0, s), "elbow_r": -0.35 - 0.25 * np.maximum(0.0, -s)}
        for joints, angles, (i, j) in ((list(about_x), np.stack(list(about_x.values()), 1), (1, 2)),  # y to z
                                       (["chest"], (0.12 * s)[:, None], (2, 0))):  # about y: z to x
            k = [JOINT[n] for n in joints]
            cos, sin = np.cos(angles), np.sin(angles)
            local[:, k, i, i] = local[:, k, j, j] = cos
            local[:, k, j, i], local[:, k, i, j] = sin, -sin
        return compose_hierarchy(local, w.order, np.eye(4))


def _smoothstep(a: float, b: float, x: np.ndarray) -> np.ndarray:
    u = np.clip((x - a) / (b - a), 0.0, 1.0)
    return u * u * (3 - 2 * u)


def two_joint(v: np.ndarray, upper: int, lower: int, y_from: float, y_to: float) -> tuple[np.ndarray, np.ndarray]:
    """Joints/weights blending from `upper` (above y_to) to `lower` (below y_from) across [y_from, y_to]."""
    w_upper = _smoothstep(y_from, y_to, v[:, 1])
    j = np.zeros((len(v), 4), dtype=np.int64)
    w = np.zeros((len(v), 4))
    j[:, 0], j[:, 1] = upper, lower
    w[:, 0], w[:, 1] = w_upper, 1 - w_upper
    return j, w


def robot_parts() -> list[tuple[shapes.Geometry, np.ndarray, np.ndarray]]:
    """(geometry, joints, weights) of each body part in the rest pose."""
    parts = []

    def add(geom, upper, lower=None, y_from=0.0, y_to=1.0):
        v, f = geom
        jw = two_joint(v, upper, upper if lower is None else lower, y_from, y_to)
        parts.append(((v, f), *jw))

    add(shapes.transformed(shapes.capsule(0.18, 0.3, count=12), (0, 1.15, 0)), JOINT["chest"], JOINT["pelvis"], 0.95, 1.2)
    add(shapes.transformed(shapes.sphere(0.13, 2), (0, 1.6, 0)), JOINT["head"])
    for side, hip, knee in ((1, "hip_l", "knee_l"), (-1, "hip_r", "knee_r")):
        add(shapes.transformed(shapes.tube(0.075, 0.82, rings=10, sections=12), (0.10 * side, 0.9, 0)),
            JOINT[hip], JOINT[knee], 0.42, 0.54)
        add(shapes.transformed(shapes.box((0.12, 0.07, 0.24)), (0.10 * side, 0.035, 0.04)), JOINT[knee])
    for side, shoulder, elbow in ((1, "shoulder_l", "elbow_l"), (-1, "shoulder_r", "elbow_r")):
        add(shapes.transformed(shapes.tube(0.05, 0.55, rings=8, sections=10), (0.27 * side, 1.4, 0)),
            JOINT[shoulder], JOINT[elbow], 1.04, 1.16)
    return parts


def robot_mesh(name: str, color, walk: WalkCycle) -> Mesh:
    parts = robot_parts()
    (v, f) = shapes.combine([p[0] for p in parts])
    joints = np.concatenate([p[1] for p in parts])
    weights = np.concatenate([p[2] for p in parts])
    # merge=False: the parts overlap but stay separate surfaces, each with its own weights
    r = clean_geometry(v, f, f"builtin:robots: mesh '{name}'", merge=False)
    inverse_bind = np.tile(np.eye(4), (len(SKELETON), 1, 1))
    inverse_bind[:, :3, 3] = -walk.rest  # bind pose = rest pose: joints are pure translations
    skin = Skin(inverse_bind=inverse_bind, joints=joints[r.source_vertex], weights=weights[r.source_vertex],
                animator=walk, joint_names=[n for n, _, _ in SKELETON])
    return Mesh(name=name, vertices=r.vertices, faces=r.faces, color=tuple(color), skin=skin)


ROBOTS = (  # (path of (x, z), closed loop (else there and back), speed m/s, colour)
    ([(-2.0, -1.5), (2.0, -1.5), (2.0, 1.5), (-2.0, 1.5)], True, 1.0, (0.8, 0.3, 0.2)),
    ([(-6.0, 3.5), (3.0, 3.5)], False, 1.1, (0.2, 0.5, 0.8)),
    ([(-7.0, -3.5), (-7.0, 2.5)], False, 0.8, (0.85, 0.75, 0.2)),
    ([(4.5, -1.0), (7.0, -1.0), (7.0, 1.2), (4.5, 1.2)], True, 0.9, (0.3, 0.7, 0.35)),
    ([(-5.5, -1.2), (-3.5, -1.2), (-3.5, 1.2), (-5.5, 1.2)], True, 0.7, (0.6, 0.4, 0.75)),
)
ROOM_X, ROOM_Z, ROOM_H, WALL_T = 8.0, 5.0, 4.0, 0.3


def robots() -> Scene:
    b = SceneBuilder("robots")
    wall_c, floor_c, metal = (0.75, 0.75, 0.72), (0.5, 0.5, 0.52), (0.55, 0.57, 0.6)
    b.place("floor", shapes.box((2 * ROOM_X + 2 * WALL_T, 0.2, 2 * ROOM_Z + 2 * WALL_T)), trs((0, -0.1, 0)),
            color=floor_c)
    b.place("ceiling", shapes.box((2 * ROOM_X + 2 * WALL_T, 0.2, 2 * ROOM_Z + 2 * WALL_T)),
            trs((0, ROOM_H + 0.1, 0)), color=wall_c)
    long_wall = b.mesh("long_wall", shapes.box((2 * ROOM_X + 2 * WALL_T, ROOM_H, WALL_T)), color=wall_c)
    short_wall = b.mesh("short_wall", shapes.box((WALL_T, ROOM_H, 2 * ROOM_Z)), color=wall_c)
    for side in (-1, 1):
        b.instance(f"wall_z{side:+d}", long_wall, trs((0, ROOM_H / 2, side * (ROOM_Z + WALL_T / 2))))
        b.instance(f"wall_x{side:+d}", short_wall, trs((side * (ROOM_X + WALL_T / 2), ROOM_H / 2, 0)))
    b.place("pillar", shapes.cylinder(0.4, ROOM_H, sections=24), trs((0, ROOM_H / 2, 0)), color=wall_c)
    bench = b.mesh("workbench", _workbench(), color=metal)
    for k, x in enumerate((-4.0, 4.0)):
        b.instance(f"workbench{k}", bench, trs((x, 0, -3.0)))
    crate = b.mesh("crate", shapes.box((0.9, 0.9, 0.9)), color=(0.6, 0.45, 0.3))
    for k, (x, y, z, yaw) in enumerate(((6.2, 0.45, 3.0, 10), (7.1, 0.45, 3.3, -15), (6.6, 1.35, 3.1, 35))):
        b.instance(f"crate{k}", crate, trs((x, y, z), (0, yaw, 0)))
    shelf = b.mesh("shelf", _shelf(), color=metal)
    for k, x in enumerate((-1.5, 1.5)):
        b.instance(f"shelf{k}", shelf, trs((x, 0, -ROOM_Z + 0.35)))
    for k, (path, closed, speed, color) in enumerate(ROBOTS):
        walk = WalkCycle(frequency=speed / STRIDE_PER_CYCLE, phase=1.3 * k)
        mesh = len(b.meshes)
        b.meshes.append(robot_mesh(f"robot{k}", color, walk))
        pts = np.array([[x, 0.0, z] for x, z in path])
        anim = PathAnimation(base=trs(pts[0]), path=Polyline(pts, closed=closed), speed=speed)
        b.instance(f"robot{k}", mesh, anim.matrix(0.0), animation=anim)
    b.camera("overview", [(0.0, (-7.0, 2.6, 4.4), (0.0, 0.8, -1.0)), (8.0, (0.0, 3.0, 4.6), (0.0, 0.8, -1.5)),
                          (16.0, (7.0, 2.6, 4.4), (0.0, 0.8, -1.0)), (24.0, (0.0, 3.3, 3.5), (0.0, 0.6, -2.0)),
                          (32.0, (-7.0, 2.6, 4.4), (0.0, 0.8, -1.0))], fov_y=70.0)
    return b.build(ao_distance=1.0)


def _workbench() -> shapes.Geometry:
    parts = [shapes.transformed(shapes.box((3.0, 0.08, 1.0)), (0, 0.9, 0))]
    parts += [shapes.transformed(shapes.box((0.08, 0.86, 0.08)), (x, 0.43, z))
              for x in (-1.4, 1.4) for z in (-0.42, 0.42)]
    return shapes.combine(parts)


def _shelf() -> shapes.Geometry:
    parts = [shapes.transformed(shapes.box((2.0, 0.05, 0.5)), (0, y, 0)) for y in (0.3, 1.0, 1.7, 2.4)]
    parts += [shapes.transformed(shapes.box((0.05, 2.45, 0.5)), (x, 1.225, 0)) for x in (-1.0, 1.0)]
    return shapes.combine(parts)
