"""Scene loading: built-ins, bare mesh files (glTF node transforms), cleaning, bad input."""
from __future__ import annotations

import json
import logging
import struct
from pathlib import Path

import numpy as np
import pygltflib
import pytest
import trimesh

from psao.scene import GeometryError, SceneFormatError, SceneNotFound, load_scene
from psao.scene.builtin import BUILTINS
from psao.scene.meshfile import _unique_rows, clean_geometry



def world_triangles(scene, inst) -> np.ndarray:
    m = scene.meshes[inst.mesh]
    t = inst.transform
    return (m.vertices @ t[:3, :3].T + t[:3, 3])[m.faces]


def triangle_areas(tri: np.ndarray) -> np.ndarray:
    return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)


@pytest.mark.parametrize("name", sorted(BUILTINS))
def test_builtin_geometry_is_clean(name):
    scene = load_scene(f"builtin:{name}")
    assert scene.source == f"builtin:{name}" and scene.ao_distance > 0
    names = [i.name for i in scene.instances]
    assert len(set(names)) == len(names)
    for inst in scene.instances:
        tri = world_triangles(scene, inst)
        assert np.isfinite(tri).all(), inst.name
        assert triangle_areas(tri).min() > 0, inst.name
    for m in scene.meshes:
        assert m.faces.dtype == np.int64 and m.vertices.dtype == np.float64
        assert m.faces.min() >= 0 and m.faces.max() < len(m.vertices)
        assert len(np.unique(m.faces)) == len(m.vertices), f"{m.name}: unused vertices"


def test_builtin_hash_stable_and_distinct():
    hashes = {n: load_scene(f"builtin:{n}").content_hash() for n in BUILTINS}
    assert {n: load_scene(f"builtin:{n}").content_hash() for n in BUILTINS} == hashes
    assert len(set(hashes.values())) == len(hashes)


def test_cornell_is_tiny_open_box_facing_inwards():
    scene = load_scene("builtin:cornell")
    assert sum(len(scene.meshes[i.mesh].faces) for i in scene.instances) < 1000
    lo, hi = scene.world_bounds()
    np.testing.assert_allclose(hi - lo, [1, 1, 1])
    centre = (lo + hi) / 2
    walls = [i for i in scene.instances if "block" not in i.name]
    assert len(walls) == 5
    for inst in walls:  # every wall triangle faces the box centre
        tri = world_triangles(scene, inst)
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        assert (np.einsum("ij,ij->i", n, centre - tri[:, 0]) > 0).all(), inst.name
    for inst in scene.instances:
        if "block" in inst.name:  # closed blocks: watertight with outward normals
            m = scene.meshes[inst.mesh]
            tm = trimesh.Trimesh(m.vertices, m.faces, process=False)
            assert tm.is_watertight and tm.volume > 0
    assert scene.camera_paths


def test_courtyard_layout():
    scene = load_scene("builtin:courtyard")
    tris = sum(len(scene.meshes[i.mesh].faces) for i in scene.instances)
    assert 5_000 < tris < 100_000
    lo, hi = scene.world_bounds()
    size = hi - lo
    assert 28 < size[0] < 34 and 10 < size[1] < 14 and 14 < size[2] < 18
    assert 1.5 <= scene.ao_distance <= 2.0
    uses = np.bincount([i.mesh for i in scene.instances], minlength=len(scene.meshes))
    by_name = {m.name: k for k, m in enumerate(scene.meshes)}
    assert uses[by_name["column_ground"]] >= 10 and uses[by_name["railing"]] >= 10
    assert {m.name for m in scene.meshes if m.double_sided} == {"banner"}
    for m in scene.meshes:  # everything except the cloth is a closed solid
        if not m.double_sided:
            assert trimesh.Trimesh(m.vertices, m.faces, process=False).is_watertight, m.name
    boulders = [i for i in scene.instances if i.name.startswith("boulder")]
    assert len(boulders) >= 3
    for inst in boulders:  # resting on the floor (y = 0), not floating, not buried
        y = world_triangles(scene, inst)[..., 1]
        assert -0.1 < y.min() <= 0.0


