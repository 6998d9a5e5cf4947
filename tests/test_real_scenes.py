"""The real scenes in ../shared/scenes bake without error (skipped when the folder is absent)."""
from pathlib import Path

import numpy as np
import pytest

from psao_scene import load_scene
from psao_server.bake import bake_scene, reconstruction_error, sample_probes
from psao_server.settings import BakeSettings

SCENES = Path(__file__).resolve().parents[1].parent / "shared" / "scenes"
REAL = {
    "sponza/sponza_s_lod4.glb": 16.0,
    "bunny/stanford-bunny.obj": 20000.0,
    "cornellbox/CornellBox-Original.glb": 64.0,
    "cesiumman/CesiumMan.glb": 4096.0,
    "fox/Fox.glb": 1.0,
}


@pytest.mark.parametrize("rel,density", sorted(REAL.items()))
def test_real_scene_bakes(rel, density):
    path = SCENES / rel
    if not path.exists():
        pytest.skip(f"{path} not present")
    scene = load_scene(path)
    res = bake_scene(scene, BakeSettings(density=density, rays=16), show_progress=False)
    try:
        err = reconstruction_error(res.grid, scene, res.tracer, sample_probes(scene, 2000), rays=64)
    finally:
        res.tracer.close()
    t = res.grid.point_table()
    assert len(t) > 1000
    # Sponza (decimated, interpenetrating geometry) puts many surfaces through one cell; a crowded cell key
    # takes further cells, so what is dropped stays under the 0.5% target.
    assert res.stats["points_dropped_overflow"] < 0.005 * res.stats["points_generated"]
    assert np.isfinite(err["recon_mae"]) and err["recon_mae"] < 0.2
    assert err["hole_fraction"] < 0.1
