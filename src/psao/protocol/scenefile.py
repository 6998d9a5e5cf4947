"""The scene a server sends to clients that do not have it (SceneData messages): a compact binary format.

It holds what a client needs to rasterise and pose the geometry the server traces, nothing more:
meshes (float32 vertices in mesh-local space, uint32 triangles, albedo, double-sided flag), skins,
instances (mesh and local-to-world transform at rest), camera paths and the AO distance. Rigid
animation is not in it: the server sends every instance's transform in Snapshot and Update.

A skin is per-vertex joints (uint8) and weights (float32, 4 per vertex) and its skinning matrices
(joint matrix times inverse bind, the 3x4 upper rows) sampled at K times t_k = period * k / K; a client
poses the mesh at time t by blending the two samples around t mod period (`skin_pose`, which the web
client mirrors). K = 1 is a static skin. Sampling makes any animator, procedural or glTF, one format.

The whole blob is one zstd frame on the wire (psao.protocol.messages.SceneData chunks it). Layout, all
little-endian, every count checked against what is left before an array is made:

    b"PSCN" | version u16 | pad u16 | ao_distance f64 | name | meshes u32 | instances u32 | paths u32
    mesh      name | flags u8 (1 double-sided, 2 skinned) | pad u8 x3 | color f32 x3 | V u32 | F u32
              | vertices f32 (V, 3) | faces u32 (F, 3)
              [skinned: J u16 | pad u16 | K u32 | period f32 | joints u8 (V, 4) | weights f32 (V, 4)
              | matrices f32 (K, J, 3, 4)]
    instance  name | mesh u32 | transform f32 (4, 4) row-major
    path      name | fov_y f32 (degrees) | loop u8 | pad u8 x3 | K u32 | keys f32 (K, 7): t, eye, target
    name      u16 byte length | UTF-8
"""
from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

from psao.protocol.errors import LimitError, PayloadError
from psao.protocol.limits import DEFAULT_LIMITS, Limits
from psao.protocol.updates import Reader

MAGIC = b"PSCN"
VERSION = 1
MAX_JOINTS = 256  # joints are indexed with 8 bits
FLAG_DOUBLE_SIDED = 1
FLAG_SKINNED = 2

_HEAD = struct.Struct("<4sHHd")  # magic, version, pad, ao distance
_COUNTS = struct.Struct("<III")  # meshes, instances, camera paths
_MESH = struct.Struct("<B3x3fII")  # flags, colour, vertices, faces
_SKIN = struct.Struct("<H2xIf")  # joints, samples, period (s)
_INSTANCE = struct.Struct("<I")
_PATH = struct.Struct("<fB3xI")  # fov_y, loop, keys
_NAME = struct.Struct("<H")


@dataclass
class SkinData:
    joints: np.ndarray  # (V, 4) uint8, index into the J joints
    weights: np.ndarray  # (V, 4) float32, each row sums to 1
    period: float  # seconds the samples cover (0 with one sample: static)
    matrices: np.ndarray  # (K, J, 3, 4) float32 skinning matrices at t_k = period * k / K

    @property
    def joint_count(self) -> int:
        return int(self.matrices.shape[1])


@dataclass
class MeshData:
    name: str
    vertices: np.ndarray  # (V, 3) float32, mesh-local
    faces: np.ndarray  # (F, 3) uint32
    double_sided: bool = False
    color: tuple[float, float, float] = (0.8, 0.8, 0.8)  # linear RGB albedo
    skin: SkinData | None = None


@dataclass
class InstanceData:
    name: str
    mesh: int
    transform: np.ndarray  # (4, 4) float32 local-to-world at rest


@dataclass
class CameraPathData:
    name: str
    fov_y: float  # degrees
    loop: bool
    keys: np.ndarray  # (K, 7) float32: time (s), eye xyz, target xyz