# ----------------------------------------------------------------------------- glTF node transforms

def _write_gltf(path: Path, nodes: list[pygltflib.Node], roots: list[int]) -> np.ndarray:
    """A glTF with one triangle mesh (a unit right triangle) used by the given nodes."""
    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=np.float32)
    idx = np.array([0, 1, 2], dtype=np.uint16)
    blob = pos.tobytes() + idx.tobytes() + b"\0\0"
    g = pygltflib.GLTF2(
        scene=0, scenes=[pygltflib.Scene(nodes=roots)], nodes=nodes,
        meshes=[pygltflib.Mesh(name="tri", primitives=[pygltflib.Primitive(
            attributes=pygltflib.Attributes(POSITION=0), indices=1)])],
        accessors=[
            pygltflib.Accessor(bufferView=0, componentType=5126, count=3, type="VEC3",
                               min=[0, 0, 0], max=[1, 1, 0]),
            pygltflib.Accessor(bufferView=1, componentType=5123, count=3, type="SCALAR")],
        bufferViews=[pygltflib.BufferView(buffer=0, byteOffset=0, byteLength=36),
                     pygltflib.BufferView(buffer=0, byteOffset=36, byteLength=6)],
        buffers=[pygltflib.Buffer(byteLength=len(blob))])
    g.set_binary_blob(blob)
    g.save_binary(str(path))
    return pos.astype(np.float64)


def test_gltf_node_hierarchy_kept_as_instances(tmp_path):
    q = [0.0, np.sin(np.pi / 4), 0.0, np.cos(np.pi / 4)]  # 90 degrees about +Y, (x, y, z, w)
    nodes = [
        pygltflib.Node(name="parent", translation=[10, 0, 0], scale=[2, 2, 2], children=[1, 2]),
        pygltflib.Node(name="child_rot", mesh=0, rotation=q),
        pygltflib.Node(name="child_mat", mesh=0,
                       matrix=[1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 5, 0, 1]),  # column-major: t=(0,5,0)
    ]
    pos = _write_gltf(tmp_path / "h.glb", nodes, [0])
    scene = load_scene(tmp_path / "h.glb")
    assert len(scene.meshes) == 1 and [i.name for i in scene.instances] == ["child_rot", "child_mat"]
    rot_y90 = np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]], dtype=np.float64)
    expect_rot = 2 * pos @ rot_y90.T + [10, 0, 0]
    expect_mat = 2 * (pos + [0, 5, 0]) + [10, 0, 0]
    got = {i.name: world_triangles(scene, i)[0] for i in scene.instances}
    for name, expect in (("child_rot", expect_rot), ("child_mat", expect_mat)):
        # the loader may reorder vertices (merging): compare the triangle as a set of corners
        np.testing.assert_allclose(sorted(map(tuple, got[name])), sorted(map(tuple, expect)), atol=1e-12)


def test_gltf_with_bad_node_transform_is_rejected(tmp_path):
    nodes = [pygltflib.Node(name="flat", mesh=0, scale=[1, 0, 1])]
    _write_gltf(tmp_path / "z.glb", nodes, [0])
    with pytest.raises(GeometryError, match=r"z\.glb.*instance 'flat'.*zero scale"):
        load_scene(tmp_path / "z.glb")


def test_cornellbox_glb_matches_trimesh_world_geometry(shared_scene):
    path = shared_scene("cornellbox/CornellBox-Original.glb")
    scene = load_scene(path)
    ours = np.concatenate([world_triangles(scene, i).reshape(-1, 3) for i in scene.instances])
    ref = trimesh.load(str(path), force="scene").to_geometry()
    np.testing.assert_allclose(np.sort(np.unique(ours.round(6), axis=0), axis=0),
                               np.sort(np.unique(np.asarray(ref.vertices).round(6), axis=0), axis=0), atol=1e-6)
    assert len(scene.instances) == 7


