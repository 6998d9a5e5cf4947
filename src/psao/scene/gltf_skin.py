"""Skins and joint animations read from glTF (pygltflib documents wrapped by meshfile's reader)."""
from __future__ import annotations

import numpy as np

from psao.scene.errors import SceneFormatError
from psao.scene.skin import MAX_JOINTS, Channel, NodeAnimator, Skin, check_skin

def skin_from_gltf(g, skin_index: int, joints: np.ndarray, weights: np.ndarray, animation: int | str = 0) -> Skin:
    """The Skin of glTF skin `skin_index` for a mesh's (V, 4) joints/weights (already in Mesh.vertices
    order), animated by glTF animation `animation`, an index or a name (static when the file has none)."""
    doc = g.doc
    skin = doc.skins[skin_index]
    name = skin.name or f"skin{skin_index}"
    where = f"{g.path}: skin '{name}'"
    joint_nodes = np.asarray(skin.joints or [], dtype=np.int64)
    if len(joint_nodes) > MAX_JOINTS:
        raise SceneFormatError(f"{where}: {len(joint_nodes)} joints, more than the {MAX_JOINTS} supported")
    if len(joint_nodes) and (joint_nodes.min() < 0 or joint_nodes.max() >= len(doc.nodes)):
        raise SceneFormatError(f"{where}: a joint refers to a missing node")
    if len(np.unique(joint_nodes)) != len(joint_nodes):
        twice = int(next(j for k, j in enumerate(joint_nodes) if j in joint_nodes[:k]))
        raise SceneFormatError(f"{where}: node {twice} is listed twice among its joints")
    joints, weights = check_skin(joints, weights, len(joint_nodes), where)
    if skin.inverseBindMatrices is not None:
        ibm = g.accessor(skin.inverseBindMatrices, f"skin '{name}' inverseBindMatrices").astype(np.float64)
        if len(ibm) != len(joint_nodes) or not np.isfinite(ibm).all():
            raise SceneFormatError(f"{where}: inverseBindMatrices must be {len(joint_nodes)} finite matrices")
        ibm = ibm.reshape(-1, 4, 4).transpose(0, 2, 1)  # column-major in the file
    else:
        ibm = np.tile(np.eye(4), (len(joint_nodes), 1, 1))
    animator = gltf_node_animator(g, joint_nodes, gltf_animation_index(g, animation))
    names = [doc.nodes[j].name or f"node{j}" for j in joint_nodes]
    return Skin(inverse_bind=ibm, joints=joints, weights=weights, animator=animator, joint_names=names)


def node_skin_from_gltf(g, node: int, vertex_count: int, animation: int | str = 0) -> Skin:
    """A one-joint Skin on glTF node `node` for a mesh of `vertex_count` vertices in that node's local space
    (inverse bind identity, every vertex weighted 1 to it): the mesh follows the node as animation
    `animation` moves it, rigidly."""
    joint_nodes = np.array([node], dtype=np.int64)
    animator = gltf_node_animator(g, joint_nodes, gltf_animation_index(g, animation))
    weights = np.zeros((vertex_count, 4))
    weights[:, 0] = 1.0
    return Skin(inverse_bind=np.eye(4)[None], joints=np.zeros((vertex_count, 4), np.int64), weights=weights,
                animator=animator, joint_names=[g.doc.nodes[node].name or f"node{node}"])


def animated_nodes(g, animation: int | str = 0) -> set[int]:
    """The nodes glTF animation `animation` (index or name) moves: those its translation, rotation or scale
    channels target, and their descendants (empty when the file has no animation)."""
    index = gltf_animation_index(g, animation)
    if index < 0:
        return set()
    nodes = g.doc.nodes
    moved, stack = set(), []
    for ch in g.doc.animations[index].channels or []:
        target = ch.target
        if target is not None and target.path in _CHANNEL_WIDTH and isinstance(target.node, int):
            stack.append(target.node)
    while stack:
        n = stack.pop()
        if n in moved or not 0 <= n < len(nodes):
            continue
        moved.add(n)
        stack.extend(nodes[n].children or [])
    return moved


