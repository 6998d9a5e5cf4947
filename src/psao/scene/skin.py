"""Skinned meshes: per-vertex joints and weights, inverse bind matrices and the joint animators.

Mesh.skin is a Skin: per-vertex joints and weights for Mesh.vertices (same order), inverse bind
matrices, and an animator giving the joint matrices at time t in the mesh's local space; a skinned
vertex is sum_k w_k * (joint_matrices(t)[j_k] @ inverse_bind[j_k]) @ v, then the instance transform
(identity for glTF skins, whose joints are already in the file's world space). Reading skins from glTF
is gltf_skin.py; deforming vertices on the device is skinning.py.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from psao.scene.errors import SceneFormatError
from psao.scene.transforms import quat_to_matrix, slerp

log = logging.getLogger("psao.scene")

MAX_JOINTS = 256  # joints per skin: the Warp kernel and the wire format index joints with 8 bits


class JointAnimator(Protocol):
    def joint_matrices(self, t: float) -> np.ndarray:
        """(J, 4, 4) joint matrices at time t in the skinned mesh's local space."""


@dataclass
class Skin:
    inverse_bind: np.ndarray  # (J, 4, 4) float64
    joints: np.ndarray  # (V, 4) int64, per vertex of Mesh.vertices, index into the J joints
    weights: np.ndarray  # (V, 4) float64, each row sums to 1
    animator: JointAnimator
    joint_names: list[str] = field(default_factory=list)

    @property
    def joint_count(self) -> int:
        return len(self.inverse_bind)

    def joint_matrices(self, t: float) -> np.ndarray:
        return self.animator.joint_matrices(float(t))

    def skinning_matrices(self, t: float) -> np.ndarray:
        """(J, 4, 4) matrices applied to rest-pose vertices: joint_matrices(t) @ inverse_bind."""
        return self.joint_matrices(t) @ self.inverse_bind


def skinning_matrices_of(skins: list[Skin], t: float) -> np.ndarray:
    """(sum of J, 4, 4) Skin.skinning_matrices of several skins at time t, concatenated in their order: the
    joint matrices of animators with equal `batch_key` in one batched call (their class's joint_matrices_of),
    an animator shared by several skins once, then one stacked product with the inverse binds."""
    animators = list({id(s.animator): s.animator for s in skins}.values())
    groups: dict = {}
    for a in animators:
        groups.setdefault(getattr(a, "batch_key", id(a)), []).append(a)
    joints = {}
    for group in groups.values():
        posed = (type(group[0]).joint_matrices_of(group, float(t)) if hasattr(group[0], "batch_key")
                 else [group[0].joint_matrices(float(t))])
        joints.update({id(a): m for a, m in zip(group, posed)})
    return np.concatenate([joints[id(s.animator)] for s in skins]) @ np.concatenate([s.inverse_bind for s in skins])


def check_skin(joints: np.ndarray, weights: np.ndarray, joint_count: int,
               where: str) -> tuple[np.ndarray, np.ndarray]:
    """Validate per-vertex skin data; returns joints (unused slots set to joint 0, so every index is
    valid) and weights normalised to sum 1 per vertex."""
    if joint_count > MAX_JOINTS:
        raise SceneFormatError(f"{where}: {joint_count} joints, more than the {MAX_JOINTS} supported")
    if joint_count == 0:
        raise SceneFormatError(f"{where}: skin has no joints")
    if joints.shape != weights.shape or joints.shape[1:] != (4,):
        raise SceneFormatError(f"{where}: joints and weights must both be (V, 4)")
    if not np.isfinite(weights).all() or (weights < 0).any():
        raise SceneFormatError(f"{where}: weights must be finite and >= 0")
    used = weights > 0
    if (joints[used] < 0).any() or (joints[used] >= joint_count).any():
        raise SceneFormatError(f"{where}: a vertex refers to a joint outside 0..{joint_count - 1}")
    total = weights.sum(axis=1, keepdims=True)
    if (total <= 0).any():
        raise SceneFormatError(f"{where}: {int((total <= 0).sum())} vertices have all weights zero")
    return np.where(used, joints, 0).astype(np.int64), weights / total


