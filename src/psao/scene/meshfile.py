"""Mesh files: geometry cleaning, glTF/GLB through pygltflib, OBJ/PLY/STL/OFF through trimesh.

glTF is read with pygltflib (not trimesh) so that vertex order is kept exactly as in the file: skins
(per-vertex joints and weights) index those vertices. Node transforms are kept: one Mesh per glTF mesh
(its primitives concatenated), one Instance per node that uses it, with the node's world transform. A
mesh on a node with a skin is one Mesh per (mesh, skin), placed by its joints (identity transform). A
mesh on a node that the chosen animation moves (the node or an ancestor is a channel's target), a part of
a character hung on a bone, is one Mesh per node with a one-joint skin on that node, so it follows the
animation rigidly. Skins, joints and animations that do not fit together are SceneFormatErrors.

Cleaning (every mesh, whatever its source): faces touching a NaN/inf vertex are dropped, exactly
duplicated vertices are merged, degenerate triangles (repeated index or zero area) are dropped, unused
vertices removed. What was dropped is reported as one log line on stderr; a mesh with nothing left
is a GeometryError naming the file and the mesh.
"""
from __future__ import annotations

import base64
import logging
import struct
import urllib.parse
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from psao.scene.errors import GeometryError, SceneFormatError, SceneNotFound
from psao.scene.gltf_skin import animated_nodes, node_skin_from_gltf, skin_from_gltf
from psao.scene.model import Instance, Mesh
from psao.scene.skin import rebase_to_rest_pose
from psao.scene.transforms import trs_matrix

log = logging.getLogger("psao.scene")

GLTF_EXTENSIONS = (".gltf", ".glb")
TRIMESH_EXTENSIONS = (".obj", ".ply", ".stl", ".off")
MESH_EXTENSIONS = GLTF_EXTENSIONS + TRIMESH_EXTENSIONS

# A triangle is degenerate when its area is below this fraction of the squared bounding-box diagonal
# of its mesh: relative, so that a scene in millimetres and one in kilometres are cleaned alike.
DEGENERATE_AREA_FRACTION = 1e-14


@dataclass
class CleanResult:
    vertices: np.ndarray  # (V', 3) float64
    faces: np.ndarray  # (F', 3) int64
    source_vertex: np.ndarray  # (V',) int64: index of each kept vertex in the input (for per-vertex data)
    dropped_nonfinite: int  # faces dropped because a vertex was NaN/inf
    dropped_degenerate: int  # faces dropped as zero-area or with a repeated index
    merged_vertices: int  # vertices merged into an identical one


