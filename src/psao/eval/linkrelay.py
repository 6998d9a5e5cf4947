"""The packet forwarder between the two ends of an impaired link (psao.eval.links): one process, two TUN devices.

    python -m psao.eval.linkrelay HOST_DEV NS_DEV --rtt-ms 100 --loss 0.01 --mbit 5 [--queue-ms 100] [--seed 1]

It creates the TUN devices HOST_DEV and NS_DEV (IP packets, no extra header), prints `ready` on stdout and
then forwards every IP packet read from one device to the other, each direction on its own, like one link
with a bottleneck at its sending end:

- rate (--mbit): a packet leaves once the link has sent the packets queued before it, at the rate's
  serialisation time (bytes * 8 / rate); a packet that would wait more than --queue-ms behind them is
  dropped (a tail-drop queue, as tbf's limit);
- loss (--loss): each packet is dropped with that probability, independently of every other (Bernoulli);
- delay (--rtt-ms): each packet reaches the other device half the round trip after it left the queue.

Packets are never reordered. A JSON line on stdin ({"rtt_ms": .., "loss": .., "mbit": .., "queue_ms": ..},
psao.eval.links.LinkSettings' fields) changes the settings from then on (packets on their way keep their
due times); it answers with one JSON line of packet counts since the link was made or last changed: per
direction ("down": host to namespace, "up": back) the packets forwarded, dropped by loss and dropped by
the full queue, or {"error": ...} for bad settings. On SIGTERM, and when stdin ends (its parent is gone),
it prints the counts since then and exits. The devices are not persistent: they go away with this process, however it
ends (SIGTERM and SIGKILL alike). Timing is by the monotonic clock of a Python loop: a packet is due at an
exact virtual time, and written as soon as the loop wakes after it (typically well under 1 ms later on an
idle machine, more on a loaded one); the average rate is exact.
"""
from __future__ import annotations

import argparse
import errno
import fcntl
import heapq
import json
import os
import random
import selectors
import signal
import struct
import sys
import time
from dataclasses import dataclass, field

TUNSETIFF = 0x400454CA
IFF_TUN, IFF_NO_PI = 0x0001, 0x1000
MAX_PACKET = 65535  # bytes read per packet (an IP packet is at most this)


def open_tun(name: str) -> int:
    """A non-blocking fd of a new TUN device `name` (IP packets, no packet-info header)."""
    fd = os.open("/dev/net/tun", os.O_RDWR | os.O_NONBLOCK)
    try:
        fcntl.ioctl(fd, TUNSETIFF, struct.pack("16sH22x", name.encode(), IFF_TUN | IFF_NO_PI))
    except BaseException:
        os.close(fd)
        raise
    return fd