def gltf_animation_index(g, animation: int | str) -> int:
    """Index of a glTF animation given by index or name; -1 (static) when the file has none."""
    anims = g.doc.animations or []
    names = [a.name or f"animation{k}" for k, a in enumerate(anims)]
    if isinstance(animation, str):
        if animation not in names:
            raise SceneFormatError(f"{g.path}: no animation '{animation}' (has: {', '.join(names) or 'none'})")
        return names.index(animation)
    if not anims and animation == 0:
        return -1
    if not 0 <= animation < len(anims):
        raise SceneFormatError(f"{g.path}: no animation {animation} (has {len(anims)})")
    return int(animation)


def gltf_node_animator(g, joint_nodes: np.ndarray, animation: int) -> NodeAnimator:
    doc = g.doc
    n = len(doc.nodes)
    parents = np.full(n, -1, dtype=np.int64)
    for i, node in enumerate(doc.nodes):
        for c in node.children or []:
            if not 0 <= c < n:
                raise SceneFormatError(f"{g.path}: node {i} has a missing child {c}")
            parents[c] = i
    tr, rot, sc, fixed = np.zeros((n, 3)), np.tile([0.0, 0, 0, 1], (n, 1)), np.ones((n, 3)), [None] * n
    for i, node in enumerate(doc.nodes):
        if node.matrix is not None and len(node.matrix) == 16:
            fixed[i] = np.asarray(node.matrix, dtype=np.float64).reshape(4, 4).T
        tr[i] = node.translation if node.translation is not None else 0.0
        rot[i] = node.rotation if node.rotation is not None else [0, 0, 0, 1]
        sc[i] = node.scale if node.scale is not None else 1.0
    channels: list[Channel] = []
    duration = 0.0
    if doc.animations and 0 <= animation < len(doc.animations):
        channels, duration = gltf_channels(g, animation)
    return NodeAnimator(parents=parents, rest_translation=tr, rest_rotation=rot, rest_scale=sc, rest_matrix=fixed,
                        joint_nodes=joint_nodes, channels=channels, duration=duration)


_CHANNEL_WIDTH = {"translation": 3, "rotation": 4, "scale": 3}


def gltf_channels(g, animation: int) -> tuple[list[Channel], float]:
    """Channels of glTF animation `animation` that drive TRS, validated; and its duration."""
    doc = g.doc
    anim = doc.animations[animation]
    aname = anim.name or f"animation{animation}"
    out, duration = [], 0.0
    for ci, ch in enumerate(anim.channels):
        where = f"{g.path}: animation '{aname}' channel {ci}"
        target = ch.target
        if target is None or target.node is None or not 0 <= target.node < len(doc.nodes):
            raise SceneFormatError(f"{where}: targets a missing node {getattr(target, 'node', None)}")
        if target.path not in _CHANNEL_WIDTH:
            continue  # morph target weights: not supported, and they do not move joints
        if ch.sampler is None or not 0 <= ch.sampler < len(anim.samplers):
            raise SceneFormatError(f"{where}: refers to a missing sampler {ch.sampler}")
        sampler = anim.samplers[ch.sampler]
        interp = sampler.interpolation or "LINEAR"
        if interp not in ("LINEAR", "STEP", "CUBICSPLINE"):
            raise SceneFormatError(f"{where}: unknown interpolation '{interp}'")
        times = g.accessor(sampler.input, where).reshape(-1).astype(np.float64)
        values = g.accessor(sampler.output, where).astype(np.float64)
        width = _CHANNEL_WIDTH[target.path]
        per_key = 3 if interp == "CUBICSPLINE" else 1
        if values.size != len(times) * per_key * width:
            raise SceneFormatError(f"{where}: {values.size} output values for {len(times)} keyframes")
        values = values.reshape(len(times), per_key, width) if per_key == 3 else values.reshape(len(times), width)
        if len(times) == 0 or not np.isfinite(times).all() or not np.isfinite(values).all():
            raise SceneFormatError(f"{where}: keyframes are empty or not finite")
        if (np.diff(times) <= 0).any():
            raise SceneFormatError(f"{where}: keyframe times are not strictly increasing")
        out.append(Channel(target.node, target.path, times, values, interp))
        duration = max(duration, float(times[-1]))
    return out, duration