def test_sponza_and_fox_load(shared_scene):
    sponza = load_scene(shared_scene("sponza/sponza_s_lod4.glb"))
    lo, hi = sponza.world_bounds()
    assert 30 < (hi - lo).max() < 45
    assert sum(len(m.faces) for m in sponza.meshes) > 150_000
    fox = load_scene(shared_scene("fox/Fox.glb"))
    assert fox.meshes and np.isfinite(fox.meshes[0].vertices).all()


def test_bare_mesh_default_ao_distance_and_override(shared_scene):
    path = shared_scene("bunny/stanford-bunny.obj")
    scene = load_scene(path)
    lo, hi = scene.world_bounds()
    assert scene.ao_distance == pytest.approx(0.1 * np.linalg.norm(hi - lo))
    assert load_scene(path, ao_distance=0.02).ao_distance == 0.02


# -------------------------------------------------------------------------------------------- cleaning

def test_cleaning_merges_drops_and_reports(tmp_path, caplog):
    obj = tmp_path / "dirty.obj"
    obj.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 0 0\nv nan 0 0\nv 1 1 0\nv 2 0 0\n"
                   "f 1 2 3\n"  # good
                   "f 1 4 3\n"  # uses a duplicate of vertex 2: after merging, a duplicate of face 1
                   "f 1 2 5\n"  # touches the NaN vertex
                   "f 1 2 7\n"  # collinear: zero area
                   "f 4 6 3\n")  # good, via the duplicate
    with caplog.at_level(logging.WARNING, logger="psao.scene"):
        scene = load_scene(obj)
    m = scene.meshes[0]
    assert np.isfinite(m.vertices).all()
    assert len(m.vertices) == 4  # (0,0,0) (1,0,0) (0,1,0) (1,1,0): duplicate merged, unused dropped
    assert len(m.faces) == 3
    assert triangle_areas(m.vertices[m.faces]).min() > 0
    msgs = [r.getMessage() for r in caplog.records]
    assert len(msgs) == 1 and "dirty.obj" in msgs[0] and "1 triangles with NaN" in msgs[0] and "1 degenerate" in msgs[0]


def test_unique_rows_equals_numpy_unique():
    rng = np.random.default_rng(3)
    points = rng.integers(-3, 4, (5000, 3)).astype(float) / 3  # many repeats
    points[rng.integers(0, 5000, 200), 1] = -0.0  # -0.0 and 0.0 are one value, as np.unique takes them
    want = np.unique(points, axis=0, return_index=True, return_inverse=True)
    got = _unique_rows(points)
    for w, g in zip(want, got):
        assert np.array_equal(w.reshape(g.shape), g)


def test_cleaning_keeps_winding():
    v = np.array([[0, 0, 0], [0, 1, 0], [1, 0, 0], [0, 1, 0]], dtype=float)
    r = clean_geometry(v, [[0, 2, 3]], "t")
    n = np.cross(*(r.vertices[r.faces[0, 1:]] - r.vertices[r.faces[0, 0]]))
    assert n[2] > 0  # (0,0,0) (1,0,0) (0,1,0) is counter-clockwise about +z