@dataclass
class Direction:
    """One direction of the link: packets read from `src`, written to `dst` when due."""

    src: int
    dst: int
    rng: random.Random
    delay_s: float = 0.0  # one-way delay, seconds
    loss: float = 0.0  # drop probability per packet
    bytes_per_s: float | None = None  # rate, bytes per second (None: unlimited)
    queue_s: float = 0.0  # longest wait behind earlier packets before a packet is dropped, seconds
    free_at: float = 0.0  # monotonic time at which the link has sent every packet accepted so far
    due: list = field(default_factory=list)  # heap of (due time, sequence, packet)
    seq: int = 0
    forwarded: int = 0
    dropped_loss: int = 0
    dropped_queue: int = 0

    def configure(self, settings) -> None:
        """Delay, loss, rate and queue from a LinkSettings."""
        self.delay_s = settings.rtt_ms / 2e3
        self.loss = settings.loss
        self.bytes_per_s = None if settings.mbit is None else settings.mbit * 1e6 / 8.0
        self.queue_s = settings.queue_ms / 1e3

    def take_counts(self) -> dict:
        """The packet counts since the last call (or the start), reset."""
        out = {"forwarded": self.forwarded, "dropped_loss": self.dropped_loss, "dropped_queue": self.dropped_queue}
        self.forwarded = self.dropped_loss = self.dropped_queue = 0
        return out

    def accept(self, packet: bytes, now: float) -> None:
        if self.loss and self.rng.random() < self.loss:
            self.dropped_loss += 1
            return
        sent = now
        if self.bytes_per_s is not None:
            start = max(self.free_at, now)
            if start - now > self.queue_s:
                self.dropped_queue += 1
                return
            self.free_at = sent = start + len(packet) / self.bytes_per_s
        self.seq += 1
        heapq.heappush(self.due, (sent + self.delay_s, self.seq, packet))

    def read(self, now: float) -> None:
        while True:
            try:
                packet = os.read(self.src, MAX_PACKET)
            except BlockingIOError:
                return
            except OSError as exc:
                if exc.errno in (errno.EAGAIN, errno.EIO):  # EIO: the device is not up yet
                    return
                raise
            self.accept(packet, now)

    def flush(self, now: float) -> float | None:
        """Write the packets due by `now`; the time the next one is due (None: none queued)."""
        while self.due and self.due[0][0] <= now:
            _, _, packet = heapq.heappop(self.due)
            try:
                os.write(self.dst, packet)
                self.forwarded += 1
            except OSError as exc:
                if exc.errno not in (errno.EAGAIN, errno.EIO, errno.EINVAL, errno.ENOBUFS):
                    raise
        return self.due[0][0] if self.due else None


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m psao.eval.linkrelay", description=__doc__.split("\n\n")[0])
    p.add_argument("host_dev")
    p.add_argument("ns_dev")
    p.add_argument("--rtt-ms", type=float, default=0.0, help="round-trip delay added, ms (half each way)")
    p.add_argument("--loss", type=float, default=0.0, help="fraction of packets dropped, each way, in [0, 1)")
    p.add_argument("--mbit", type=float, default=None, help="rate each way, Mbit/s (default: unlimited)")
    p.add_argument("--queue-ms", type=float, required=True,
                   help="queue before a rate-limited link, ms (psao.eval.links.LinkSettings.queue_ms)")
    p.add_argument("--seed", type=int, default=0, help="seed of the loss draws")
    return p.parse_args(argv)


def counts(dirs: list[Direction]) -> str:
    return json.dumps({name: d.take_counts() for name, d in zip(("down", "up"), dirs)})


def command(line: str, dirs: list[Direction]) -> str:
    """Apply one settings line from stdin; the answer line. (The sender waits for each answer before it
    sends another line: a second line already in stdin's buffer would wait for the next one.)"""
    from psao.eval.links import LinkSettings

    try:
        fields = json.loads(line)
        settings = LinkSettings(**fields).check()
    except (ValueError, TypeError) as exc:  # LinkError is a ValueError
        return json.dumps({"error": str(exc)})
    answer = counts(dirs)
    for d in dirs:
        d.configure(settings)
    return answer


def main(argv: list[str] | None = None) -> int:
    from psao.eval.links import LinkError, LinkSettings

    args = parse_args(argv)
    try:
        settings = LinkSettings(args.rtt_ms, args.loss, args.mbit, args.queue_ms).check()
    except LinkError as exc:
        print(f"linkrelay: {exc}", file=sys.stderr)
        return 2
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    host, ns = open_tun(args.host_dev), open_tun(args.ns_dev)
    rng = random.Random(args.seed)
    dirs = [Direction(host, ns, rng=rng), Direction(ns, host, rng=rng)]
    for d in dirs:
        d.configure(settings)
    sel = selectors.DefaultSelector()
    for d in dirs:
        sel.register(d.src, selectors.EVENT_READ, d)
    sel.register(sys.stdin, selectors.EVENT_READ, None)
    print("ready", flush=True)
    try:
        while True:
            now = time.monotonic()
            nexts = [t for t in (d.flush(now) for d in dirs) if t is not None]
            timeout = max(min(nexts) - time.monotonic(), 0.0) if nexts else None
            for key, _ in sel.select(timeout):
                if key.data is not None:
                    key.data.read(time.monotonic())
                    continue
                line = sys.stdin.readline()
                if not line:
                    return 0
                print(command(line, dirs), flush=True)
    finally:
        print(counts(dirs), flush=True)


if __name__ == "__main__":
    sys.exit(main())
