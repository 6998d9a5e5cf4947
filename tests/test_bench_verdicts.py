"""The shared benchmark verdict format: pass/fail, NaN and infinity never pass, failures counted."""

import math

import pytest

from benchmarks.verdicts import Verdicts, count_failures


def test_checks_print_one_line_each_and_set_the_exit_code(capsys):
    v = Verdicts("bench_x")
    assert v.check("ratio", 2.0, ">=", 1.5)
    assert not v.check("holes %", 0.2, "<", 0.1)
    assert v.record("grids identical", True)
    out = capsys.readouterr().out
    assert out.splitlines() == ["VERDICT PASS  bench_x  ratio: 2 >= 1.5",
                                "VERDICT FAIL  bench_x  holes %: 0.2 < 0.1",
                                "VERDICT PASS  bench_x  grids identical"]
    assert count_failures(out) == 1 and v.failures == 1 and v.exit_code() == 1


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_non_finite_values_fail(value, capsys):
    v = Verdicts("bench_x")
    assert not v.check("ratio", value, ">=", 1.0) and not v.check("ratio", value, "<", 1.0)
    assert v.exit_code() == 1 and count_failures(capsys.readouterr().out) == 2


def test_all_passing_exits_zero():
    v = Verdicts("bench_x")
    v.check("a", 1, "<=", 1)
    assert v.exit_code() == 0


def test_unknown_operator_is_refused():
    with pytest.raises(ValueError):
        Verdicts("bench_x").check("a", 1, "==", 1)


def test_quality_error_split_adds_up_to_the_mean_squared_error():
    """bench_realtime's split of the squared error by kind of point: the kinds' parts add up to the MSE
    the PSNR is computed from (points in view with an AO on both sides), and each kind counts its own."""
    import numpy as np

    from benchmarks.bench_realtime import POINT_KINDS, error_split

    rng = np.random.default_rng(0)
    samples = [rng.uniform(0, 1, (4, 50)) for _ in range(3)]
    budgeted, unbudgeted, refs = ([s[i] for s in samples] for i in range(3))
    budgeted[1][:5] = -1.0  # a point the grid did not hold at that sample
    views = [rng.uniform(size=50) < 0.7 for _ in range(3)]
    kinds = [rng.integers(0, len(POINT_KINDS), 50) for _ in range(3)]
    split = error_split(budgeted, unbudgeted, refs, views, kinds)
    ok = [v & (b >= 0) & (u >= 0) for b, u, v in zip(budgeted, unbudgeted, views)]
    mse = np.mean(np.concatenate([(b - r)[m] ** 2 for b, r, m in zip(budgeted, refs, ok)]))
    assert sum(e["mse_budgeted"] for e in split.values()) == pytest.approx(mse)
    assert sum(e["points_per_sample"] for e in split.values()) * 3 == pytest.approx(sum(int(m.sum()) for m in ok))
    first = np.mean([int((m & (k == 0)).sum()) for m, k in zip(ok, kinds)])
    assert split[POINT_KINDS[0]]["points_per_sample"] == pytest.approx(first)


def test_debiased_psnr_scores_against_the_truth_a_noisy_reference_estimates():
    """bench_realtime's frame PSNR: against a reference of `spp` rays a pixel, the reference's own noise is
    taken out, so two images score (and differ) as they do against the truth; left in, the noise lowers
    both and shrinks their gap."""
    import numpy as np

    from benchmarks.bench_realtime import debiased_psnr

    rng = np.random.default_rng(3)
    truth = rng.uniform(0.3, 1.0, (300, 300))
    spp = 512  # (bench_realtime's --frame-spp)
    ref = rng.binomial(spp, truth) / spp
    close, far = (np.clip(truth + rng.normal(0, sd, truth.shape), 0, 1) for sd in (0.02, 0.04))
    true_db = [10 * np.log10(1 / np.mean((img - truth) ** 2)) for img in (close, far)]
    got_db = [debiased_psnr(img, ref, spp) for img in (close, far)]
    plain_db = [10 * np.log10(1 / np.mean((img - ref) ** 2)) for img in (close, far)]
    assert got_db == pytest.approx(true_db, abs=0.3)
    assert got_db[0] - got_db[1] == pytest.approx(true_db[0] - true_db[1], abs=0.4)
    assert plain_db[0] - plain_db[1] < 0.8 * (true_db[0] - true_db[1])  # what the noise would hide
