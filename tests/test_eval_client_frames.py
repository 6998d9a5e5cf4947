"""The streaming client's own frames scored against RTAO: its frames.jsonl is enough to draw each frame
again for SSAO and the reference, and its PSAO images beat SSAO there (a misdrawn frame would not)."""
from __future__ import annotations

import numpy as np
import pytest

from psao.protocol.updates import GridDelta
from psao.client.mirror import Mirror
from psao.client.render.stream_render import StreamRenderer
from psao.eval.client_frames import load_client_frames, score_client_frames
from psao.eval.errors import EvalError
from psao.eval.reference import ReferenceSettings
from psao.scene import load_scene
from psao.server.bake import bake_scene
from psao.server.settings import BakeSettings


def test_client_frames_are_scored_from_their_log(ctx, tmp_path):
    scene = load_scene("builtin:cornell")
    res = bake_scene(scene, BakeSettings(density=256, rays=64), show_progress=False)
    res.tracer.close()
    grid = res.grid
    mirror = Mirror(grid.instances, len(grid.buckets), len(grid.cells))
    transforms = np.stack([i.transform for i in scene.instances]).astype(np.float32)
    mirror.apply(GridDelta(len(grid.cells), np.arange(len(transforms)), transforms,
                           np.arange(len(grid.buckets), dtype=np.uint32), grid.buckets,
                           np.arange(len(grid.cells), dtype=np.uint32), grid.cells))
    with StreamRenderer(scene, tmp_path, size=(120, 90), ctx=ctx) as cb:
        for tick in range(3):
            cb(mirror, mirror.transforms, tick=tick, camera_time=0.75 * tick)
    frames = load_client_frames(tmp_path)
    assert [f.frame for f in frames] == [0, 1, 2] and frames[2].time == pytest.approx(1.5)
    np.testing.assert_allclose(frames[0].transforms, transforms, atol=0)

    rows = score_client_frames(scene, tmp_path, 2, ReferenceSettings(spp=32, cache_dir=None))
    assert [r.frame for r in rows] == [0, 2]
    for r in rows:
        assert np.isfinite(r.psao.psnr) and r.psao.psnr > r.ssao.psnr + 5 and r.psao.flip < r.ssao.flip

    # A damaged log is one clear error naming the line.
    (tmp_path / "frames.jsonl").write_text('{"frame": 0}\n')
    with pytest.raises(EvalError, match="line 1"):
        load_client_frames(tmp_path)
    with pytest.raises(EvalError, match="frames log"):
        load_client_frames(tmp_path / "missing")


def test_stream_renderer_starts_a_fresh_log(ctx, tmp_path):
    (tmp_path / "frames.jsonl").write_text("stale\n")
    scene = load_scene("builtin:cornell")
    with StreamRenderer(scene, tmp_path, size=(32, 24), ctx=ctx):
        pass
    assert not (tmp_path / "frames.jsonl").exists()
