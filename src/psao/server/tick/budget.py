"""The time-budgeted part of the server tick: what to trace this tick, and how many points fit.

`RefineQueue` keeps, per point id, the rays accumulated since the geometry around the point last
changed (the history) and their unoccluded count. A point whose history holds fewer rays than the target
waits in the queue; every trace adds one round: the next interleaved slice of the point's target ray set
(`round_rays` rays of the `rays` the bake and the unbudgeted tick trace, same seed), and the stored AO is
the running mean (the tick gives a point reset by a change all its slices in one go: one slice blended
with a history from before the change lags behind it). So the rounds of a point add up to exactly its full trace: the
budgeted tick converges to the unbudgeted tick's very AO (and a scene at rest to the bake's, sending
nothing). A change around a point resets its history (`reset`), so the point goes to the
front of the queue; with `keep_rays` its estimate so far stands in for at most that many rays until as
many fresh rays have come, for a user that traces a reset point slice by slice (it then blends a few
rounds instead of showing one round's noise). The server tick traces a reset point's whole ray set in
one go, which outweighs the kept estimate at once. Nothing is dropped: a point waits until the budget reaches it. The queue is a mask
over the point ids, so it can never hold more entries than the scene has points.

Priority (`pick`): points in some client's extended view before points outside every view; among those,
points whose history was reset (nothing traced since their neighbourhood changed) before points being
refined; within each of those, points in a view itself (without its margins) before points only in its
margins; then the oldest waiting first, a point whose AO changed more since it was last traced (estimates
the resets give) going ahead of points that waited up to CHANGE_CREDIT_S longer: a bound on how long a
point in a view waits beyond its turn.

`TraceBudget` sizes the batch from the tracer's measured throughput: seconds = fixed cost + rays / rate,
each the median of the recent ticks' own trace calls, the tracer telling the seconds its rays took apart
from the call's (observe_trace), so a busier machine gets smaller batches. A budget below one point's cost
still traces `min_points` (progress is always made); the tick's statistics then show budget_used > 1.
A tick may leave its trace to the next (`pool`, BudgetSettings.pool_traces), whose call then has both
budgets (`trace_budget_s`): the call's fixed cost is paid once for the two.
"""
from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from psao.protocol import pointword as pw
from psao.server.errors import ConfigError

TICK_HZ_RANGE = (5.0, 60.0)  # ticks per second a service, and the budgeted tick behind it, may run at
DEFAULT_TICK_HZ = 60.0  # ServeSettings.tick_hz's default; the service tells its tick the rate (Tick.set_tick_rate)


def check_tick_hz(tick_hz: float) -> None:
    """ConfigError unless `tick_hz` is within TICK_HZ_RANGE."""
    lo, hi = TICK_HZ_RANGE
    if not lo <= tick_hz <= hi:
        raise ConfigError(f"tick rate must be within {lo:g}..{hi:g} Hz, got {tick_hz}")


