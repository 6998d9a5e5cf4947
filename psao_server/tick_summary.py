"""The statistics of a whole `psao serve` run, summed from its per-tick records (Service._record_tick):
what `psao serve --json` prints when the server stops, beside the service's counters.

Every tick's duration is kept (8 bytes a tick: a day at 60 Hz is 40 MB) so the 95th percentile is exact.
"""
from __future__ import annotations

import math
from array import array


class TickSummary:
    def __init__(self):
        self.tick_seconds = array("d")
        self.first_time: float | None = None  # service time (s) of the first and last tick recorded
        self.last_time = 0.0
        self.sums = {"bytes_sent": 0, "cells_sent": 0, "buckets_sent": 0, "cells_dirty": 0, "buckets_dirty": 0,
                     "traced": 0, "changed": 0}
        self.clients_peak = 0
        self.budget_used_sum = 0.0  # over the ticks that had a trace budget
        self.budgeted_ticks = 0

    def add(self, record: dict) -> None:
        """One tick's record: seconds_tick, time, clients, the sums' keys and, from the server tick,
        traced/changed/budget_ms/budget_used."""
        self.tick_seconds.append(float(record["seconds_tick"]))
        if self.first_time is None:
            self.first_time = float(record["time"])
        self.last_time = float(record["time"])
        for key in self.sums:
            self.sums[key] += record.get(key, 0)
        self.clients_peak = max(self.clients_peak, int(record.get("clients", 0)))
        if record.get("budget_ms"):
            self.budgeted_ticks += 1
            self.budget_used_sum += float(record["budget_used"])

    def to_dict(self) -> dict:
        """ticks, seconds (first to last tick), ticks_per_s, tick_ms_mean/p95/max, the sums, clients_peak
        and, for a budgeted tick, budget_used_mean."""
        n = len(self.tick_seconds)
        ms = sorted(1e3 * s for s in self.tick_seconds)
        span = self.last_time - self.first_time if self.first_time is not None else 0.0
        out = {
            "ticks": n,
            "seconds": span,
            "ticks_per_s": (n - 1) / span if n > 1 and span > 0 else 0.0,
            "tick_ms_mean": sum(ms) / n if n else 0.0,
            "tick_ms_p95": ms[min(n - 1, math.ceil(0.95 * n) - 1)] if n else 0.0,
            "tick_ms_max": ms[-1] if n else 0.0,
            **self.sums,
            "clients_peak": self.clients_peak,
        }
        if self.budgeted_ticks:
            out["budget_used_mean"] = self.budget_used_sum / self.budgeted_ticks
        return out
