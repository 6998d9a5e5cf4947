"""A deforming mesh kept in one Embree scene whose BVH is refitted, not rebuilt, when its vertices move.

embreex builds a mesh by copying it element by element and commits it with a full BVH build: about 17 ms
for the 8k triangles of builtin:robots, in every process that traces, every tick. Embree itself can do
better for a mesh whose triangles stay the same and only move (a skinned mesh): a scene flagged dynamic
with a geometry of build quality REFIT keeps its BVH topology and only recomputes the bounds on commit.
embreex does not expose that, so this module reaches the Embree library embreex loaded through ctypes:

    mesh = RefitMesh.build(vertices, faces)    # None where Embree cannot be reached this way
    mesh.scene.run(...)                        # an ordinary embreex scene
    mesh.move(new_vertices)                    # same faces, new vertices: write, refit

Only what embreex itself created is touched: the scene handle read from the embreex object (its layout
checked against a sentinel first), its geometry 0 and that geometry's vertex buffer (its stride found
by comparing its contents with the vertices given). Any check that fails leaves the caller to rebuild.
"""
from __future__ import annotations

import ctypes
import logging
import sys

import numpy as np

log = logging.getLogger("psao.tracer")

# Embree 4 enums (embree4/rtcore_scene.h, rtcore_geometry.h, rtcore_buffer.h)
_SCENE_FLAG_DYNAMIC = 1 << 0
_BUILD_QUALITY_LOW = 0
_BUILD_QUALITY_REFIT = 3
_BUFFER_TYPE_VERTEX = 1
_SENTINEL = 0x5CA1AB1E  # written to EmbreeScene.is_committed to find the object's layout

_API = None  # the ctypes library, False once it proved unusable in this process


def _embree_library():
    """ctypes handle on the libembree4 embreex loaded (found in this process's memory map), or False."""
    global _API
    if _API is not None:
        return _API
    _API = False
    try:
        import embreex.rtcore_scene  # noqa: F401  (maps the library)
        with open("/proc/self/maps") as f:
            paths = {line.split()[-1] for line in f if "libembree4" in line}
        if len(paths) != 1:
            return _API
        lib = ctypes.CDLL(paths.pop())
    except (ImportError, OSError):
        return _API
    vp, u32 = ctypes.c_void_p, ctypes.c_uint
    for name, args, res in (("rtcGetGeometry", [vp, u32], vp), ("rtcGetGeometryBufferData", [vp, u32, u32], vp),
                            ("rtcUpdateGeometryBuffer", [vp, u32, u32], None), ("rtcCommitGeometry", [vp], None),
                            ("rtcCommitScene", [vp], None), ("rtcSetSceneFlags", [vp, u32], None),
                            ("rtcGetSceneFlags", [vp], u32), ("rtcSetSceneBuildQuality", [vp, u32], None),
                            ("rtcSetGeometryBuildQuality", [vp, u32], None), ("rtcGetSceneDevice", [vp], vp),
                            ("rtcGetDeviceError", [vp], ctypes.c_int), ("rtcReleaseDevice", [vp], None)):
        fn = getattr(lib, name, None)
        if fn is None:
            return _API
        fn.argtypes, fn.restype = args, res
    _API = lib
    return _API


def _scene_handle(scene) -> int | None:
    """The RTCScene inside an embreex EmbreeScene: the pointer field before the `is_committed` int (the
    object's C layout: header, scene_i, is_committed, device), confirmed by reading back a sentinel."""
    base = id(scene) + object.__basicsize__
    before = scene.is_committed
    try:
        scene.is_committed = _SENTINEL
        found = ctypes.c_uint.from_address(base + ctypes.sizeof(ctypes.c_void_p)).value == _SENTINEL
    finally:
        scene.is_committed = before
    return ctypes.c_void_p.from_address(base).value if found else None