@dataclass
class Channel:
    node: int | np.ndarray  # a node, or (G,) nodes animated alike (merge_channels)
    path: str  # "translation" | "rotation" | "scale"
    times: np.ndarray  # (K,) strictly increasing
    values: np.ndarray  # (K, C), (K, G, C) for G nodes, or (K, 3, C) for CUBICSPLINE (in-tangent, value, out-tangent)
    interpolation: str  # "LINEAR" | "STEP" | "CUBICSPLINE"

    def sample(self, t: float) -> np.ndarray:
        times, k = self.times, len(self.times)
        if k == 1 or t <= times[0]:
            return self._value(0)
        if t >= times[-1]:
            return self._value(k - 1)
        i = int(np.searchsorted(times, t, side="right") - 1)
        if self.interpolation == "STEP":
            return self._value(i)
        dt = times[i + 1] - times[i]
        u = (t - times[i]) / dt
        if self.interpolation == "CUBICSPLINE":
            p0, m0 = self.values[i, 1], self.values[i, 2] * dt
            p1, m1 = self.values[i + 1, 1], self.values[i + 1, 0] * dt
            v = ((2 * u**3 - 3 * u**2 + 1) * p0 + (u**3 - 2 * u**2 + u) * m0
                 + (-2 * u**3 + 3 * u**2) * p1 + (u**3 - u**2) * m1)
            return v / np.linalg.norm(v) if self.path == "rotation" else v
        a, b = self.values[i], self.values[i + 1]
        return slerp(a, b, u) if self.path == "rotation" else a + (b - a) * u

    def _value(self, i: int) -> np.ndarray:
        return self.values[i, 1] if self.interpolation == "CUBICSPLINE" else self.values[i]


def merge_channels(channels: list[Channel]) -> list[Channel]:
    """The same channels with those of one path, one LINEAR or STEP interpolation and equal key times merged
    into one channel of several nodes, sampled in one pass (a glTF skin's joints usually share their
    keys); the values are the very numbers the channels give one by one."""
    groups: dict[tuple, list[Channel]] = {}
    out = []
    for c in channels:
        if c.interpolation == "CUBICSPLINE" or np.ndim(c.node):
            out.append(c)
        else:
            groups.setdefault((c.path, c.interpolation, c.times.tobytes()), []).append(c)
    for (path, interpolation, _), cs in groups.items():
        out.append(Channel(np.array([c.node for c in cs]), path, cs[0].times, np.stack([c.values for c in cs], axis=1),
                           interpolation))
    return out


@dataclass
class NodeAnimator:
    """Joint matrices from a node hierarchy: rest TRS per node, animated by channels, looping.
    Works for glTF skins and for the procedural ones alike (parents as indices, -1 for roots)."""
    parents: np.ndarray  # (N,) int, parents before children
    rest_translation: np.ndarray  # (N, 3)
    rest_rotation: np.ndarray  # (N, 4) (x, y, z, w)
    rest_scale: np.ndarray  # (N, 3)
    rest_matrix: list  # per node: a fixed (4, 4) local matrix (glTF `matrix` nodes) or None
    joint_nodes: np.ndarray  # (J,) node index of each joint
    channels: list[Channel]
    duration: float  # seconds; time loops with this period (0: static)
    root: np.ndarray = field(default_factory=lambda: np.eye(4))  # applied above the root nodes

    def __post_init__(self):
        self.order = hierarchy_order(self.parents, self.joint_nodes)
        self._merged_of: list | None = None  # the channel list _merged was made from

    def _sampled(self) -> tuple[list[Channel], list[int]]:
        """The channels merged for sampling and the nodes whose fixed matrix stands (no channel moves
        them), worked out again only when `channels` is another list."""
        if self._merged_of is not self.channels:
            animated = {int(n) for c in self.channels for n in np.atleast_1d(c.node)}
            self._merged = merge_channels(self.channels), [n for n, fixed in enumerate(self.rest_matrix)
                                                            if fixed is not None and n not in animated]
            self._merged_of = self.channels
        return self._merged

    def local_matrices(self, t: float) -> np.ndarray:
        t = t % self.duration if self.duration > 0 else 0.0
        tr, rot, sc = self.rest_translation.copy(), self.rest_rotation.copy(), self.rest_scale.copy()
        channels, fixed = self._sampled()
        for c in channels:
            v = c.sample(t)
            {"translation": tr, "rotation": rot, "scale": sc}[c.path][c.node] = v
        m = np.zeros((len(tr), 4, 4))
        m[:, :3, :3] = quat_to_matrix(rot) * sc[:, None, :]
        m[:, :3, 3] = tr
        m[:, 3, 3] = 1.0
        for n in fixed:
            m[n] = self.rest_matrix[n]
        return m

    def rest_joint_matrices(self) -> np.ndarray:
        """(J, 4, 4) joint matrices of the rest pose (node TRS without any animation)."""
        channels, self.channels = self.channels, []
        try:
            return self.joint_matrices(0.0)
        finally:
            self.channels = channels

    def joint_matrices(self, t: float) -> np.ndarray:
        return compose_hierarchy(self.local_matrices(t), self.order, self.root)[self.joint_nodes]