@dataclass
class BudgetSettings:
    # (the tick rate is the service's, ServeSettings.tick_hz: the automatic budget is a share of its period, a
    # set one at most the period; check_rate)
    budget_ms: float | None = None  # milliseconds of tracing per tick, within (0, period]; None = automatic
    # (headroom x period - other stages)
    headroom: float = 0.85  # automatic budget: this share of the tick period, less the other stages (the tick's
    # animate, select and grid, and what its service spends a tick besides: TraceBudget.observe_service)
    floor: float = 0.2  # automatic budget: never below this share of the tick period, nor of the tick's real length
    round_rays: int = 8  # rays per point per trace round, a divisor of the target rays (the history accumulates
    # rounds, one slice of the target ray set each, up to the target); fitting_round_rays: the default's
    # largest divisor
    keep_rays: int = 24  # on a change around a point, its estimate so far stands in for this many rays (at
    # most) until as many fresh rays have come (RefineQueue); the server tick gives a reset point its whole
    # ray set at once, so there it never shows; 0 = forget at once
    min_points: int = 1  # traced every tick whatever the budget, so the queue always moves
    exact_points: int = 100_000  # static points near movers given their whole ray set at once each tick, from
    # the rays the static scene lets through (the bake's static hits, static_hits.StaticHits) traced against
    # the moving parts alone: those in view whose AO changed most since their last trace (at least
    # exact_min_change); at most this many, and at most what exact_share of the budget allows; 0 = none
    exact_share: float = 0.5  # of the trace budget, for those whole traces first; the rounds get the rest
    # (traced in the same call); 0 = no whole traces
    exact_cost: float = 0.6  # a whole trace from static hits against a full trace of as many rays, > 0: the
    # static scene is most of a ray's cost but occludes only a few of the rays of the points one tick of
    # motion selects, so a whole trace from their static hits costs well under a full one; the ratio on the
    # built-in scenes is measured by `python -m benchmarks.bench_static_hits`
    refill_points: int = 256  # static points a tick traces whole (full rays) to keep their static hits again
    # after a scene edit voided them, out of the whole traces' share; 0 = whole traces stop after an edit
    exact_min_change: float = 1.0 / 255  # estimated AO change (selection.occlusion_change, summed) worth it
    pool_traces: bool = True  # a tick that tests motion traces nothing (after a tick that traced) and leaves its
    # trace budget to the next tick, which traces both ticks' worth in one call: a trace call's fixed cost
    # (posing and refitting the movers, making the rays, handing the batch over: a few ms, much of a
    # tick's budget) is paid once for two ticks, and the motion test's long selection no longer shares a
    # tick with a trace; the points a test resets then wait one tick more. False: every tick traces
    motion_hz: float = 30.0  # motion tests (the points near movers found and their histories reset) a second of
    # scene time at most: a tick in between picks from what the last test reset and the queue's sweep; the
    # next test compares with the last one's frame, so no motion goes untested; 0 = every tick
    scan_points: int = 20000  # waiting points a tick looks at (at least 16 per point it traces): all of them
    # while the queue is no longer, else the next part of a sweep over it (RefineQueue.candidates)
    calls: int = 5  # recent trace calls whose median ray rate and fixed cost size the next batch (observe_trace)
    window: int = 32  # recent ticks whose median of the other stages' seconds they are taken to take
    local_rays: int = 65536  # the budgeted tick's trace calls of fewer rays run in its own process
    # (TraceSettings.local_rays): at a tick's sizes, handing a call to the tracer's worker processes (pickled
    # jobs, the moving part refitted in each) costs more than the second core gives back
    rays_per_tick: float = 0.0  # > 0: trace this many rays a tick (of the measured rate: whole traces count
    # exact_cost a ray) whatever the time they take, instead of what the time budget allows; for quality
    # studies that must not depend on the machine's load (benchmarks.bench_realtime --fixed-rays)

    def check_rate(self, tick_hz: float) -> None:
        """ConfigError unless `tick_hz` is within TICK_HZ_RANGE and a set budget within (0, its period]."""
        check_tick_hz(tick_hz)
        period_ms = 1e3 / tick_hz
        if self.budget_ms is not None and not (math.isfinite(self.budget_ms) and 0 < self.budget_ms <= period_ms):
            raise ConfigError(f"tick budget must be within (0, {period_ms:g}] ms (the tick period at {tick_hz:g} "
                              f"Hz; psao serve --tick-budget-ms), got {self.budget_ms}")

    def check(self, rays: int) -> None:
        """ConfigError for a setting out of range, naming it; `rays`: the tick's target rays per point. (The
        budget against the tick period: check_rate.)"""
        if self.budget_ms is not None and not (math.isfinite(self.budget_ms) and self.budget_ms > 0):
            raise ConfigError(f"tick budget must be a number of ms > 0 (psao serve --tick-budget-ms), got {self.budget_ms}")
        if not 1 <= self.round_rays <= rays or rays % self.round_rays:
            raise ConfigError(f"round rays must divide the tick's rays ({rays}): each round traces one equal slice of "
                              f"the target ray set (psao serve --tick-rays, --rays), got {self.round_rays}")
        if not (math.isfinite(self.rays_per_tick) and self.rays_per_tick >= 0):
            raise ConfigError(f"rays per tick must be a number >= 0 (0: from the time budget), got {self.rays_per_tick}")
        if not (math.isfinite(self.motion_hz) and self.motion_hz >= 0):
            raise ConfigError(f"motion tests a second must be a number >= 0 (0: every tick), got {self.motion_hz}")
        if min(self.min_points, self.scan_points, self.calls, self.window, self.local_rays) < 1:
            raise ConfigError(f"min points, scan points, calls, window and local rays must be >= 1, got "
                              f"{self.min_points}, {self.scan_points}, {self.calls}, {self.window}, {self.local_rays}")
        if not (0 <= self.exact_share <= 1) or self.exact_points < 0:
            raise ConfigError(f"exact share must be within [0, 1] and exact points >= 0, got {self.exact_share}, "
                              f"{self.exact_points}")
        if not (math.isfinite(self.exact_cost) and self.exact_cost > 0) or self.refill_points < 0:
            raise ConfigError(f"exact cost must be a number > 0 and refill points >= 0, got {self.exact_cost}, "
                              f"{self.refill_points}")


