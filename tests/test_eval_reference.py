"""RTAO reference against closed forms, determinism and its cache."""
from __future__ import annotations

import numpy as np
import pytest

from psao.client.render.gbuffer import GBufferArrays
from psao.eval.errors import EvalError
from psao.eval.reference import FrameKey, ReferenceSettings, reference_ao
from psao.scene.model import Instance, Mesh, Scene


def quad(y: float, half: float, up: bool) -> Mesh:
    v = np.array([[-half, y, -half], [half, y, -half], [half, y, half], [-half, y, half]], float)
    f = np.array([[0, 2, 1], [0, 3, 2]]) if up else np.array([[0, 1, 2], [0, 2, 3]])
    return Mesh(name=f"quad{y}", vertices=v, faces=f)


def floor_ceiling_scene(height: float, ao_distance: float, half: float = 20.0) -> Scene:
    meshes = [quad(0.0, half, up=True), quad(height, half, up=False)]
    instances = [Instance(name=f"i{k}", mesh=k, transform=np.eye(4)) for k in range(2)]
    return Scene(name="floor-ceiling", meshes=meshes, instances=instances, ao_distance=ao_distance)


def floor_gbuffer(size=(24, 16), extent: float = 2.0, y: float = 0.0) -> GBufferArrays:
    """A synthetic G-buffer: every pixel a point on the floor (normal +y) within +-extent, a border of
    background pixels."""
    w, h = size
    xs = np.linspace(-extent, extent, w)
    zs = np.linspace(-extent, extent, h)
    x, z = np.meshgrid(xs, zs)
    world = np.stack([x, np.full_like(x, y), z], axis=-1).astype(np.float32)
    normal = np.zeros_like(world)
    normal[..., 1] = 1.0
    mask = np.ones((h, w), bool)
    mask[0, :] = mask[:, 0] = False
    z0 = np.zeros((h, w), np.float32)
    return GBufferArrays(world=world, normal=normal, local=world, local_normal=normal, color=world,
                         instance=np.where(mask, 0, -1).astype(np.int32), depth=z0, mask=mask)


@pytest.mark.parametrize("height,dist", [(0.5, 1.0), (0.8, 1.0), (1.0, 2.5)])
def test_floor_under_ceiling_matches_closed_form(height, dist):
    # A cosine-weighted ray from the floor reaches the ceiling within D iff cos(theta) > H / D, which
    # has probability 1 - (H/D)^2: visibility is (H/D)^2. The ceiling reaches sqrt(D^2 - H^2) beyond
    # every pixel, so its finite size does not matter.
    scene = floor_ceiling_scene(height, dist)
    gb = floor_gbuffer()
    ao = reference_ao(scene, gb, np.stack([np.eye(4)] * 2), ReferenceSettings(spp=512, cache_dir=None, workers=1),
                      show_progress=False)
    want = (height / dist) ** 2
    covered = ao[gb.mask]
    assert np.all(ao[~gb.mask] == 1.0)
    assert abs(covered.mean() - want) < 0.005
    assert np.abs(covered - want).max() < 0.05  # stratified 512 rays per pixel


def test_open_floor_is_unoccluded_and_ceiling_out_of_range():
    scene = floor_ceiling_scene(height=2.0, ao_distance=1.0)  # ceiling beyond the AO distance
    gb = floor_gbuffer()
    ao = reference_ao(scene, gb, np.stack([np.eye(4)] * 2), ReferenceSettings(spp=64, cache_dir=None, workers=1),
                      show_progress=False)
    assert np.all(ao == 1.0)


def test_transforms_place_the_occluders():
    # The same ceiling mesh lifted by a transform: AO follows the transform, not the rest pose.
    scene = floor_ceiling_scene(height=0.5, ao_distance=1.0)
    lift = np.eye(4)
    lift[1, 3] = 0.3  # ceiling at 0.8
    ao = reference_ao(scene, floor_gbuffer(), np.stack([np.eye(4), lift]),
                      ReferenceSettings(spp=512, cache_dir=None, workers=1), show_progress=False)
    assert abs(ao[floor_gbuffer().mask].mean() - 0.64) < 0.006


def test_pixel_seeded_rays_are_deterministic_and_cached(tmp_path):
    scene = floor_ceiling_scene(0.7, 1.0)
    gb = floor_gbuffer()
    tr = np.stack([np.eye(4)] * 2)
    key = FrameKey(np.eye(4), np.eye(4), 0.0)
    s = ReferenceSettings(spp=16, cache_dir=tmp_path, workers=1)
    a = reference_ao(scene, gb, tr, s, key, show_progress=False)
    b = reference_ao(scene, gb, tr, ReferenceSettings(spp=16, cache_dir=None, workers=1), show_progress=False)
    np.testing.assert_array_equal(a, b)  # same pixel ids, same rays
    entries = list(tmp_path.glob("*.npz"))
    assert len(entries) == 1
    # The cache is what answers the second time: overwrite the entry, get the overwritten values back.
    np.savez_compressed(entries[0], ao=np.full_like(a, 0.25))
    np.testing.assert_array_equal(reference_ao(scene, gb, tr, s, key, show_progress=False), 0.25)
    # Another spp or camera is another entry.
    reference_ao(scene, gb, tr, ReferenceSettings(spp=8, cache_dir=tmp_path, workers=1), key, show_progress=False)
    reference_ao(scene, gb, tr, s, FrameKey(np.eye(4), 2 * np.eye(4), 0.0), show_progress=False)
    assert len(list(tmp_path.glob("*.npz"))) == 3


def test_bad_settings_and_transforms():
    scene = floor_ceiling_scene(0.5, 1.0)
    with pytest.raises(EvalError, match="samples per pixel"):
        reference_ao(scene, floor_gbuffer(), np.stack([np.eye(4)] * 2), ReferenceSettings(spp=0, cache_dir=None))
    with pytest.raises(EvalError, match="transforms"):
        reference_ao(scene, floor_gbuffer(), np.eye(4)[None], ReferenceSettings(spp=4, cache_dir=None))