def hierarchy_order(parents: np.ndarray, needed=None) -> list[tuple[int, int]]:
    """(node, parent) of a hierarchy's nodes (parents as indices, -1 for roots), every parent before its
    children; with `needed`, only those nodes and their ancestors."""
    keep = np.zeros(len(parents), bool)
    for n in range(len(parents)) if needed is None else np.asarray(needed, np.int64).tolist():
        while n >= 0 and not keep[n]:
            keep[n] = True
            n = int(parents[n])
    return [(n, int(parents[n])) for n in topological_order(parents) if keep[n]]


def compose_hierarchy(local: np.ndarray, order: list[tuple[int, int]], root: np.ndarray) -> np.ndarray:
    """World matrices (..., N, 4, 4) of a hierarchy's nodes from their local ones (..., N, 4, 4): root @ local
    for a root, its parent's world @ local below, in `order` (hierarchy_order; nodes left out of it stay
    undefined). Leading axes are separate hierarchies of the same shape, composed together. A node at a
    time: numpy gathers stacked 4 x 4 matrices by index arrays several times slower than one product."""
    world = np.empty_like(local)
    for n, p in order:
        world[..., n, :, :] = (root if p < 0 else world[..., p, :, :]) @ local[..., n, :, :]
    return world


def topological_order(parents: np.ndarray) -> list[int]:
    """Node indices with every parent before its children."""
    children: dict[int, list[int]] = {}
    for n, p in enumerate(parents):
        children.setdefault(int(p), []).append(n)
    order, stack = [], list(reversed(children.get(-1, [])))
    while stack:
        n = stack.pop()
        order.append(n)
        stack.extend(reversed(children.get(n, [])))
    return order


@dataclass
class TimeShift:
    """Another animator, `offset` seconds ahead: several characters from one file out of step."""
    inner: JointAnimator
    offset: float  # seconds

    @property
    def duration(self) -> float:
        return getattr(self.inner, "duration", 0.0)

    def joint_matrices(self, t: float) -> np.ndarray:
        return self.inner.joint_matrices(t + self.offset)

    def rest_joint_matrices(self) -> np.ndarray:
        return self.inner.rest_joint_matrices()


# A glTF mesh's vertices are in bind space; when every joint's rest-pose matrix times its inverse bind
# matrix is the same B (the file was bound in its rest pose, the usual case), B @ v is the rest pose in
# the file's world space. Storing that as Mesh.vertices (and inverse_bind @ B^-1) gives static
# consumers (bounds, bakes, the rasteriser) the right geometry and leaves the skinned result unchanged.
REST_POSE_TOLERANCE = 1e-4  # max |B_k - B_0| relative to |B_0|, float32 files reach about 1e-5


def rebase_to_rest_pose(mesh) -> bool:
    """Move a skinned mesh from bind space to its rest pose (see above); False when joints disagree."""
    skin = mesh.skin
    b = skin.animator.rest_joint_matrices() @ skin.inverse_bind
    if np.abs(b - b[0]).max() > REST_POSE_TOLERANCE * max(1.0, np.abs(b[0]).max()):
        log.warning("%s: skin bound away from its rest pose: vertices stay in bind space", mesh.name)
        return False
    b0 = b[0]
    if abs(np.linalg.det(b0[:3, :3])) < 1e-12:
        return False
    mesh.vertices = mesh.vertices @ b0[:3, :3].T + b0[:3, 3]
    if np.linalg.det(b0[:3, :3]) < 0:
        mesh.faces = mesh.faces[:, ::-1].copy()
    skin.inverse_bind = skin.inverse_bind @ np.linalg.inv(b0)
    return True
