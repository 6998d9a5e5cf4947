"""The run summary of `psao serve --json`: bounded memory however many ticks, p95 within a bin of exact."""
import math
import tracemalloc

import numpy as np
import pytest

from psao.server.tick.summary import BIN_RATIO, TickSummary


def record(i: int, seconds: float) -> dict:
    return {"seconds_tick": seconds, "time": 0.05 * i, "clients": 1 + i % 3, "bytes_sent": 10, "cells_sent": 2}


def exact_p95(seconds) -> float:
    ms = sorted(seconds)
    return ms[min(len(ms) - 1, math.ceil(0.95 * len(ms)) - 1)]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_summary_matches_exact_statistics(seed):
    rng = np.random.default_rng(seed)
    seconds = rng.lognormal(math.log(0.02), 1.0, size=5000)
    s = TickSummary()
    for i, x in enumerate(seconds):
        s.add(record(i, float(x)))
    d = s.to_dict()
    assert d["ticks"] == len(seconds) and d["clients_peak"] == 3 and d["bytes_sent"] == 10 * len(seconds)
    assert d["tick_ms_mean"] == pytest.approx(1e3 * seconds.mean())
    assert d["tick_ms_max"] == pytest.approx(1e3 * seconds.max())
    p95 = 1e3 * exact_p95(seconds)
    assert p95 <= d["tick_ms_p95"] <= p95 * BIN_RATIO * (1 + 1e-9)
    assert d["ticks_per_s"] == pytest.approx((len(seconds) - 1) / (0.05 * (len(seconds) - 1)))


def test_few_and_extreme_ticks():
    assert TickSummary().to_dict()["tick_ms_p95"] == 0.0
    s = TickSummary()
    s.add(record(0, 0.0))
    assert s.to_dict()["tick_ms_p95"] == 0.0
    for i, x in enumerate([1e-9, 3.0, 2e5]):  # below and above the histogram's range: p95 stays within min..max
        s.add(record(i + 1, x))
    d = s.to_dict()
    assert d["tick_ms_max"] == pytest.approx(2e8) and d["tick_ms_p95"] == pytest.approx(2e8)


def test_memory_does_not_grow_with_ticks():
    """A server running for days: memory after 50k more ticks is what it was (no list of durations)."""
    s = TickSummary()
    for i in range(1000):
        s.add(record(i, 0.01 + 1e-5 * i))
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    for i in range(1000, 51_000):
        s.add(record(i, 0.01 + 1e-7 * i))
    grown = tracemalloc.get_traced_memory()[0] - before
    tracemalloc.stop()
    assert grown < 64 * 1024, grown
