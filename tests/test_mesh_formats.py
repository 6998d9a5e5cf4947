"""Real-world glTF variants load or say in one line why not: required extensions, Draco, quantised
positions, strips and fans, morph targets, and files that are not what their name says."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pygltflib
import pytest

from psao.scene import load_scene
from psao.scene.errors import SceneError

QUAD = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 2, 0], [1, 2, 0]], np.float32)


def write_glb(path: Path, positions: np.ndarray, indices: np.ndarray | None, mode: int = 4, pos_type: int = 5126,
              normalized: bool = False, extensions_required=(), draco: bytes | None = None, targets: bool = False,
              scale=None) -> Path:
    """One mesh, one node, one primitive; the pieces given are written as the glTF spec says."""
    blob = b""
    views, accessors = [], []

    def add(data: bytes) -> int:
        nonlocal blob
        blob += b"\0" * (-len(blob) % 4)
        views.append(pygltflib.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(data)))
        blob += data
        return len(views) - 1

    pos = np.asarray(positions)
    accessors.append(pygltflib.Accessor(bufferView=None if draco else add(pos.tobytes()), componentType=pos_type,
                                        count=len(pos), type="VEC3", normalized=normalized or None,
                                        min=pos.min(axis=0).tolist(), max=pos.max(axis=0).tolist()))
    attrs = pygltflib.Attributes(POSITION=0)
    prim = pygltflib.Primitive(attributes=attrs, mode=mode)
    if indices is not None:
        idx = np.asarray(indices, np.uint16)
        accessors.append(pygltflib.Accessor(bufferView=None if draco else add(idx.tobytes()), componentType=5123,
                                            count=len(idx), type="SCALAR"))
        prim.indices = 1
    if draco is not None:
        prim.extensions = {"KHR_draco_mesh_compression": {"bufferView": add(draco), "attributes": {"POSITION": 0}}}
    if targets:
        delta = np.full_like(pos, 5.0)
        accessors.append(pygltflib.Accessor(bufferView=add(delta.tobytes()), componentType=5126, count=len(pos),
                                            type="VEC3"))
        prim.targets = [{"POSITION": len(accessors) - 1}]
    used = sorted(set(extensions_required) | ({"KHR_draco_mesh_compression"} if draco else set()))
    g = pygltflib.GLTF2(scene=0, scenes=[pygltflib.Scene(nodes=[0])], nodes=[pygltflib.Node(mesh=0, scale=scale)],
                        meshes=[pygltflib.Mesh(primitives=[prim], weights=[1.0] if targets else None)],
                        accessors=accessors, bufferViews=views, buffers=[pygltflib.Buffer(byteLength=len(blob))],
                        extensionsUsed=used, extensionsRequired=list(extensions_required))
    g.set_binary_blob(blob)
    g.save_binary(str(path))
    return path


def world_area(scene) -> float:
    return sum(scene.meshes[i.mesh].area(i.transform[:3, :3]) for i in scene.instances)


def one_line_error(path) -> str:
    with pytest.raises(SceneError) as err:
        load_scene(path)
    text = str(err.value)
    assert "\n" not in text
    return text


def test_triangle_strip_and_fan(tmp_path):
    strip = load_scene(write_glb(tmp_path / "strip.glb", QUAD, np.arange(6), mode=5))
    assert len(strip.meshes[0].faces) == 4 and world_area(strip) == pytest.approx(2.0)
    fan = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [-1, 1, 0]], np.float32)
    fanned = load_scene(write_glb(tmp_path / "fan.glb", fan, np.arange(5), mode=6))
    assert len(fanned.meshes[0].faces) == 3 and world_area(fanned) == pytest.approx(1.5)
    # the strip's alternating winding keeps every triangle facing the same way
    n = fanned.meshes[0].face_normals()
    assert np.allclose(n, n[0]) and np.allclose(strip.meshes[0].face_normals(), strip.meshes[0].face_normals()[0])


def test_quantised_positions(tmp_path):
    q = (QUAD / 2.0 * 32767).astype(np.int16)  # normalised int16 in [0, 1], node scale 2 gives the original
    scene = load_scene(write_glb(tmp_path / "q.glb", q, np.arange(6), mode=5, pos_type=5122, normalized=True,
                                 extensions_required=("KHR_mesh_quantization",), scale=[2.0, 2.0, 2.0]))
    assert world_area(scene) == pytest.approx(2.0, rel=1e-3)


def test_draco_compressed_primitive(tmp_path):
    import DracoPy

    tris = np.array([[0, 1, 2], [1, 3, 2], [2, 3, 4], [3, 5, 4]], np.uint32)
    data = DracoPy.encode(QUAD, tris, quantization_bits=14)
    scene = load_scene(write_glb(tmp_path / "d.glb", QUAD, tris.reshape(-1), draco=data,
                                 extensions_required=("KHR_draco_mesh_compression",)))
    assert len(scene.meshes[0].faces) == 4 and world_area(scene) == pytest.approx(2.0, rel=1e-3)


def test_morph_targets_load_at_rest(tmp_path):
    scene = load_scene(write_glb(tmp_path / "m.glb", QUAD, np.arange(6), mode=5, targets=True))
    assert np.abs(scene.meshes[0].vertices).max() <= 2.0  # base positions, not displaced by the target


@pytest.mark.parametrize("ext", ["EXT_meshopt_compression", "VENDOR_made_up"])
def test_unsupported_required_extension_is_named(tmp_path, ext):
    text = one_line_error(write_glb(tmp_path / "x.glb", QUAD, np.arange(6), mode=5, extensions_required=(ext,)))
    assert f"requires glTF extension {ext}" in text


def test_texture_transform_is_ignored(tmp_path):
    scene = load_scene(write_glb(tmp_path / "t.glb", QUAD, np.arange(6), mode=5,
                                 extensions_required=("KHR_texture_transform",)))
    assert world_area(scene) == pytest.approx(2.0)


def test_git_lfs_pointer(tmp_path):
    p = tmp_path / "model.glb"
    p.write_text("version https://git-lfs.github.com/spec/v1\noid sha256:" + "ab" * 32 + "\nsize 3832476\n")
    assert "Git LFS pointer" in one_line_error(p)


@pytest.mark.parametrize("name", ["model.gltf", "model.obj", "model.glb"])
def test_html_page(tmp_path, name):
    p = tmp_path / name
    p.write_text("<!DOCTYPE html>\n<html><head><title>Sign in</title></head><body>...</body></html>\n")
    assert "HTML page" in one_line_error(p)


def test_gltf_json_without_its_bin(tmp_path):
    g = pygltflib.GLTF2().load(str(write_glb(tmp_path / "x.glb", QUAD, np.arange(6), mode=5)))
    g.convert_buffers(pygltflib.BufferFormat.BINFILE)
    g.save(str(tmp_path / "sep.gltf"))
    (tmp_path / "sep.gltf").parent.joinpath(g.buffers[0].uri).unlink()
    text = one_line_error(tmp_path / "sep.gltf")
    assert g.buffers[0].uri in text and "not next to it" in text


def test_empty_file(tmp_path):
    (tmp_path / "e.obj").write_bytes(b"")
    assert "empty" in one_line_error(tmp_path / "e.obj")
