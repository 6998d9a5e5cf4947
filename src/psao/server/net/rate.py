"""Each client's throughput, estimated from the answers to the server's pings (FanoutSettings.adapt_rate).

A ping goes out behind the messages sent before it, so its answer shows that the client has read those
bytes, and its round trip is the link's delay plus whatever waits in the buffers on the way. The
estimate (`RateEstimate`, one per client) starts unset: nothing paced. Over windows of at least
`rate_window` seconds it takes a delivery sample (bytes shown read over the window's span) and looks at the
round trips of the window's answers:

- **link-limited**: the least round trip of the window exceeds the least seen so far by more than
  `queue_target` (a queue has built on the link) while the sender had more to send (it was held back by
  the unread-messages limit or by its own pacing during the window). The estimate becomes
  `drain_share` of the largest of the last `rate_samples` samples (what the link carried: one window can
  fall short when a large message straddles its end), a little under it so that the queue drains. A client
  that is merely sent little never holds its sender back, so its low delivery rate is never taken.
- **not limited** (no queue): an estimate that is set grows by `probe_gain` when the window used at least
  half of it (probing upward), to at most `probe_gain` times the largest recent sample (an estimate the
  client does not use stays near what it does use), and is dropped (nothing paced) once it exceeds
  `unset_mbit`.

`link_mbit` is the mean of the estimates the link-limited windows set: what the client's link was seen
to carry (the service logs it when the client leaves).

The service paces every message to the estimate (with an explicit cap `client_mbit`, to the lesser of the
two) and sizes its own Updates to a tick's share of it (Fanout.cells_budget), the cells nearest the
camera first: a slow link carries what it can, with a queue of about `queue_target`, instead of seconds of
Updates. A fast client's pings come back without a queue, so it is never paced.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

from psao.server.settings import FanoutSettings

MIN_RATE = 0.02e6 / 8  # bytes/s: an estimate never goes below this (0.02 Mbit/s)


@dataclass
class RateEstimate:
    """One client's estimated throughput (bytes/s, None: not link-limited, nothing paced) and the state
    of its current window."""

    rate: float | None = None
    base_rtt: float = float("inf")  # the least ping round trip seen (seconds)
    limited_windows: int = 0  # windows that found the client link-limited
    limited_sum: float = 0.0  # the sum of the estimates they set (bytes/s)
    window_start: float = 0.0  # perf_counter() when the window began (0: before the first answer)
    window_bytes: int = 0  # bytes shown read when the window began
    window_rtt: float = float("inf")  # the least round trip of the window's answers
    held: bool = False  # the sender was held back during the window (more to send than it sent)
    samples: deque = field(default_factory=deque)  # the last windows' delivery samples (bytes/s)

    def note_held(self) -> None:
        """The client's sender waited for its client (unread messages) or for its pacing."""
        self.held = True

    @property
    def mbit(self) -> float | None:
        """The estimate now, Mbit/s (None: not paced)."""
        return None if self.rate is None else self.rate * 8 / 1e6

    @property
    def link_mbit(self) -> float | None:
        """The mean estimate of the link-limited windows, Mbit/s (None: none was)."""
        return self.limited_sum / self.limited_windows * 8 / 1e6 if self.limited_windows else None

    def answered(self, rtt: float, acked_bytes: int, now: float, settings: FanoutSettings) -> None:
        """A ping's answer: `rtt` seconds after it was sent, showing `acked_bytes` (all sent before it) read."""
        self.base_rtt = min(self.base_rtt, rtt)
        self.window_rtt = min(self.window_rtt, rtt)
        if not self.window_start:
            self.window_start, self.window_bytes = now, acked_bytes
            return
        span = now - self.window_start
        if span < settings.rate_window:
            return
        sample = (acked_bytes - self.window_bytes) / span
        self.samples.append(sample)
        while len(self.samples) > settings.rate_samples:
            self.samples.popleft()
        queued = self.window_rtt > self.base_rtt + settings.queue_target
        if queued and self.held:
            self.limited_windows += 1
            self.rate = max(MIN_RATE, settings.drain_share * max(self.samples))
            self.limited_sum += self.rate
        elif not queued and self.rate is not None and sample >= 0.5 * self.rate:
            self.rate = max(self.rate, min(self.rate * settings.probe_gain, settings.probe_gain * max(self.samples)))
            if self.rate * 8 / 1e6 > settings.unset_mbit:
                self.rate = None
        self.window_start, self.window_bytes = now, acked_bytes
        self.window_rtt, self.held = float("inf"), False


def pace_rate(estimate: RateEstimate, settings: FanoutSettings) -> float | None:
    """Bytes/s to pace a client to: its estimate (where adapt_rate) and the explicit cap, the lesser; None:
    not paced."""
    rates = [settings.client_mbit * 1e6 / 8] if settings.client_mbit is not None else []
    if settings.adapt_rate and estimate.rate is not None:
        rates.append(estimate.rate)
    return min(rates) if rates else None
