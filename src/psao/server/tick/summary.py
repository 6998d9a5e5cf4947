"""The statistics of a whole `psao serve` run, summed from its per-tick records (Service._record_tick):
what `psao serve --json` prints when the server stops, beside the service's counters.

Memory is fixed however long the server runs: tick durations go into a histogram of log-spaced bins
(`DurationHistogram`, each bin `BIN_RATIO` wide), so the 95th percentile is known to within that ratio;
the mean and the maximum are exact.
"""
from __future__ import annotations

import math

import numpy as np

BIN_RATIO = 1.01  # neighbouring bin edges differ by 1%: the p95's relative error is below that
LOWEST_S = 1e-6  # durations at or below this fall in the first bin (s)
HIGHEST_S = 1e4  # and at or above this in the last (s)


class DurationHistogram:
    """Counts of durations in log-spaced bins from LOWEST_S to HIGHEST_S, with exact count, sum, min, max."""

    def __init__(self):
        self._log_ratio = math.log(BIN_RATIO)
        self.counts = np.zeros(math.ceil(math.log(HIGHEST_S / LOWEST_S) / self._log_ratio) + 1, np.int64)
        self.n = 0
        self.total = 0.0
        self.lowest = math.inf
        self.highest = -math.inf

    def _bin(self, seconds: float) -> int:
        if seconds <= LOWEST_S:
            return 0
        return min(len(self.counts) - 1, int(math.log(seconds / LOWEST_S) / self._log_ratio) + 1)

    def add(self, seconds: float) -> None:
        self.counts[self._bin(seconds)] += 1
        self.n += 1
        self.total += seconds
        self.lowest = min(self.lowest, seconds)
        self.highest = max(self.highest, seconds)

    def quantile(self, q: float) -> float:
        """The q-quantile (the smallest duration with at least q of them at or below it), as the upper edge
        of its bin, kept within the exact min and max: at most BIN_RATIO above the exact value (the last
        bin, open above, answers the exact max; the first at most LOWEST_S)."""
        if not self.n:
            return 0.0
        rank = max(1, math.ceil(q * self.n))
        b = int(np.searchsorted(np.cumsum(self.counts), rank))
        edge = self.highest if b == len(self.counts) - 1 else LOWEST_S * BIN_RATIO ** b
        return min(max(edge, self.lowest), self.highest)


# Upper edges (ms) of the bins of the in-view wait histogram (TickStats.view_waits): how long the points in a
# client's view waited from the reset of their history (the motion changed their neighbourhood) to their
# first re-trace; the last bin is open above. Fine around the target (100 ms) so the reported p95, a bin's upper
# edge, is within 10% of the true one there.
VIEW_WAIT_EDGES_MS = (5, 10, 20, 30, 40, 50, 60, 70, 80, 90, 100, 110, 120, 135, 150, 175, 200, 250, 300, 400, 500,
                      750, 1000, 2000, 5000, 10000)


def view_wait_counts(waits_ms: np.ndarray) -> list[int]:
    """Counts of `waits_ms` in the bins of VIEW_WAIT_EDGES_MS (len + 1 bins, a wait on an edge in the lower)."""
    bins = np.searchsorted(np.asarray(VIEW_WAIT_EDGES_MS, np.float64), np.asarray(waits_ms, np.float64), side="left")
    return np.bincount(bins, minlength=len(VIEW_WAIT_EDGES_MS) + 1).tolist()


def view_wait_quantile(counts, q: float) -> float:
    """The q-quantile of a view_wait_counts histogram as its bin's upper edge (ms; inf in the open last
    bin, 0 without waits)."""
    counts = np.asarray(counts, np.int64)
    if counts.sum() == 0:
        return 0.0
    b = int(np.searchsorted(np.cumsum(counts), max(1, int(np.ceil(q * counts.sum())))))
    return float(VIEW_WAIT_EDGES_MS[b]) if b < len(VIEW_WAIT_EDGES_MS) else float("inf")


class TickSummary:
    def __init__(self):
        self.durations = DurationHistogram()
        self.first_time: float | None = None  # service time (s) of the first and last tick recorded
        self.last_time = 0.0
        self.sums = {"bytes_sent": 0, "cells_sent": 0, "buckets_sent": 0, "cells_dirty": 0, "buckets_dirty": 0,
                     "traced": 0, "changed": 0}
        self.clients_peak = 0
        self.budget_used_sum = 0.0  # over the ticks that had a trace budget
        self.budgeted_ticks = 0
        self.view_waits = np.zeros(len(VIEW_WAIT_EDGES_MS) + 1, np.int64)  # summed TickStats.view_waits

    def add(self, record: dict) -> None:
        """One tick's record: seconds_tick, time, clients, the sums' keys and, from the server tick,
        traced/changed/budget_ms/budget_used."""
        self.durations.add(float(record["seconds_tick"]))
        if self.first_time is None:
            self.first_time = float(record["time"])
        self.last_time = float(record["time"])
        for key in self.sums:
            self.sums[key] += record.get(key, 0)
        self.clients_peak = max(self.clients_peak, int(record.get("clients", 0)))
        if record.get("view_waits"):
            self.view_waits += np.asarray(record["view_waits"], np.int64)
        if record.get("budget_ms"):
            self.budgeted_ticks += 1
            self.budget_used_sum += float(record["budget_used"])

    def to_dict(self) -> dict:
        """ticks, seconds (first to last tick), ticks_per_s, tick_ms_mean/p95/max, the sums, clients_peak
        and, for a budgeted tick, budget_used_mean and the in-view waits (count, p50 and p95 as bin edges).
        tick_ms_p95 is within BIN_RATIO above the exact p95."""
        d = self.durations
        n = d.n
        span = self.last_time - self.first_time if self.first_time is not None else 0.0
        out = {
            "ticks": n,
            "seconds": span,
            "ticks_per_s": (n - 1) / span if n > 1 and span > 0 else 0.0,
            "tick_ms_mean": 1e3 * d.total / n if n else 0.0,
            "tick_ms_p95": 1e3 * d.quantile(0.95),
            "tick_ms_max": 1e3 * d.highest if n else 0.0,
            **self.sums,
            "clients_peak": self.clients_peak,
        }
        if self.budgeted_ticks:
            out["budget_used_mean"] = self.budget_used_sum / self.budgeted_ticks
        if self.view_waits.any():  # (the quantiles as bin edges; inf: beyond the last edge)
            out.update(view_waits=int(self.view_waits.sum()), view_wait_p50_ms=view_wait_quantile(self.view_waits, 0.5),
                       view_wait_p95_ms=view_wait_quantile(self.view_waits, 0.95))
        return out