@dataclass
class SceneFile:
    name: str
    ao_distance: float  # world units
    meshes: list[MeshData] = field(default_factory=list)
    instances: list[InstanceData] = field(default_factory=list)
    camera_paths: list[CameraPathData] = field(default_factory=list)

    def serialize(self) -> bytes:
        out = [_HEAD.pack(MAGIC, VERSION, 0, self.ao_distance), _name(self.name),
               _COUNTS.pack(len(self.meshes), len(self.instances), len(self.camera_paths))]
        for mesh in self.meshes:
            out.append(_mesh_bytes(mesh))
        for inst in self.instances:
            if not 0 <= inst.mesh < len(self.meshes):
                raise PayloadError(f"scene: instance '{inst.name}' refers to mesh {inst.mesh} of {len(self.meshes)}")
            out += [_name(inst.name), _INSTANCE.pack(inst.mesh), _f32(inst.transform, (4, 4), "instance transform")]
        for path in self.camera_paths:
            keys = _f32(path.keys, (-1, 7), "camera path keys")
            out += [_name(path.name), _PATH.pack(path.fov_y, int(path.loop), len(keys) // 28), keys]
        return b"".join(out)

    @classmethod
    def parse(cls, data: bytes, limits: Limits = DEFAULT_LIMITS) -> "SceneFile":
        r = Reader(data, "scene")
        magic, version, _pad, ao_distance = r.unpack(_HEAD)
        if magic != MAGIC:
            raise PayloadError(f"scene: bad magic {magic!r}, expected {MAGIC!r}")
        if version != VERSION:
            raise PayloadError(f"scene: format version {version}, this end reads {VERSION}")
        if not (np.isfinite(ao_distance) and ao_distance > 0):
            raise PayloadError(f"scene: AO distance {ao_distance} is not a positive number")
        name = _read_name(r)
        n_mesh, n_inst, n_path = r.unpack(_COUNTS)
        for what, n, most in (("meshes", n_mesh, limits.max_scene_meshes), ("instances", n_inst, limits.max_instances),
                              ("camera paths", n_path, limits.max_scene_meshes)):
            if n > most:
                raise LimitError(f"scene: {n} {what} over the limit of {most}")
        scene = cls(name, float(ao_distance))
        scene.meshes = [_read_mesh(r, limits) for _ in range(n_mesh)]
        for _ in range(n_inst):
            iname = _read_name(r)
            (mesh,) = r.unpack(_INSTANCE)
            if mesh >= n_mesh:
                raise PayloadError(f"scene: instance '{iname}' refers to mesh {mesh} of {n_mesh}")
            scene.instances.append(InstanceData(iname, int(mesh), _finite(r.array("<f4", 16).reshape(4, 4), iname)))
        for _ in range(n_path):
            pname = _read_name(r)
            fov, loop, k = r.unpack(_PATH)
            if not 0 < k <= limits.max_scene_camera_keys:
                raise LimitError(f"scene: camera path '{pname}' has {k} keys (1..{limits.max_scene_camera_keys})")
            keys = _finite(r.array("<f4", 7 * k).reshape(k, 7), f"camera path '{pname}'")
            if not (np.isfinite(fov) and 0 < fov < 180):
                raise PayloadError(f"scene: camera path '{pname}' field of view {fov} outside (0, 180)")
            scene.camera_paths.append(CameraPathData(pname, float(fov), bool(loop), keys))
        r.done()
        return scene


def skin_pose(skin: SkinData, t: float) -> np.ndarray:
    """(J, 4, 4) float32 skinning matrices at time t seconds: the samples around t mod period, blended
    linearly (the web client does the same in JavaScript)."""
    k = len(skin.matrices)
    if k == 1 or skin.period <= 0:
        i, j, f = 0, 0, np.float32(0.0)
    else:
        u = (float(t) % skin.period) / skin.period * k
        i = min(int(np.floor(u)), k - 1)
        j = (i + 1) % k
        f = np.float32(u - i)
    m = skin.matrices[i] * (np.float32(1.0) - f) + skin.matrices[j] * f
    out = np.zeros((skin.joint_count, 4, 4), np.float32)
    out[:, :3, :] = m
    out[:, 3, 3] = 1.0
    return out


# ---------------------------------------------------------------------------------------------- helpers

def _name(text: str) -> bytes:
    raw = text.encode("utf-8")
    if len(raw) > 0xFFFF:
        raise PayloadError(f"scene: name of {len(raw)} bytes is too long")
    return _NAME.pack(len(raw)) + raw


def _read_name(r: Reader) -> str:
    (n,) = r.unpack(_NAME)
    try:
        return bytes(r.take(n)).decode("utf-8")
    except UnicodeDecodeError:
        raise PayloadError("scene: a name is not valid UTF-8") from None


def _f32(a, shape, what: str) -> bytes:
    arr = np.asarray(a, dtype="<f4")
    try:
        arr = arr.reshape(shape)
    except ValueError:
        raise PayloadError(f"scene: {what} have shape {arr.shape}, expected {shape}") from None
    if not np.all(np.isfinite(arr)):
        raise PayloadError(f"scene: {what} have NaN or infinite entries")
    return np.ascontiguousarray(arr).tobytes()


def _finite(a: np.ndarray, what: str) -> np.ndarray:
    if not np.all(np.isfinite(a)):
        raise PayloadError(f"scene: {what} has NaN or infinite numbers")
    return a


def _mesh_bytes(m: MeshData) -> bytes:
    v = _f32(m.vertices, (-1, 3), f"mesh '{m.name}' vertices")
    faces = np.asarray(m.faces, dtype=np.int64).reshape(-1, 3)
    n_v = len(v) // 12
    if len(faces) and (faces.min() < 0 or faces.max() >= n_v):
        raise PayloadError(f"scene: mesh '{m.name}' has a face index outside its {n_v} vertices")
    flags = (FLAG_DOUBLE_SIDED if m.double_sided else 0) | (FLAG_SKINNED if m.skin is not None else 0)
    out = [_name(m.name), _MESH.pack(flags, *map(float, m.color), n_v, len(faces)), v,
           faces.astype("<u4").tobytes()]
    if m.skin is not None:
        s = m.skin
        mats = np.asarray(s.matrices, dtype="<f4")
        if mats.ndim != 4 or mats.shape[2:] != (3, 4) or not 0 < mats.shape[1] <= MAX_JOINTS or not len(mats):
            raise PayloadError(f"scene: mesh '{m.name}' skin matrices have shape {mats.shape}, expected (K, J<=256, 3, 4)")
        joints = np.asarray(s.joints).reshape(-1, 4)
        if len(joints) != n_v or joints.min() < 0 or joints.max() >= mats.shape[1]:
            raise PayloadError(f"scene: mesh '{m.name}' skin joints do not fit its vertices and {mats.shape[1]} joints")
        out += [_SKIN.pack(mats.shape[1], len(mats), s.period), joints.astype(np.uint8).tobytes(),
                _f32(s.weights, (n_v, 4), f"mesh '{m.name}' skin weights"), _f32(mats, mats.shape, "skin matrices")]
    return b"".join(out)


def _read_mesh(r: Reader, limits: Limits) -> MeshData:
    name = _read_name(r)
    flags, cr, cg, cb, n_v, n_f = r.unpack(_MESH)
    if n_v > limits.max_scene_vertices or n_f > limits.max_scene_faces:
        raise LimitError(f"scene: mesh '{name}' has {n_v} vertices and {n_f} faces, over the limits of "
                         f"{limits.max_scene_vertices} and {limits.max_scene_faces}")
    vertices = _finite(r.array("<f4", 3 * n_v).reshape(n_v, 3), f"mesh '{name}' vertices")
    faces = r.array("<u4", 3 * n_f).reshape(n_f, 3)
    if n_f and int(faces.max()) >= n_v:
        raise PayloadError(f"scene: mesh '{name}' has a face index outside its {n_v} vertices")
    mesh = MeshData(name, vertices, faces, bool(flags & FLAG_DOUBLE_SIDED), (cr, cg, cb))
    if flags & FLAG_SKINNED:
        n_j, k, period = r.unpack(_SKIN)
        if not 0 < n_j <= MAX_JOINTS or not 0 < k <= limits.max_skin_samples:
            raise LimitError(f"scene: mesh '{name}' skin of {n_j} joints and {k} samples "
                             f"(limits {MAX_JOINTS} and {limits.max_skin_samples})")
        if not (np.isfinite(period) and period >= 0):
            raise PayloadError(f"scene: mesh '{name}' skin period {period} is not a number >= 0")
        joints = r.array(np.uint8, 4 * n_v).reshape(n_v, 4)
        if n_v and int(joints.max()) >= n_j:
            raise PayloadError(f"scene: mesh '{name}' refers to a joint outside 0..{n_j - 1}")
        weights = _finite(r.array("<f4", 4 * n_v).reshape(n_v, 4), f"mesh '{name}' skin weights")
        mats = _finite(r.array("<f4", 12 * n_j * k).reshape(k, n_j, 3, 4), f"mesh '{name}' skin matrices")
        mesh.skin = SkinData(joints, weights, float(period), mats)
    return mesh
