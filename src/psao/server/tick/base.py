"""What the service (psao.server.net.service.Service) drives at its tick rate: the `Tick` interface.

    Tick                      a tick of either kind; every method has a default that does nothing
    |-- on the event loop     `threaded` False: `tick(grid, t)` edits the grid between sends
    |                         (the test hooks of psao.server.tick.testhook, `FunctionTick` for a bare function)
    `-- threaded              `threaded` True: `prepare(t)` on the service's tick thread, writing no grid while
                              the senders read it, then `apply(plan)` on the loop, which writes it
                              (psao.server.tick.server_tick.ServerTick, AtRest)

A tick returns its statistics (`TickRecord`: what the service logs and writes to its stats jsonl) or None.
"""
from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar, Protocol

import numpy as np


class TickRecord(Protocol):
    seconds_total: float  # seconds the tick's own stages took (the service counts the rest as its own)

    def to_dict(self) -> dict: ...


class Tick:
    threaded: ClassVar[bool] = False  # prepare on the tick thread and apply on the loop, instead of __call__
    places_instances: ClassVar[bool] = False  # `transforms()` gives the instances' transforms (else the service's own)
    applies_edits: ClassVar[bool] = False  # `edit()` applies SceneEdits (else the service's own transforms take them)

    def __call__(self, grid, t: float) -> TickRecord | None:
        """The whole tick at scene time `t` on the caller's thread."""
        return self.apply(self.prepare(t))

    def prepare(self, t: float) -> object:
        """A threaded tick's work at scene time `t`, without writing the grid; what `apply` writes."""
        return t

    def apply(self, plan: object) -> TickRecord | None:
        """Write what `prepare` made into the grid."""
        return None

    def observe_service(self, seconds: float) -> None:
        """What the service spent on the last tick besides the tick's own stages (fan-out, the clients'
        messages, waking the next tick)."""

    def set_tick_rate(self, tick_hz: float) -> None:
        """The service ticks this `tick_hz` times a second (ServeSettings.tick_hz): told before its first tick."""

    def set_cameras(self, cameras: list) -> None:
        """The connected clients' cameras, (view 4x4, projection 4x4) pairs; [] when none sent one."""

    def transforms(self) -> np.ndarray:
        """(n_instances, 4, 4) float32 transforms of the last tick (places_instances ticks)."""
        raise NotImplementedError(f"{type(self).__name__} does not place instances")

    def edit(self, instance: int, transform: np.ndarray) -> None:
        """Instance `instance` is at `transform` from the next tick on (applies_edits ticks)."""
        raise NotImplementedError(f"{type(self).__name__} applies no scene edits")

    def close(self) -> None:
        """Release what the tick holds (tracer processes); a second call does nothing."""


class FunctionTick(Tick):
    """A bare function `fn(grid, t)` (or any callable that is not a Tick) as a tick on the event loop."""

    def __init__(self, fn: Callable[[object, float], object]):
        self.fn = fn

    def __call__(self, grid, t: float) -> TickRecord | None:
        return self.fn(grid, t)


def as_tick(tick: Tick | Callable | None) -> Tick | None:
    """`tick` as a Tick (a callable that is not one is wrapped in FunctionTick); None stays None."""
    return tick if tick is None or isinstance(tick, Tick) else FunctionTick(tick)
