"""A per-client rate cap (FanoutSettings.client_mbit, `psao serve --client-mbit`): every message paced, the
client's own Updates carrying the cells nearest its camera first, its mirror exact. The service in-process
with a real client over loopback; waits are for counts, and the one bound on time only fails if the pacing
sends faster than the cap (a slow machine sends less, never more)."""
from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

from psao.client.connection import MirrorClient
from psao.protocol.limits import DEFAULT_LIMITS
from psao.server.errors import ConfigError
from psao.server.net.clients import Client
from psao.server.settings import FanoutSettings, ServeSettings
from psao.server.tick.testhook import RandomEdits
from test_bad_input_server import HASH, make_grid
from test_fanout import assert_digests_equal, start

CAP_MBIT = 0.1  # well under what the test grid's Updates take uncapped (about 0.3 Mbit/s)


def test_take_pending_sends_the_nearest_cells_first_and_keeps_the_rest():
    client = Client("test", n_buckets=8, capacity=100)
    slots = np.array([5, 17, 42, 60, 99], np.uint32)
    client.mark(np.zeros(0, np.uint32), slots, 100)
    far = {5: 9.0, 17: 1.0, 42: 7.0, 60: 0.5, 99: 3.0}
    distance = lambda s: np.array([far[int(x)] for x in s])  # noqa: E731
    b, c, drained = client.take_pending(DEFAULT_LIMITS, 100, distance=distance, max_cells=3)
    assert c.tolist() == [17, 60, 99]  # the three nearest, in ascending slot order (the encoders need it)
    assert not drained and sorted(client.cells_pending.indices().tolist()) == [5, 42]
    b, c, drained = client.take_pending(DEFAULT_LIMITS, 100, distance=distance, max_cells=3)
    assert c.tolist() == [5, 42] and drained


def test_a_capped_client_is_paced_within_its_rate_and_its_mirror_stays_exact(tmp_path):
    async def scenario():
        settings = ServeSettings(port=0, tick_hz=30, stats_interval=1e9, digest_log=tmp_path / "server.jsonl",
                                 fanout=FanoutSettings(client_mbit=CAP_MBIT))
        service, stop, task, url = await start(make_grid(3000), settings, RandomEdits(150))
        try:
            client = MirrorClient(url, HASH, digest_log=tmp_path / "c0.jsonl", digest_every=5)
            began = time.perf_counter()
            await client.run(frames=40)
            elapsed = time.perf_counter() - began
        finally:
            stop.set()
            await task
        return service, client, elapsed

    service, client, elapsed = asyncio.run(scenario())
    assert service.counters.paced_seconds > 0  # the cap held messages back (the snapshot alone exceeds it)
    rate = CAP_MBIT * 1e6 / 8
    largest = DEFAULT_LIMITS.server_message_bytes
    budget = rate * (elapsed + FanoutSettings.pace_burst) + min(largest, client.stats.snapshot_bytes)
    assert client.stats.bytes_received <= budget
    assert_digests_equal(tmp_path, ["c0"], at_least=2)


@pytest.mark.parametrize("mbit", [0.0, -1.0, float("nan"), float("inf")])
def test_a_cap_that_is_not_a_positive_rate_is_refused(mbit):
    with pytest.raises(ConfigError, match="client rate cap must be > 0 Mbit/s"):
        ServeSettings(fanout=FanoutSettings(client_mbit=mbit)).check()


def _windows(estimate, settings, samples):
    """Feed `estimate` one answer per window: (rtt s, bytes/s over the window, held back)."""
    now, acked = estimate.window_start, estimate.window_bytes
    if not now:
        now = 1.0
        estimate.answered(0.05, acked, now, settings)  # the first answer opens the first window
    for rtt, rate, held in samples:
        if held:
            estimate.note_held()
        now += settings.rate_window
        acked += int(rate * settings.rate_window)
        estimate.answered(rtt, acked, now, settings)


def test_the_estimate_takes_what_a_queueing_link_carried_and_nothing_from_a_client_sent_little():
    from psao.server.net.rate import RateEstimate

    settings = FanoutSettings()
    queued = 0.05 + 2 * settings.queue_target
    little = RateEstimate()  # round trips grow, but its sender never waited: it was sent little
    _windows(little, settings, [(queued, 1e4, False)] * 6)
    assert little.rate is None and little.link_mbit is None
    quiet = RateEstimate()  # held back, but no queue on the way: not its link
    _windows(quiet, settings, [(0.05, 1e4, True)] * 6)
    assert quiet.rate is None
    slow = RateEstimate()
    _windows(slow, settings, [(queued, 62_500, True)] * 6)  # 0.5 Mbit/s, queueing
    assert slow.rate == pytest.approx(settings.drain_share * 62_500)
    assert slow.link_mbit == pytest.approx(settings.drain_share * 0.5)
    was = slow.rate
    _windows(slow, settings, [(0.05, was, False)])  # the queue drained and the estimate was used: probe up
    assert slow.rate == pytest.approx(was * settings.probe_gain)
    _windows(slow, settings, [(0.05, 0.1 * was, False)] * 3)  # barely used: it stays
    assert slow.rate == pytest.approx(was * settings.probe_gain)


def test_an_estimate_paces_and_budgets_like_a_cap_and_the_lesser_of_the_two_holds():
    from psao.server.net.fanout import Fanout
    from psao.server.net.rate import RateEstimate, pace_rate

    est = RateEstimate(rate=1e5)
    assert pace_rate(RateEstimate(), FanoutSettings()) is None
    assert pace_rate(est, FanoutSettings()) == 1e5
    assert pace_rate(est, FanoutSettings(adapt_rate=False)) is None
    assert pace_rate(est, FanoutSettings(client_mbit=0.4)) == 0.4e6 / 8
    assert pace_rate(est, FanoutSettings(client_mbit=8)) == 1e5
    assert pace_rate(RateEstimate(), FanoutSettings(client_mbit=8, adapt_rate=False)) == 1e6
    client = Client("test", n_buckets=8, capacity=100)
    client.rate, client.bytes_per_cell = est, 100.0
    budget = Fanout.cells_budget(type("F", (), {"settings": FanoutSettings()})(), client, tick_hz=20)
    assert budget == int(1e5 / 20 / 100)


@pytest.mark.parametrize("field, value", [("queue_target", 0.0), ("drain_share", 1.5), ("probe_gain", 1.0),
                                          ("rate_window", -1.0), ("rate_samples", 0)])
def test_rate_estimate_settings_out_of_range_are_refused(field, value):
    with pytest.raises(ConfigError, match="rate estimate out of range"):
        ServeSettings(fanout=FanoutSettings(**{field: value})).check()
