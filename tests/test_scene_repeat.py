"""builtin:NAME-NXxNZ: a builtin scene copied on a grid (the large scene of the scale-out benchmark)."""
import numpy as np
import pytest

from psao.scene import SceneError, load_scene


def test_copies_on_a_grid_side_by_side():
    one = load_scene("builtin:courtyard")
    many = load_scene("builtin:courtyard-2x3")
    assert many.source == "builtin:courtyard-2x3" and many.name == "courtyard-2x3"
    assert len(many.instances) == 6 * len(one.instances)
    assert len({i.name for i in many.instances}) == len(many.instances)
    assert all(i.animation is None for i in many.instances) and all(m.skin is None for m in many.meshes)
    lo1, hi1 = one.world_bounds()
    lo, hi = many.world_bounds()
    ext1 = hi1 - lo1
    # 2 copies along X and 3 along Z, a tenth of the extent apart; Y unchanged
    np.testing.assert_allclose(hi - lo, [ext1[0] * (1 + 1.1), ext1[1], ext1[2] * (1 + 2 * 1.1)])
    # copy (0, 0) is the original
    for a, b in zip(one.instances, many.instances[:len(one.instances)]):
        np.testing.assert_array_equal(a.transform, b.transform)
    assert many.ao_distance == one.ao_distance
    assert load_scene("builtin:courtyard-2x3").content_hash() == many.content_hash() != one.content_hash()


@pytest.mark.parametrize("spec, text", [
    ("builtin:courtyard-0x2", "between 1 and 4096 copies, got 0 x 2"),
    ("builtin:courtyard-100x100", "between 1 and 4096 copies"),
    ("builtin:nope-2x2", "unknown scene 'builtin:nope-2x2'"),
])
def test_bad_repeats_are_errors(spec, text):
    with pytest.raises(SceneError, match=text):
        load_scene(spec)