def _used_vertices(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """The sorted indices that `faces` use (np.unique(faces), by a mask: indices are bounded by n_vertices)."""
    mask = np.zeros(n_vertices, dtype=bool)
    mask[faces.reshape(-1)] = True
    return np.flatnonzero(mask)


def _unique_rows(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """np.unique(points, axis=0, return_index=True, return_inverse=True) for (n, 3) floats, by one lexsort
    (several times faster on large meshes: np.unique sorts rows as structured records)."""
    order = np.lexsort((points[:, 2], points[:, 1], points[:, 0]))  # stable: a group's first is its lowest index
    ranked = points[order]
    starts = np.ones(len(ranked), dtype=bool)
    starts[1:] = (ranked[1:] != ranked[:-1]).any(axis=1)
    inverse = np.empty(len(points), dtype=np.int64)
    inverse[order] = np.cumsum(starts) - 1
    return ranked[starts], order[starts], inverse


def clean_geometry(vertices, faces, where: str, merge: bool = True) -> CleanResult:
    """Clean one mesh; `where` ("file: mesh 'name'") names it in messages.

    merge=False keeps vertices that share a position apart (skinned meshes whose duplicates may carry
    different joints); degenerate and non-finite faces are dropped either way.
    """
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise GeometryError(f"{where}: face index out of range (0..{len(v) - 1})")
    finite_v = np.isfinite(v).all(axis=1)
    face_ok = finite_v[f].all(axis=1) if f.size else np.zeros(0, dtype=bool)
    dropped_nonfinite = int((~face_ok).sum())
    f = f[face_ok]

    source = np.arange(len(v), dtype=np.int64)
    merged = 0
    if merge and len(f):
        used = _used_vertices(f, len(v))
        uniq, first, inverse = _unique_rows(v[used])
        remap = np.full(len(v), -1, dtype=np.int64)
        remap[used] = inverse.reshape(-1)
        merged = len(used) - len(uniq)
        v, f, source = uniq, remap[f], used[first]

    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area2 = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    finite_pts = v[np.isfinite(v).all(axis=1)]
    diag = float(np.linalg.norm(np.ptp(finite_pts, axis=0))) if len(finite_pts) else 0.0
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    degenerate = repeated | ~(area2 > 2.0 * DEGENERATE_AREA_FRACTION * diag * diag)
    dropped_degenerate = int(degenerate.sum())
    f = f[~degenerate]

    if len(f) == 0:
        raise GeometryError(
            f"{where}: no usable triangles ({dropped_nonfinite} with NaN/inf vertices, "
            f"{dropped_degenerate} degenerate)")
    used = _used_vertices(f, len(v))
    compact = np.full(len(v), -1, dtype=np.int64)
    compact[used] = np.arange(len(used))
    if dropped_nonfinite or dropped_degenerate:
        log.warning("%s: dropped %d triangles with NaN/inf vertices and %d degenerate triangles",
                    where, dropped_nonfinite, dropped_degenerate)
    return CleanResult(v[used], compact[f], source[used], dropped_nonfinite, dropped_degenerate, merged)


def clean_mesh(name: str, vertices, faces, where: str, **mesh_fields) -> Mesh:
    r = clean_geometry(vertices, faces, where)
    return Mesh(name=name, vertices=r.vertices, faces=r.faces, **mesh_fields)


def load_mesh_file(path: Path, animation: int | str = 0) -> tuple[list[Mesh], list[Instance]]:
    """Meshes and instances (world transforms) of one mesh file; `animation` (index or name) picks the
    glTF animation that drives skins."""
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in MESH_EXTENSIONS:
        raise SceneFormatError(
            f"{path}: unsupported mesh format '{ext or '(none)'}' (supported: {', '.join(MESH_EXTENSIONS)})")
    if not path.is_file():
        raise SceneNotFound(f"{path}: mesh file not found")
    check_not_a_stand_in(path)
    if ext in GLTF_EXTENSIONS:
        return load_gltf(path, animation)
    return _load_with_trimesh(path)


# What a file that should be a mesh may really be: the first bytes tell (a download that saved a web page,
# a clone without `git lfs pull`). Checked before any parser sees the file.
LFS_POINTER_PREFIX = b"version https://git-lfs.github.com/spec/"
HTML_PREFIXES = (b"<!doctype html", b"<html", b"<head", b"<!--")


def check_not_a_stand_in(path: Path) -> None:
    """SceneFormatError naming what the file really is when it is a Git LFS pointer or an HTML page."""
    with open(path, "rb") as f:
        head = f.read(512)
    text = head.lstrip(b"\xef\xbb\xbf \t\r\n")
    if text.startswith(LFS_POINTER_PREFIX):
        raise SceneFormatError(f"{path}: this is a Git LFS pointer, not the mesh: fetch the file itself "
                               f"(git lfs pull) or download the real file")
    if text.lower().startswith(HTML_PREFIXES):
        raise SceneFormatError(f"{path}: this is an HTML page, not a mesh file (a download link that returned "
                               f"a web page?)")
    if len(head) == 0:
        raise SceneFormatError(f"{path}: the file is empty")


TEXT_MESH_EXTENSIONS = (".obj", ".off")


def _load_with_trimesh(path: Path) -> tuple[list[Mesh], list[Instance]]:
    import trimesh
    if path.suffix.lower() in TEXT_MESH_EXTENSIONS:  # text formats: say so, rather than trimesh's guessing errors
        try:
            path.read_bytes().decode("utf-8")
        except UnicodeDecodeError as e:
            raise SceneFormatError(f"{path}: not a readable {path.suffix[1:].upper()} file (not UTF-8 text at byte "
                                   f"{e.start})") from None
    try:
        scene = trimesh.load(str(path), force="scene", process=False)
    except Exception as e:  # trimesh raises many kinds on a corrupt file
        raise SceneFormatError(f"{path}: cannot read mesh file: {type(e).__name__}: {e}".splitlines()[0]) from None
    meshes: list[Mesh] = []
    index: dict[str, int] = {}
    instances: list[Instance] = []
    for node in scene.graph.nodes_geometry:
        transform, geom_name = scene.graph[node]
        geom = scene.geometry[geom_name]
        if not hasattr(geom, "faces") or len(geom.faces) == 0:
            continue
        if geom_name not in index:
            index[geom_name] = len(meshes)
            meshes.append(clean_mesh(str(geom_name), geom.vertices, geom.faces, f"{path}: mesh '{geom_name}'"))
        instances.append(Instance(name=str(node), mesh=index[geom_name],
                                  transform=np.asarray(transform, dtype=np.float64)))
    if not instances:
        raise GeometryError(f"{path}: no triangle meshes in file")
    return meshes, instances


def merged_mesh(name: str, meshes: list[Mesh], instances: list[Instance], **mesh_fields) -> Mesh:
    """All instances of a file baked into one mesh (for a TOML [[mesh]] that names a file)."""
    verts, faces, offset = [], [], 0
    for inst in instances:
        m = meshes[inst.mesh]
        t = inst.transform
        v = m.vertices @ t[:3, :3].T + t[:3, 3]
        f = m.faces if np.linalg.det(t[:3, :3]) > 0 else m.faces[:, ::-1]  # mirrored node: keep winding
        verts.append(v)
        faces.append(f + offset)
        offset += len(v)
    r = clean_geometry(np.concatenate(verts), np.concatenate(faces), f"mesh '{name}'")
    return Mesh(name=name, vertices=r.vertices, faces=r.faces, **mesh_fields)


# ---------------------------------------------------------------- glTF through pygltflib

DRACO = "KHR_draco_mesh_compression"
# Extensions a file may require that PSAO reads: Draco-compressed and quantised geometry (integer
# accessors, read and normalised like any other), and those that only change textures, materials or
# lights, which PSAO does not use (AO needs geometry alone), so ignoring them is safe.
SUPPORTED_REQUIRED_EXTENSIONS = frozenset({
    DRACO, "KHR_mesh_quantization", "KHR_texture_transform", "KHR_texture_basisu", "EXT_texture_webp",
    "EXT_texture_avif", "KHR_materials_unlit", "KHR_materials_emissive_strength", "KHR_materials_ior",
    "KHR_materials_specular", "KHR_materials_transmission", "KHR_materials_volume", "KHR_materials_clearcoat",
    "KHR_materials_sheen", "KHR_materials_iridescence", "KHR_materials_anisotropy",
    "KHR_materials_pbrSpecularGlossiness", "KHR_materials_variants", "KHR_lights_punctual",
})

_COMPONENT_DTYPES = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32,
                     5126: np.float32}
_TYPE_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


_GLB_MAGIC = 0x46546C67  # b"glTF"


def check_glb_lengths(path: Path) -> None:
    """A GLB's header length and every chunk's declared length must match the bytes the file holds (a
    reader would otherwise trust a 2 GiB claim from a 60-byte file). Not a GLB: nothing to check."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(12)
        if len(head) < 12 or struct.unpack_from("<I", head)[0] != _GLB_MAGIC:
            return
        _, _, total = struct.unpack("<III", head)
        if total != size:
            raise SceneFormatError(f"{path}: GLB header declares {total} bytes, the file holds {size}")
        at = 12
        while at < size:
            chunk = f.read(8)
            if len(chunk) < 8:
                raise SceneFormatError(f"{path}: GLB chunk header cut short at byte {at}")
            n, kind = struct.unpack("<II", chunk)
            if at + 8 + n > size:
                raise SceneFormatError(f"{path}: GLB chunk at byte {at} declares {n} bytes, the file holds "
                                       f"{size - at - 8} after it")
            f.seek(n, 1)
            at += 8 + n


class GltfFile:
    """A parsed glTF/GLB with its buffers in memory and typed accessor reads."""

    def __init__(self, path: Path):
        import pygltflib
        self.path = Path(path)
        check_glb_lengths(self.path)
        try:
            with warnings.catch_warnings():  # pygltflib warns (two lines) about chunks it skips
                warnings.simplefilter("ignore")
                self.doc = pygltflib.GLTF2().load(str(path))
        except Exception as e:
            raise SceneFormatError(f"{path}: cannot parse glTF: {type(e).__name__}: {e}".splitlines()[0]) from None
        if self.doc is None:
            raise SceneFormatError(f"{path}: cannot parse glTF")
        unsupported = [e for e in (self.doc.extensionsRequired or []) if e not in SUPPORTED_REQUIRED_EXTENSIONS]
        if unsupported:
            raise SceneFormatError(
                f"{path}: requires glTF extension{'s' if len(unsupported) > 1 else ''} {', '.join(unsupported)}, "
                f"which PSAO cannot read (supported: {', '.join(sorted(SUPPORTED_REQUIRED_EXTENSIONS))})")
        self._buffers: dict[int, bytes] = {}

    def buffer(self, i: int) -> bytes:
        if i not in self._buffers:
            uri = self.doc.buffers[i].uri
            if uri is None:
                blob = self.doc.binary_blob()
                if blob is None:
                    raise SceneFormatError(f"{self.path}: buffer {i} has no data")
                self._buffers[i] = bytes(blob)
            elif uri.startswith("data:"):
                self._buffers[i] = base64.b64decode(uri.split(",", 1)[1])
            else:
                file = self._local_file(uri, f"buffer {i}")
                if not file.is_file():
                    raise SceneNotFound(f"{self.path}: this glTF keeps its geometry in '{uri}', which is not next "
                                        f"to it: copy that file beside the .gltf (or use the .glb)")
                declared = self.doc.buffers[i].byteLength or 0
                if file.stat().st_size < declared:
                    raise SceneFormatError(f"{self.path}: buffer {i} declares {declared} bytes, '{uri}' holds "
                                           f"{file.stat().st_size}")
                with open(file, "rb") as f:
                    self._buffers[i] = f.read(declared) if declared else f.read()  # never more than declared
            declared = self.doc.buffers[i].byteLength or 0
            if len(self._buffers[i]) < declared:
                raise SceneFormatError(f"{self.path}: buffer {i} declares {declared} bytes, holds {len(self._buffers[i])}")
        return self._buffers[i]

    def _local_file(self, uri: str, what: str) -> Path:
        """The file a relative URI names inside the scene's folder; anything else (a scheme, an absolute
        path, a way out by '..' or a link) is refused: a scene file must not read the rest of the disk."""
        path = urllib.parse.unquote(uri)
        folder = self.path.parent.resolve()
        if urllib.parse.urlsplit(uri).scheme or Path(path).is_absolute():
            raise SceneFormatError(f"{self.path}: {what}: URI '{uri}' is not a relative path inside the scene's folder")
        file = (folder / path).resolve()
        if not file.is_relative_to(folder):
            raise SceneFormatError(f"{self.path}: {what}: URI '{uri}' leads outside the scene's folder")
        return file

    def accessor(self, i: int, what: str) -> np.ndarray:
        """Accessor i as an (count, width) array (normalized integers scaled to [0, 1] / [-1, 1])."""
        try:
            acc = self.doc.accessors[i]
        except (IndexError, TypeError):
            raise SceneFormatError(f"{self.path}: {what}: accessor {i} does not exist") from None
        if acc.sparse is not None:
            raise SceneFormatError(f"{self.path}: {what}: sparse accessors are not supported")
        if acc.componentType not in _COMPONENT_DTYPES or acc.type not in _TYPE_WIDTHS or (acc.count or 0) < 0:
            raise SceneFormatError(f"{self.path}: {what}: accessor {i} has an unknown component type or type")
        dtype = np.dtype(_COMPONENT_DTYPES[acc.componentType]).newbyteorder("<")
        width = _TYPE_WIDTHS[acc.type]
        if acc.bufferView is None:
            return np.zeros((acc.count, width), dtype=dtype)
        try:
            view = self.doc.bufferViews[acc.bufferView]
            data = self.buffer(view.buffer)
        except (IndexError, TypeError):
            raise SceneFormatError(f"{self.path}: {what}: accessor {i} refers to a missing buffer view or buffer") from None
        start = (view.byteOffset or 0) + (acc.byteOffset or 0)
        item = dtype.itemsize * width
        stride = view.byteStride or item
        end = start + stride * (acc.count - 1) + item if acc.count else start
        if end > (view.byteOffset or 0) + view.byteLength or end > len(data):
            raise SceneFormatError(f"{self.path}: {what}: accessor {i} runs past its buffer")
        raw = np.frombuffer(data, dtype=np.uint8, count=end - start, offset=start)
        if stride == item:
            out = raw.view(dtype).reshape(acc.count, width)
        else:
            rows = np.lib.stride_tricks.as_strided(raw, shape=(acc.count, item), strides=(stride, 1))
            out = np.ascontiguousarray(rows).view(dtype).reshape(acc.count, width)
        if acc.normalized and dtype.kind in "iu":
            out = np.maximum(out / np.iinfo(dtype).max, -1.0)
        return out

    def local_matrix(self, n: int) -> np.ndarray:
        node = self.doc.nodes[n]
        if node.matrix is not None and len(node.matrix) == 16:
            return np.asarray(node.matrix, dtype=np.float64).reshape(4, 4).T  # glTF is column-major
        return trs_matrix(node.translation, node.rotation, node.scale)

    def world_matrices(self) -> dict[int, np.ndarray]:
        """World matrix of every node reachable from the default scene (all roots when none)."""
        doc = self.doc
        if doc.scenes:
            roots = doc.scenes[doc.scene or 0].nodes or []
        else:
            children = {c for n in doc.nodes for c in (n.children or [])}
            roots = [i for i in range(len(doc.nodes)) if i not in children]
        world: dict[int, np.ndarray] = {}
        stack = [(r, np.eye(4)) for r in roots]
        while stack:
            n, parent = stack.pop()
            if n in world or not 0 <= n < len(doc.nodes):
                raise SceneFormatError(f"{self.path}: node {n} is missing or part of a cycle")
            world[n] = parent @ self.local_matrix(n)
            stack.extend((c, world[n]) for c in (doc.nodes[n].children or []))
        return world

    def node_name(self, n: int) -> str:
        return self.doc.nodes[n].name or f"node{n}"


def _triangles(mode: int, idx: np.ndarray) -> np.ndarray | None:
    """Triangle list from a primitive's indices; None for points and lines."""
    if mode == 4:
        return idx[: len(idx) // 3 * 3].reshape(-1, 3)
    if mode == 5:  # strip: alternate winding
        k = np.arange(len(idx) - 2)
        tri = np.stack([idx[k], idx[k + 1], idx[k + 2]], axis=1)
        tri[1::2] = tri[1::2][:, [1, 0, 2]]
        return tri
    if mode == 6:  # fan
        k = np.arange(1, len(idx) - 1)
        return np.stack([np.full_like(k, idx[0]), idx[k], idx[k + 1]], axis=1)
    return None


@dataclass
class GltfMeshData:
    """A glTF mesh, primitives concatenated, before cleaning (vertex order as in the file)."""
    name: str
    vertices: np.ndarray
    faces: np.ndarray
    joints: np.ndarray | None  # (V, 4) int64 JOINTS_0, when every primitive has it
    weights: np.ndarray | None  # (V, 4) float64 WEIGHTS_0
    color: tuple[float, float, float]
    double_sided: bool
    skinned_primitives: int = 0  # primitives with JOINTS_0 and WEIGHTS_0
    primitives: int = 0  # triangle primitives read


def read_gltf_mesh(g: GltfFile, mi: int) -> GltfMeshData:
    mesh = g.doc.meshes[mi]
    name = mesh.name or f"mesh{mi}"
    verts, faces, joints, weights, offset = [], [], [], [], 0
    skinned_prims: list[int] = []
    color, double_sided = (0.8, 0.8, 0.8), False
    for pi, prim in enumerate(mesh.primitives):
        what = f"mesh '{name}' primitive {pi}"
        tri_mode = 4 if prim.mode is None else prim.mode
        if prim.attributes.POSITION is None or tri_mode not in (4, 5, 6):
            log.warning("%s: %s: skipped (no positions or not triangles)", g.path, what)
            continue
        draco = (prim.extensions or {}).get(DRACO)
        if draco is not None:
            v, tri, skin = _draco_primitive(g, draco, what)
        else:
            v = g.accessor(prim.attributes.POSITION, what).astype(np.float64)
            idx = (g.accessor(prim.indices, what).reshape(-1).astype(np.int64) if prim.indices is not None
                   else np.arange(len(v), dtype=np.int64))
            tri = _triangles(tri_mode, idx)
            skin = None
            if prim.attributes.JOINTS_0 is not None and prim.attributes.WEIGHTS_0 is not None:
                skin = (g.accessor(prim.attributes.JOINTS_0, what), g.accessor(prim.attributes.WEIGHTS_0, what))
        # Morph targets (prim.targets) are left out: the mesh is read at rest, its base positions.
        verts.append(v)
        faces.append(tri + offset)
        if skin is not None:
            for attribute, values in zip(("JOINTS_0", "WEIGHTS_0"), skin):
                if len(values) != len(v):
                    raise SceneFormatError(f"{g.path}: {what}: {attribute} has {len(values)} entries for "
                                           f"{len(v)} positions")
            joints.append(skin[0].astype(np.int64))
            weights.append(skin[1].astype(np.float64))
            skinned_prims.append(pi)
        offset += len(v)
        if prim.material is not None and pi == 0:
            mat = g.doc.materials[prim.material]
            double_sided = bool(mat.doubleSided)
            pbr = mat.pbrMetallicRoughness
            if pbr is not None and pbr.baseColorFactor:
                color = tuple(float(c) for c in pbr.baseColorFactor[:3])
    if not verts:
        raise GeometryError(f"{g.path}: mesh '{name}': no triangle primitives")
    skinned = len(joints) == len(verts)
    return GltfMeshData(name, np.concatenate(verts), np.concatenate(faces),
                        np.concatenate(joints) if skinned else None,
                        np.concatenate(weights) if skinned else None, color, double_sided,
                        len(skinned_prims), len(verts))


def _draco_primitive(g: GltfFile, ext: dict, what: str):
    """(positions (V, 3) float64, triangles (F, 3), (joints, weights) or None) of a Draco-compressed
    primitive (KHR_draco_mesh_compression: its buffer view holds the Draco mesh; `attributes` maps glTF
    attribute names to Draco attribute ids). Draco keeps its own vertex order, used for every attribute."""
    import DracoPy

    try:
        view = g.doc.bufferViews[int(ext["bufferView"])]
        data = g.buffer(view.buffer)[(view.byteOffset or 0):(view.byteOffset or 0) + view.byteLength]
        mesh = DracoPy.decode(data)
    except (KeyError, IndexError, TypeError, ValueError) as e:
        raise SceneFormatError(f"{g.path}: {what}: cannot read its Draco data ({type(e).__name__}: {e})".splitlines()[0]) from None
    except Exception as e:  # DracoPy raises its own kinds on corrupt data
        raise SceneFormatError(f"{g.path}: {what}: Draco data does not decode ({type(e).__name__})") from None
    ids = ext.get("attributes", {})

    def attribute(name):
        if name not in ids:
            return None
        found = mesh.get_attribute_by_unique_id(int(ids[name]))
        return None if found is None else np.asarray(found["data"])

    pos = attribute("POSITION")
    if pos is None:
        pos = np.asarray(mesh.points)
    faces = np.asarray(mesh.faces, np.int64).reshape(-1, 3)
    joints, weights = attribute("JOINTS_0"), attribute("WEIGHTS_0")
    skin = None if joints is None or weights is None else (joints, weights)
    return np.asarray(pos, np.float64).reshape(-1, 3), faces, skin


# What malformed glTF fields raise deep inside the reader (wrong types, indices out of range, bad
# sizes); the file is untrusted input, so these become one SceneFormatError at this boundary.
MALFORMED_ERRORS = (KeyError, IndexError, TypeError, ValueError, AttributeError, OverflowError, MemoryError)


def load_gltf(path: Path, animation: int | str = 0) -> tuple[list[Mesh], list[Instance]]:
    try:
        return _load_gltf(path, animation)
    except MALFORMED_ERRORS as e:
        raise SceneFormatError(f"{path}: malformed glTF ({type(e).__name__}: {e})".splitlines()[0][:300]) from None


def _load_gltf(path: Path, animation: int | str) -> tuple[list[Mesh], list[Instance]]:
    g = GltfFile(path)
    world = g.world_matrices()
    moved = animated_nodes(g, animation)
    skins = g.doc.skins or []
    meshes: list[Mesh] = []
    mesh_index: dict[tuple, int] = {}  # (glTF mesh, skin) or (glTF mesh, None, node) or (glTF mesh,) -> Mesh
    read: dict[int, GltfMeshData | None] = {}  # glTF mesh -> its data (None: no triangles)
    instances: list[Instance] = []
    mesh_names: set[str] = set()
    inst_names: set[str] = set()
    for n in sorted(world):
        node = g.doc.nodes[n]
        if node.mesh is None:
            continue
        if node.mesh not in read:
            try:
                read[node.mesh] = read_gltf_mesh(g, node.mesh)
            except GeometryError as e:
                log.warning("%s", e)
                read[node.mesh] = None
            except MALFORMED_ERRORS as e:  # name the node and mesh when the fault is in the mesh
                raise SceneFormatError(f"{path}: node '{g.node_name(n)}' mesh {node.mesh}: malformed glTF "
                                       f"({type(e).__name__}: {e})".splitlines()[0]) from None
        data = read[node.mesh]
        if data is None:
            continue
        if node.skin is not None:
            if not 0 <= node.skin < len(skins):
                raise SceneFormatError(f"{path}: node '{g.node_name(n)}' refers to a missing skin {node.skin}")
            if data.joints is None:
                raise SceneFormatError(
                    f"{path}: node '{g.node_name(n)}' has skin {node.skin} but mesh '{data.name}' has JOINTS_0 "
                    f"and WEIGHTS_0 on {data.skinned_primitives} of its {data.primitives} primitives")
            key = (node.mesh, node.skin)
        elif n in moved:
            key = (node.mesh, None, n)
        else:
            key = (node.mesh,)
        if key not in mesh_index:
            name = _unique(data.name, mesh_names)
            r = clean_geometry(data.vertices, data.faces, f"{path}: mesh '{name}'",
                               merge=node.skin is None)
            mesh = Mesh(name=name, vertices=r.vertices, faces=r.faces, double_sided=data.double_sided,
                        color=data.color)
            if node.skin is not None:
                mesh.skin = skin_from_gltf(g, node.skin, data.joints[r.source_vertex],
                                           data.weights[r.source_vertex], animation)
            elif n in moved:
                mesh.skin = node_skin_from_gltf(g, n, len(r.vertices), animation)
            if mesh.skin is not None:
                rebase_to_rest_pose(mesh)
            mesh_index[key] = len(meshes)
            meshes.append(mesh)
        # A skinned mesh is placed by its joints, not by its node (glTF 2.0, skins): identity transform.
        skinned = meshes[mesh_index[key]].skin is not None
        instances.append(Instance(name=_unique(g.node_name(n), inst_names), mesh=mesh_index[key],
                                  transform=np.eye(4) if skinned else world[n]))
    if not instances:
        raise GeometryError(f"{path}: no triangle meshes in the default scene")
    return meshes, instances


def _unique(name: str, taken: set[str]) -> str:
    out, k = name, 1
    while out in taken:
        out, k = f"{name}.{k}", k + 1
    taken.add(out)
    return out