def test_mesh_with_only_nan_is_geometry_error(tmp_path):
    obj = tmp_path / "nan.obj"
    obj.write_text("v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(GeometryError, match=r"nan\.obj.*mesh 'nan\.obj'.*no usable triangles"):
        load_scene(obj)


# ------------------------------------------------------------------------------------------- bad input

def one_line(excinfo) -> str:
    msg = str(excinfo.value)
    assert "\n" not in msg
    return msg


def test_missing_files(tmp_path):
    for name in ("nothere.obj", "nothere.glb", "nothere.toml"):
        with pytest.raises(SceneNotFound) as e:
            load_scene(tmp_path / name)
        assert name in one_line(e)


def test_unknown_builtin_lists_known():
    with pytest.raises(SceneNotFound) as e:
        load_scene("builtin:nope")
    msg = one_line(e)
    assert "builtin:nope" in msg and all(f"builtin:{n}" in msg for n in BUILTINS)


def test_unsupported_extension(tmp_path):
    f = tmp_path / "scene.fbx"
    f.write_bytes(b"x")
    with pytest.raises(SceneFormatError) as e:
        load_scene(f)
    assert "scene.fbx" in one_line(e) and ".fbx" in one_line(e)


def test_malformed_toml_names_line(tmp_path):
    f = tmp_path / "bad.toml"
    f.write_text('[scene]\nname = "x"\nao_distance = = 2\n')
    with pytest.raises(SceneFormatError) as e:
        load_scene(f)
    assert "bad.toml" in one_line(e) and "line 3" in one_line(e)


@pytest.mark.filterwarnings("error")  # nothing but the error: no library warning reaches the user
def test_corrupt_glb(tmp_path):
    f = tmp_path / "broken.glb"
    f.write_bytes(b"glTF" + struct.pack("<II", 2, 40) + b"\0" * 8)
    with pytest.raises((SceneFormatError, GeometryError)) as e:
        load_scene(f)
    assert "broken.glb" in one_line(e)


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_bad_ao_distance(bad):
    with pytest.raises(SceneFormatError):
        load_scene("builtin:cornell", ao_distance=bad)


@pytest.mark.parametrize("kind", ["bin_file", "data_uri"])
def test_gltf_json_with_external_or_embedded_buffer(tmp_path, kind):
    import base64
    nodes = [pygltflib.Node(name="a", mesh=0, translation=[0, 0, 1])]
    pos = _write_gltf(tmp_path / "x.glb", nodes, [0])
    g = pygltflib.GLTF2().load(str(tmp_path / "x.glb"))
    blob = g.binary_blob()
    if kind == "bin_file":
        (tmp_path / "x.bin").write_bytes(blob)
        g.buffers[0].uri = "x.bin"
    else:
        g.buffers[0].uri = "data:application/octet-stream;base64," + base64.b64encode(blob).decode()
    g.set_binary_blob(None)
    g.save_json(str(tmp_path / "x.gltf"))
    scene = load_scene(tmp_path / "x.gltf")
    np.testing.assert_allclose(sorted(map(tuple, world_triangles(scene, scene.instances[0])[0])),
                               sorted(map(tuple, pos + [0, 0, 1])), atol=1e-12)
    if kind == "bin_file":
        (tmp_path / "x.bin").unlink()
        with pytest.raises(SceneNotFound, match=r"x\.gltf.*x\.bin"):
            load_scene(tmp_path / "x.gltf")


@pytest.mark.parametrize("ext", ["stl", "ply", "off", "obj"])
def test_trimesh_formats_round_trip(tmp_path, ext):
    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    box.apply_translation((5.0, 0.0, -1.0))
    f = tmp_path / f"box.{ext}"
    box.export(str(f))
    scene = load_scene(f)
    tri = np.concatenate([world_triangles(scene, i) for i in scene.instances])
    assert len(tri) == 12
    assert triangle_areas(tri).sum() == pytest.approx(box.area)
    lo, hi = scene.world_bounds()
    np.testing.assert_allclose([lo, hi], box.bounds, atol=1e-6)
    assert scene.ao_distance == pytest.approx(0.1 * np.linalg.norm(hi - lo))


def _gltf_with_buffer_uri(folder: Path, uri_for, byte_length=None) -> Path:
    """x.gltf in `folder` whose buffer is a file named by uri_for(bin_path) (written where it says)."""
    nodes = [pygltflib.Node(name="a", mesh=0)]
    folder.mkdir(parents=True, exist_ok=True)
    _write_gltf(folder / "x.glb", nodes, [0])
    g = pygltflib.GLTF2().load(str(folder / "x.glb"))
    blob = g.binary_blob()
    uri, where = uri_for(folder)
    where.parent.mkdir(parents=True, exist_ok=True)
    where.write_bytes(blob)
    g.buffers[0].uri = uri
    if byte_length is not None:
        g.buffers[0].byteLength = byte_length
    g.set_binary_blob(None)
    g.save_json(str(folder / "x.gltf"))
    return folder / "x.gltf"


@pytest.mark.parametrize("uri_for, text", [
    (lambda d: ("../outside.bin", d.parent / "outside.bin"), "leads outside the scene's folder"),
    (lambda d: ("%2E%2E/outside.bin", d.parent / "outside.bin"), "leads outside the scene's folder"),
    (lambda d: (str(d.parent / "abs.bin"), d.parent / "abs.bin"), "not a relative path"),
    (lambda d: ((d.parent / "u.bin").as_uri(), d.parent / "u.bin"), "not a relative path"),
    (lambda d: ("../../../../../../../../etc/passwd", d / "unused.bin"), "leads outside the scene's folder"),
])
def test_gltf_buffer_uris_stay_in_the_scene_folder(tmp_path, uri_for, text):
    path = _gltf_with_buffer_uri(tmp_path / "scene", uri_for)
    with pytest.raises(SceneFormatError, match=text):
        load_scene(path)


def test_gltf_buffer_through_a_link_out_of_the_folder_refused(tmp_path):
    path = _gltf_with_buffer_uri(tmp_path / "scene", lambda d: ("link.bin", d.parent / "real.bin"))
    (path.parent / "link.bin").symlink_to(tmp_path / "real.bin")
    with pytest.raises(SceneFormatError, match="leads outside"):
        load_scene(path)


def test_gltf_buffer_in_a_subfolder_is_fine(tmp_path):
    path = _gltf_with_buffer_uri(tmp_path / "scene", lambda d: ("data/x%20y.bin", d / "data" / "x y.bin"))
    assert len(load_scene(path).instances) == 1


def _glb_bytes(doc: dict, blob: bytes, bin_chunk_length: int | None = None) -> bytes:
    """A GLB written by hand (pygltflib rewrites declared lengths on save)."""
    import json

    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    blob += b"\0" * (-len(blob) % 4)
    n_bin = len(blob) if bin_chunk_length is None else bin_chunk_length
    body = struct.pack("<II", len(js), 0x4E4F534A) + js + struct.pack("<II", n_bin, 0x004E4942) + blob
    return struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body


@pytest.mark.parametrize("kind", ["file", "glb buffer", "glb chunk"])
def test_declared_buffer_length_checked_against_real_size(tmp_path, kind):
    if kind == "file":
        path = _gltf_with_buffer_uri(tmp_path, lambda d: ("x.bin", d / "x.bin"), byte_length=1 << 31)
    else:
        _write_gltf(tmp_path / "x.glb", [pygltflib.Node(name="a", mesh=0)], [0])
        g = pygltflib.GLTF2().load(str(tmp_path / "x.glb"))
        blob = g.binary_blob()
        doc = json.loads(g.to_json())
        if kind == "glb buffer":
            doc["buffers"][0]["byteLength"] = 1 << 31
        else:
            doc["buffers"][0]["byteLength"] = len(blob)
        path = tmp_path / "big.glb"
        path.write_bytes(_glb_bytes(doc, blob, bin_chunk_length=(1 << 31) if kind == "glb chunk" else None))
    if kind == "glb chunk":  # a chunk claiming more than the file holds: refused, nothing that size allocated
        with pytest.raises(SceneFormatError):
            load_scene(path)
        return
    with pytest.raises(SceneFormatError, match=f"declares {1 << 31} bytes"):
        load_scene(path)