def fitting_round_rays(rays: int, most: int = BudgetSettings.round_rays) -> int:
    """Rays per round for a target of `rays`: the largest divisor of `rays` up to `most` (`most` when
    `rays` < 1, which BakeSettings.check refuses)."""
    return max((d for d in range(1, min(most, rays) + 1) if rays % d == 0), default=most)


class TraceBudget:
    """Points per tick from measured tracing speed."""

    def __init__(self, settings: BudgetSettings, rays_per_second: float = 2e6, overhead_s: float = 0.0,
                 tick_hz: float = DEFAULT_TICK_HZ):
        self.settings = settings
        self.set_tick_hz(tick_hz)
        self.rays_per_second = max(float(rays_per_second), 1e3)  # the rays' own rate, fixed costs apart
        self.overhead_s = max(float(overhead_s), 0.0)  # what a call costs besides its rays
        self.other_stages_s = 0.0  # animate + select + grid: the median of the recent ticks
        self.service_s = 0.0  # what the tick's service spends a tick besides them (fan-out, messages): the median
        self._per_ray: deque[float] = deque(maxlen=settings.calls)  # seconds a ray of the recent calls
        self._fixed: deque[float] = deque(maxlen=settings.calls)  # their seconds besides their rays
        self._others: deque[float] = deque(maxlen=settings.window)
        self._service: deque[float] = deque(maxlen=settings.window)
        self.pooled = 0  # ticks that left their trace to the next one (pool_traces) since the last trace call

    def set_tick_hz(self, tick_hz: float) -> None:
        """The tick rate the budget is a share of (ServerTick.set_tick_rate); ConfigError (check_rate) if it
        is out of range or a set budget exceeds its period."""
        self.settings.check_rate(tick_hz)
        self.tick_hz = tick_hz

    def budget_s(self) -> float:
        s = self.settings
        if s.budget_ms is not None:
            return s.budget_ms / 1e3
        # Never below `floor` of the period, nor below `floor` of the tick as it really runs: when the
        # other stages alone overrun the period, tracing keeps its share instead of starving.
        others = self.other_stages_s + self.service_s
        return max(s.headroom / self.tick_hz - others, s.floor / self.tick_hz, s.floor / (1 - s.floor) * others)

    def exact_rays(self, rays: int) -> float:
        """What a whole trace of `rays` rays from static hits costs, in rays of the measured rate."""
        return rays * self.settings.exact_cost

    def exact_points(self, rays: int) -> int:
        """How many whole traces of `rays` rays from static hits fit in exact_share of this tick's rays."""
        s = self.settings
        if s.exact_share <= 0:
            return 0
        return min(s.exact_points, int(s.exact_share * self.rays_in_budget() / max(self.exact_rays(rays), 1e-9)))

    def trace_budget_s(self) -> float:
        """Seconds this tick's trace call may take: its own budget and those of the ticks that left theirs
        to it (pool)."""
        return (1 + self.pooled) * self.budget_s()

    def pool(self) -> None:
        """This tick traces nothing: its budget goes to the next trace call."""
        self.pooled += 1

    def rays_in_budget(self) -> float:
        """Rays this tick's trace budget (trace_budget_s) allows at the measured rate, after a call's
        fixed cost. A fixed cost beyond the budget is paid whenever anything is traced: then half a
        budget's worth of rays goes on top of it, or the tick would crawl along at min_points."""
        if self.settings.rays_per_tick > 0:
            return (1 + self.pooled) * self.settings.rays_per_tick
        budget = self.trace_budget_s()
        return max(budget - self.overhead_s, 0.5 * budget) * self.rays_per_second

    def points(self, rays_per_point: int, spent_rays: float = 0.0) -> int:
        """How many points of `rays_per_point` rays fit in this tick's budget, less `spent_rays` (rays of the
        measured rate) of it given to whole traces, but at least what is not exact_share of it (at least min_points)."""
        whole = self.rays_in_budget()
        n = max(whole - spent_rays, (1 - self.settings.exact_share) * whole) / max(rays_per_point, 1)
        return max(int(n), self.settings.min_points)

    def observe_trace(self, rays: float, seconds: float, ray_seconds: float | None = None) -> None:
        """Learn from one trace call of `rays` rays (whole traces from static hits counted at exact_cost) in
        `seconds`, of which the tracer spent `ray_seconds` making and tracing the rays (the rest is the
        call's fixed cost: handing it over, refitting the moving part, ...; None: not known, all of it
        counts as the rays', so a fixed cost near the budget shrinks the batches towards min_points: the
        Warp tracer does not tell). The rate and the fixed cost are the medians of the recent calls' (`calls`):
        the calls' mix changes (a ray from static hits, a static point's and a mover's cost apart by up to
        3 times), and one call slowed by something else (a busy core, a first call's set-up) changes neither."""
        self.pooled = 0
        if rays <= 0 or not (math.isfinite(seconds) and seconds > 0):
            return
        ray_s = seconds if ray_seconds is None or not 0 < ray_seconds <= seconds else ray_seconds
        self._per_ray.append(ray_s / rays)
        self._fixed.append(seconds - ray_s)
        self.rays_per_second = max(1.0 / float(np.median(self._per_ray)), 1e3)
        self.overhead_s = float(np.median(self._fixed))

    def observe_other(self, seconds: float) -> None:
        """The other stages' seconds of one tick (their median over the recent ticks is what they take)."""
        self._others.append(max(float(seconds), 0.0))
        self.other_stages_s = float(np.median(self._others))

    @property
    def service_observed(self) -> int:
        """How many of the recent ticks' service seconds service_s is the median of."""
        return len(self._service)

    def observe_service(self, seconds: float) -> None:
        """What the service running the tick spent on one tick besides its stages (sending its changes,
        reading the clients' messages, waking the tick up): the tick's period holds that too."""
        if math.isfinite(seconds):
            self._service.append(max(float(seconds), 0.0))
            self.service_s = float(np.median(self._service))