class RefitMesh:
    """Deforming triangle meshes in one embreex scene, one geometry each (Embree's two-level BVH for a
    dynamic scene: each geometry's own BVH is refitted, the small top level over them rebuilt), moved in
    place by `move`. One geometry per separately moving part keeps each refitted BVH as good as its first
    build; a single BVH over parts that walk apart would have to refit boxes spanning the gaps."""

    def __init__(self, scene, api, handle: int, geometries: list[int], views: list[np.ndarray],
                 faces: np.ndarray, starts: np.ndarray):
        self.scene = scene  # embreex EmbreeScene: trace it with scene.run
        self.faces = faces  # (F, 3) int32 over the merged vertices, fixed
        self.starts = starts  # first merged vertex of each part, and the vertex count at the end
        self._api, self._handle, self._geometries, self._views = api, handle, geometries, views

    @classmethod
    def build(cls, vertices: np.ndarray, faces: np.ndarray, device, parts=None) -> "RefitMesh | None":
        """The mesh (merged vertices (V, 3), faces (F, 3) into them) in a new scene on `device` (an embreex
        EmbreeDevice), committed for refitting; `parts`: the vertex count of each separately moving part
        (consecutive vertices; a part's faces use only its own vertices), None for one part. None where
        this Embree cannot be driven so (the caller then rebuilds scenes as embreex does)."""
        # (embreex: optional at import of the package; the Embree back-end checked it loads before this)
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        api = _embree_library()
        v = np.ascontiguousarray(vertices, np.float32)
        f = np.ascontiguousarray(faces, np.int32)
        if not api or len(f) == 0 or sys.byteorder != "little":
            return None
        starts = np.concatenate([[0], np.cumsum(parts if parts is not None else [len(v)])]).astype(np.int64)
        if starts[-1] != len(v):
            return None
        part_of = np.searchsorted(starts, f[:, 0], side="right") - 1
        if np.any(np.diff(part_of) < 0) or np.any(f < starts[part_of, None]) or np.any(f >= starts[part_of + 1, None]):
            return None  # faces must come part by part, each within its part's vertices
        scene = rtcore_scene.EmbreeScene(device)
        pieces = []
        for k in range(len(starts) - 1):
            pf = f[part_of == k] - starts[k]
            pv = v[starts[k]:starts[k + 1]]
            if len(pf) and len(pv) >= 2:
                TriangleMesh(scene, pv, pf)
                pieces.append((k, pv))
        handle = _scene_handle(scene)
        if not handle:
            return _unusable("the embreex scene's layout is not the one expected")
        geometries, views = [], []
        for gid, (k, pv) in enumerate(pieces):
            geometry = api.rtcGetGeometry(handle, gid)
            buffer = api.rtcGetGeometryBufferData(geometry, _BUFFER_TYPE_VERTEX, 0) if geometry else None
            if not buffer:
                return _unusable("no vertex buffer found on the embreex geometry")
            stride = _stride_of(buffer, pv)
            if stride is None:
                return _unusable("the embreex vertex buffer does not hold the vertices given")
            # a numpy view on Embree's buffer (owned by the scene, which this object keeps)
            raw = (ctypes.c_float * (len(pv) * stride // 4)).from_address(buffer)
            views.append((k, np.ctypeslib.as_array(raw).reshape(len(pv), stride // 4)[:, :3]))
            geometries.append(geometry)
            api.rtcSetGeometryBuildQuality(geometry, _BUILD_QUALITY_REFIT)
            api.rtcCommitGeometry(geometry)
        api.rtcSetSceneFlags(handle, api.rtcGetSceneFlags(handle) | _SCENE_FLAG_DYNAMIC)
        api.rtcSetSceneBuildQuality(handle, _BUILD_QUALITY_LOW)
        api.rtcCommitScene(handle)
        scene.is_committed = 1
        if _device_error(api, handle):
            return _unusable("Embree reported an error setting the scene up for refitting")
        return cls(scene, api, handle, geometries, views, f, starts)

    def move(self, vertices: np.ndarray) -> None:
        """Same triangles, new merged vertices (V, 3): written into the scene's buffers, BVHs refitted."""
        for geometry, (k, view) in zip(self._geometries, self._views):
            view[...] = vertices[self.starts[k]:self.starts[k + 1]]  # (cast to float32 on the way)
            self._api.rtcUpdateGeometryBuffer(geometry, _BUFFER_TYPE_VERTEX, 0)
            self._api.rtcCommitGeometry(geometry)
        self._api.rtcCommitScene(self._handle)

    def same_mesh(self, vertices: np.ndarray, faces: np.ndarray, parts=None) -> bool:
        """Whether (vertices, faces, parts) is this mesh moved: as many vertices per part, the same triangles."""
        counts = np.diff(self.starts)
        return (len(vertices) == self.starts[-1] and faces.shape == self.faces.shape
                and (parts is None and len(counts) == 1 or parts is not None and np.array_equal(parts, counts))
                and np.array_equal(faces, self.faces))


def _stride_of(buffer: int, v: np.ndarray) -> int | None:
    """Bytes per vertex in Embree's buffer at `buffer` (12 or 16), found by its contents matching `v`."""
    for stride in (16, 12):
        raw = ctypes.string_at(buffer, stride * len(v))
        got = np.frombuffer(raw, np.float32).reshape(len(v), stride // 4)[:, :3]
        if np.array_equal(got, v):
            return stride
    return None


def _device_error(api, handle: int) -> bool:
    device = api.rtcGetSceneDevice(handle)  # counts a reference: released below
    try:
        return api.rtcGetDeviceError(device) != 0
    finally:
        api.rtcReleaseDevice(device)


def _unusable(why: str) -> None:
    """Stop trying in this process: log once why, and let callers rebuild."""
    global _API
    if _API:
        log.warning("Embree refit unavailable (%s): deforming meshes are rebuilt each time they move", why)
    _API = False
    return None


__all__ = ["RefitMesh"]