def measure_tracer(tracer, positions, normals, ids, trace_settings) -> float:
    """Rays per second of one call tracing the given points, its fixed cost included (TraceBudget's
    starting rate, which the ticks' own calls replace), after a warm-up call of a few of them (a first
    call's lazy set-up)."""
    tracer.visibility(positions[:1], normals[:1], ids[:1], trace_settings)
    t0 = time.perf_counter()
    tracer.visibility(positions, normals, ids, trace_settings)
    return len(ids) * trace_settings.rays_traced / max(time.perf_counter() - t0, 1e-6)


HIDDEN_S = 4e9  # priority key offsets (seconds, beyond any wait): a point out of every view,
REFINING_S = 2e9  # a point that holds rays since its last reset,
MARGIN_S = 1e9  # a point in a view's margin only (fov and distance margins: seen once the camera turns)
CHANGE_S = 100.0  # seconds of waiting a change estimate of 1 (RefineQueue.change) is worth in the key,
CHANGE_CREDIT_S = 0.1  # up to this: a change moves a point ahead of those that waited at most this much longer,
# so no point in a view waits more than this beyond its turn in first-come order for points that change more
MAX_CHANGE = 1000.0  # change estimates accumulate up to this


def first_by_key(ids: np.ndarray, key: np.ndarray, k: int) -> np.ndarray:
    """The `k` ids of smallest key, in key order (ties: as given)."""
    if k <= 0:
        return ids[:0]
    if len(ids) > k:
        part = np.argpartition(key, k - 1)[:k]
        return ids[part[np.argsort(key[part], kind="stable")]]
    return ids[np.argsort(key, kind="stable")]


def first_within(ids: np.ndarray, key: np.ndarray, cost: np.ndarray, total: float, least: int = 0) -> np.ndarray:
    """The ids of smallest key, in key order (ties: as first_by_key), as many as their `cost`s (one per id, > 0)
    add up to without passing `total`, but at least `least` of them."""
    if len(ids) == 0:
        return ids
    most = max(int(total / max(float(cost.min()), 1e-12)), least)  # no more can fit: sort only these
    order = first_by_key(np.arange(len(ids)), key, most)
    n = int(np.searchsorted(np.cumsum(cost[order]), total, side="right"))
    return ids[order[:max(n, min(least, len(order)))]]


class RefineQueue:
    """Per point: rays accumulated since the last reset, unoccluded rays among them, slices of the target
    ray set traced, and since when the point waits (perf_counter seconds)."""

    compact_min = 1024  # dead entries the waiting list may hold before it is compacted

    def __init__(self, n: int, target_rays: int, keep_rays: int = 0, slices: int = 1):
        self.target = int(target_rays)
        self.keep = int(keep_rays)
        self.slices = int(slices)  # the target ray set is traced in this many rounds of target / slices rays
        self.rays = np.zeros(n, np.int32)  # fresh rays: traced since the last change around the point
        self.done = np.zeros(n, np.int32)  # slices traced since then
        # the slice the point's next round traces: it moves on with every round and is not set back by a
        # reset, so the rounds of a point in a changing neighbourhood go through its whole ray set (a blend
        # of recent rounds averages different rays instead of re-tracing the same slice), and any `slices`
        # rounds in a row are the whole set
        self.next_slice = np.zeros(n, np.int32)
        self.unoccluded = np.zeros(n, np.float32)
        self.old_rays = np.zeros(n, np.float32)  # the estimate from before the change, as so many rays
        self.old_unoccluded = np.zeros(n, np.float32)
        # fresh rays up to which the kept estimate blends in: as many as it stands for after a change (it
        # was measured around other geometry), the whole ray set for a few-ray first grid (same geometry)
        self.old_until = np.zeros(n, np.float32)
        self.waiting_since = np.full(n, time.perf_counter())
        # how much the point's AO may have changed since it was last traced (the sum of the estimates the
        # resets gave, e.g. selection.occlusion_change): the point changed most goes first
        self.change = np.zeros(n, np.float32)
        # the waiting ids (done < slices), sorted, with "dead" entries (done reached slices since) removed
        # in bulk once they are a quarter of the list: finding the waiting points, or the next window of
        # them, costs in proportion to them, and a finished round does not rewrite the whole list
        self._list = np.arange(n, dtype=np.int64)
        self._listed = np.ones(n, bool)  # id is in _list (waiting or dead)
        self._dead = 0  # entries of _list that no longer wait
        self.count = n  # points waiting
        self._cursors = [0, 0]  # per sweep (0: the tick's, 1: a refiner's), where its next part starts in _list

    def _now_waiting(self, ids: np.ndarray) -> None:
        """`ids` join the waiting set (called before their done is set to 0)."""
        new = np.unique(ids[self.done[ids] >= self.slices])
        if len(new) == 0:
            return
        self.count += len(new)
        listed = self._listed[new]
        self._dead -= int(listed.sum())  # dead entries come back to life
        new = new[~listed]
        if len(new):
            self._listed[new] = True
            at = self._at()
            merged = np.concatenate([self._list, new])
            merged.sort(kind="stable")  # two sorted runs: a linear merge
            self._list = merged
            self._move_cursors(at)

    def _finished(self, ids: np.ndarray, before: np.ndarray) -> None:
        """`ids` (distinct) whose done grew from `before`: those now holding every slice stop waiting."""
        gone = int(((before < self.slices) & (self.done[ids] >= self.slices)).sum())
        if gone == 0:
            return
        self.count -= gone
        self._dead += gone
        if self._dead > max(len(self._list) // 4, self.compact_min):
            self._compact()

    def _compact(self) -> None:
        w = self._list
        alive = self.done[w] < self.slices
        at = self._at()
        self._listed[w[~alive]] = False
        self._list = w[alive]
        self._dead = 0
        self._move_cursors(at)

    def _at(self) -> list:
        """The id each sweep's cursor is at (None: at the end)."""
        return [self._list[c] if c < len(self._list) else None for c in self._cursors]

    def _move_cursors(self, at: list) -> None:
        """Cursors to the same ids in a changed list (or the first id after them)."""
        self._cursors = [0 if a is None else int(np.searchsorted(self._list, a)) for a in at]

    def seed_from_codes(self, ids: np.ndarray, codes: np.ndarray, rays: int) -> None:
        """The bake's AO (its quantised value stands for the mean of its rays): with at least the target's
        rays it is the converged history; with fewer (a few-ray first grid) it is an estimate of its own
        ray set of the same geometry, standing in for `rays` rays beside the fresh slices until the point
        holds its whole target set (then that set's AO alone, as a full bake gives)."""
        vis = codes.astype(np.float32) / 255.0
        if rays >= self.target:
            before = self.done[ids]
            self.rays[ids], self.done[ids] = self.target, self.slices
            self.unoccluded[ids] = vis * self.target
            self._finished(ids, before)
        else:
            self._now_waiting(ids)
            self.rays[ids], self.done[ids], self.unoccluded[ids] = 0, 0, 0.0
            self.old_rays[ids], self.old_unoccluded[ids] = rays, vis * rays
            self.old_until[ids] = self.target

    def first_grid(self, ids: np.ndarray) -> np.ndarray:
        """Bool per id: holds only a few-ray first grid's estimate (seed_from_codes), no slice of its own
        and no change around it since."""
        return (self.done[ids] == 0) & self._first_estimate(ids)

    def _first_estimate(self, ids: np.ndarray) -> np.ndarray:
        """Bool per id: its kept estimate blends in beyond its own rays (up to the target: a few-ray first
        grid's, seed_from_codes; an estimate kept across a change stops at its own rays)."""
        return self.old_until[ids] > self.old_rays[ids]

    def unstarted(self, ids: np.ndarray) -> np.ndarray:
        """Bool per id: nothing traced since its last reset, and no first grid's estimate (first_grid): its
        next trace is its whole ray set."""
        return (self.rays[ids] == 0) & (self.done[ids] == 0) & ~self._first_estimate(ids)

    def reset(self, ids: np.ndarray, now: float, change: np.ndarray | None = None) -> None:
        """The geometry around `ids` changed: their history is void; they wait from now unless they waited already.
        Points with no fresh rays since their last reset (and no more kept rays than keep_rays) are left as
        they are: a reset again changes nothing for them (a mover's neighbourhood is reset every tick it moves, so this keeps the cost to the points
        traced since). `change`: per id, an estimate of how much its AO changed (added to `change`)."""
        if change is not None:
            self.change[ids] = np.minimum(self.change[ids] + change, MAX_CHANGE)
        cap = min(self.keep, self.target) if self.keep else np.inf
        old = self.old_rays[ids]
        ids = ids[(self.rays[ids] > 0) | (self.done[ids] > 0) | (old > cap)
                  | (self.old_until[ids] > old)]  # a first grid's estimate (now of other geometry)
        fresh = ids[self.rays[ids] >= self.target]
        self.waiting_since[fresh] = now
        if self.keep:
            total, unocc = self._blend(ids)
            kept = np.minimum(total, min(self.keep, self.target))
            self.old_unoccluded[ids] = unocc / np.maximum(total, 1) * kept
            self.old_rays[ids] = kept
        self.old_until[ids] = self.old_rays[ids]
        self._now_waiting(ids)
        self.rays[ids] = 0
        self.done[ids] = 0
        self.unoccluded[ids] = 0.0

    def waiting(self, eligible: np.ndarray | None = None) -> np.ndarray:
        """Ids (sorted) of (eligible) points whose history is short of the target."""
        w = self._list
        return w[self.done[w] < self.slices] if eligible is None else w[eligible[w] & (self.done[w] < self.slices)]

    def exclude(self, ids: np.ndarray) -> None:
        """`ids` never wait (points the grid does not hold)."""
        before = self.done[ids]
        self.done[ids] = self.slices
        self._finished(ids, before)

    @property
    def listed(self) -> int:
        """Entries of the waiting list (waiting points, and dead ones not yet removed): a sweep's length."""
        return len(self._list)

    def candidates(self, limit: int, sweep: int = 0) -> np.ndarray:
        """Ids (sorted) of waiting points to choose from: all of them while the list holds at most `limit`,
        else the next `limit` entries of a sweep over the list (wrapping; `sweep` 0 is the tick's, 1 a
        refiner's), so a long queue (a first grid being refined) costs a bounded amount per tick and every
        waiting point is looked at once a sweep."""
        w = self.window(limit, sweep)
        return w[self.done[w] < self.slices]

    def window(self, limit: int, sweep: int = 0) -> np.ndarray:
        """The entries of the waiting list `candidates` chooses from (sorted, dead ones too), moving the
        sweep's cursor as it does."""
        w = self._list
        if len(w) > limit:
            start = self._cursors[sweep]
            end = start + limit
            part = w[start:end]
            if end > len(w):  # wrap: the beginning of the list, before the part
                end -= len(w)
                part = np.concatenate([w[:end], part])
            self._cursors[sweep] = end
            w = part
        return w

    def looked_at(self, limit: int, changed: np.ndarray, sweep: int = 0) -> np.ndarray:
        """Sorted ids holding every waiting point of the union of candidates(limit, sweep) and `changed`
        (sorted, distinct), maybe with some that no longer wait: the sweep's window (moving its cursor as
        candidates does) and the ids of `changed` outside the window's range of ids, put where they fall
        (no sort: a waiting point is listed, so a waiting id of `changed` within that range is in the
        window already). Not to be modified (it may be the list itself)."""
        w, start = self._list, self._cursors[sweep]
        part = self.window(limit, sweep)
        if len(w) <= limit or len(part) == 0:  # the whole list: every waiting point
            return part
        if start + limit <= len(w):  # part = w[start:start + limit]: the ids changed on either side of it
            lo, hi = np.searchsorted(changed, part[0]), np.searchsorted(changed, part[-1], side="right")
            return np.concatenate([changed[:lo], part, changed[hi:]])
        end = start + limit - len(w)  # part = w[:end], w[start:]: the ids changed between the two
        lo = np.searchsorted(changed, w[end - 1], side="right")
        hi = np.searchsorted(changed, w[start]) if start < len(w) else len(changed)
        return np.concatenate([w[:end], changed[lo:hi], w[start:]])

    def pick(self, ids: np.ndarray, visible: np.ndarray, k: int, core: np.ndarray | None = None) -> np.ndarray:
        """The first `k` of `ids` in priority order: in some extended view before out of every view; among
        those, reset before refining; within each, a view's own points (`core`) before those only in its
        margins; then the oldest wait, less a credit for the estimated change (at most CHANGE_CREDIT_S)."""
        if len(ids) == 0:
            return ids
        return first_by_key(ids, self.key(ids, visible, float(self.waiting_since[ids].min()), core), k)

    def key(self, ids: np.ndarray, visible: np.ndarray, base: float, core: np.ndarray | None = None) -> np.ndarray:
        """Priority key of `ids` (smaller first): HIDDEN_S if out of every view, MARGIN_S if visible only in
        a view's margins (not in `core`; None: every visible point is), plus REFINING_S if the point holds
        rays since its last reset, plus its wait start less `base`, less CHANGE_S per unit of estimated
        change since its last trace (at most CHANGE_CREDIT_S). (select_kernels.priority_kernel computes the same in one pass, with
        the views.)"""
        tier = np.where(visible, 0.0 if core is None else np.where(core, 0.0, MARGIN_S), HIDDEN_S)
        return ((tier + (self.rays[ids] > 0) * REFINING_S)
                + ((self.waiting_since[ids] - base)
                   - np.minimum(self.change[ids].astype(np.float64) * CHANGE_S, CHANGE_CREDIT_S)))

    def add(self, ids: np.ndarray, visibility: np.ndarray, rays: int, now: float, slices: int = 1) -> np.ndarray:
        """Accumulate, for distinct `ids`, one round (each point's slice `next_slice`, of `rays` rays; or `slices` slices at once, e.g.
        the whole target set traced in one call); returns the AO codes of the running means. Points still
        short of the target keep waiting (their wait restarts now, so others get their turn)."""
        self.unoccluded[ids] += np.rint(visibility.astype(np.float32) * rays)  # a count: exact in float32
        self.rays[ids] += rays
        before = self.done[ids]
        self.done[ids] += slices
        self.next_slice[ids] = (self.next_slice[ids] + slices) % self.slices
        self._finished(ids, before)
        self.waiting_since[ids] = now
        self.change[ids] = 0.0
        total, unocc = self._blend(ids)
        return pw.quantise_ao(unocc / total)

    def _blend(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rays, unoccluded rays) of the current estimate: the fresh rays, plus the kept estimate until
        old_until fresh rays have come, and never beyond the target (a point with its whole ray set shows
        that set's AO alone)."""
        fresh_r, fresh_u = self.rays[ids].astype(np.float32), self.unoccluded[ids]
        with_old = (fresh_r < self.old_until[ids]) & (self.done[ids] < self.slices)
        total = fresh_r + np.where(with_old, self.old_rays[ids], 0.0)
        unocc = fresh_u + np.where(with_old, self.old_unoccluded[ids], 0.0)
        return total, unocc
