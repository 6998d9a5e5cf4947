"""Impaired network links on this machine: a client in a network namespace of its own, joined to the host
through an emulated link with a round-trip delay, packet loss and a rate cap.

    with impaired_link(LinkSettings(rtt_ms=100, loss=0.01, mbit=5)) as link:
        # a server listens on link.host_address (or on 0.0.0.0); a client runs inside the namespace:
        proc = psao.eval.processes.spawn(["client", f"ws://{link.host_address}:{port}"], wrap=link.prefix)

What is emulated, and how: `impaired_link` creates a network namespace and two TUN devices, one in the
namespace (address `link.ns_address`) and one on the host (`link.host_address`), a /30 between them. A
forwarder process (psao.eval.linkrelay) carries every IP packet from one device to the other, each
direction on its own: a tail-drop queue drained at `mbit` (a packet that would wait longer than
`queue_ms` is dropped), independent random loss of `loss` of the packets, and a fixed one-way delay of
half of `rtt_ms`. This is packet-level emulation, as netem and tbf would do in the kernel (this machine's
kernel has neither netem nor the tc actions that drop packets at random): TCP sees real delay, real
losses (and retransmits), and a real bottleneck queue. The delay has no jitter, packets are never
reordered, and the forwarder's timing is a Python loop's: a packet is delivered as soon as the loop wakes
after its due time, which on a loaded machine adds delay of its own (the settings are a floor, not an
exact figure). A zero setting adds nothing, though every packet still passes through the forwarder.

No veth pair and no tc: tbf on a veth could cap the rate, but nothing in this kernel delays packets or
drops them at random, and one forwarder doing all three keeps their order (queue, loss, delay) plain.
`link.change(settings)` changes a live link (one namespace, one address, a sweep of settings).
Everything is torn down on exit, after errors too: the forwarder stops (its stdin closed, then SIGKILL;
its TUN devices go with it, and it exits by itself when its owner dies) and the namespace is deleted.
Namespaces left by a process that was killed (names carry its pid and its pid namespace) are deleted by
the next `impaired_link` of the same pid namespace. `links_unavailable()` says why links cannot be made
here (not root, no `ip`, no TUN device, namespaces refused), for tests to skip on.
"""
from __future__ import annotations

import contextlib
import itertools
import json
import math
import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

from psao.eval.errors import EvalError

NS_PREFIX = "psao-link-"  # namespace names: NS_PREFIX + "<pid namespace>-<pid>-<n>" (see _owner)
SUBNET_BASE = (10, 213)  # the links' /30s are carved out of 10.213.0.0/16
SUBNETS = 1 << 14  # /30s in a /16
READY_TIMEOUT_S = 30.0  # seconds for the forwarder to create its devices
IP_TIMEOUT_S = 30.0  # seconds for one `ip` command

_counter = itertools.count()


class LinkError(ValueError, EvalError):
    """Bad link settings, or a link that could not be made."""


@dataclass(frozen=True)
class LinkSettings:
    """One emulated link (the same in both directions)."""

    rtt_ms: float = 0.0  # round-trip delay added, milliseconds (half each way), >= 0
    loss: float = 0.0  # fraction of packets dropped, each way, independently: 0 <= loss < 1
    mbit: float | None = None  # rate each way, Mbit/s (10^6 bit/s), > 0; None: unlimited
    queue_ms: float = 100.0  # a rate-limited link's queue, milliseconds of sending at `mbit`, >= 0

    def check(self) -> "LinkSettings":
        """self, or LinkError naming the first bad field."""
        if not (math.isfinite(self.rtt_ms) and self.rtt_ms >= 0):
            raise LinkError(f"link rtt_ms must be >= 0 ms, got {self.rtt_ms}")
        if not (0 <= self.loss < 1):
            raise LinkError(f"link loss must be a fraction in [0, 1), got {self.loss}")
        if self.mbit is not None and not (math.isfinite(self.mbit) and self.mbit > 0):
            raise LinkError(f"link mbit must be > 0 Mbit/s (or None: unlimited), got {self.mbit}")
        if not (math.isfinite(self.queue_ms) and self.queue_ms >= 0):
            raise LinkError(f"link queue_ms must be >= 0 ms, got {self.queue_ms}")
        return self

    def label(self) -> str:
        """e.g. 'rtt 100 ms, loss 1%, 5 Mbit/s'."""
        rate = "unlimited" if self.mbit is None else f"{self.mbit:g} Mbit/s"
        return f"rtt {self.rtt_ms:g} ms, loss {100 * self.loss:g}%, {rate}"

    def relay_arguments(self) -> list[str]:
        """The settings as psao.eval.linkrelay's options."""
        rate = [] if self.mbit is None else ["--mbit", repr(self.mbit)]
        return ["--rtt-ms", repr(self.rtt_ms), "--loss", repr(self.loss), *rate, "--queue-ms", repr(self.queue_ms)]


@dataclass
class Link:
    """A namespace joined to the host by an impaired link: run commands in it, serve on host_address.
    Processes started in the namespace must be stopped before the link's with block ends."""

    namespace: str
    host_address: str  # the host's end: a server a client in the namespace reaches listens here
    ns_address: str  # the namespace's end
    settings: LinkSettings
    host_device: str  # the host's TUN device (the namespace's is inside it)
    # after the with block: per direction ("down": host to namespace, "up"), packets "forwarded",
    # "dropped_loss" and "dropped_queue" by the forwarder (empty if it could not say)
    counters: dict = field(default_factory=dict)
    _relay: subprocess.Popen | None = field(default=None, repr=False)

    def change(self, settings: LinkSettings) -> dict:
        """The link's settings from now on (packets on their way keep their delay); the forwarder's packet
        counts (as `counters`) since the link was made or last changed. LinkError: bad settings."""
        settings.check()
        if self._relay is None or self._relay.poll() is not None:
            raise LinkError("the link is gone")
        fields = {"rtt_ms": settings.rtt_ms, "loss": settings.loss, "mbit": settings.mbit, "queue_ms": settings.queue_ms}
        self._relay.stdin.write(json.dumps(fields) + "\n")
        self._relay.stdin.flush()
        answer = json.loads(_readline(self._relay, READY_TIMEOUT_S) or "{}")
        if "error" in answer or not answer:
            raise LinkError(f"the link forwarder refused {settings.label()}: {answer.get('error', 'no answer')}")
        self.settings = settings
        return answer

    @property
    def prefix(self) -> list[str]:
        """What runs a command inside the namespace (`ip netns exec NAME`; the process keeps its pid)."""
        return ["ip", "netns", "exec", self.namespace]

    def command(self, args: list[str]) -> list[str]:
        """`args` run inside the namespace."""
        return [*self.prefix, *map(str, args)]


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    proc = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=IP_TIMEOUT_S)
    if check and proc.returncode != 0:
        raise LinkError(f"ip {' '.join(args)} failed: {proc.stderr.strip() or proc.returncode}")
    return proc


def namespaces() -> list[str]:
    """Names of the network namespaces that `ip netns` knows."""
    out = _ip("netns", "list", check=False).stdout
    return [line.split()[0] for line in out.splitlines() if line.strip()]


def links_unavailable() -> str | None:
    """Why impaired links cannot be made here (one line), or None when they can."""
    if sys.platform != "linux":
        return "impaired links need Linux network namespaces"
    if os.geteuid() != 0:
        return "impaired links need root (network namespaces, TUN devices)"
    if shutil.which("ip") is None:
        return "impaired links need the `ip` command (iproute2)"
    if not os.access("/dev/net/tun", os.R_OK | os.W_OK):
        return "impaired links need /dev/net/tun"
    probe = f"{NS_PREFIX}{_owner()}-probe"
    try:
        made = _ip("netns", "add", probe, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"impaired links: `ip netns add` failed ({exc})"
    if made.returncode != 0:
        return f"impaired links: `ip netns add` failed ({made.stderr.strip() or made.returncode})"
    _ip("netns", "del", probe, check=False)
    return None


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _owner() -> str:
    """'<pid namespace>-<pid>' of this process: the pid namespace's inode tells whether a pid in another
    link's name is one this process can see (another container's processes are not)."""
    return f"{os.stat('/proc/self/ns/pid').st_ino}-{os.getpid()}"


def remove_stale_namespaces() -> list[str]:
    """Delete the link namespaces made in this pid namespace by a process that is gone; their names."""
    gone = []
    ours = _owner().split("-")[0]
    for name in namespaces():
        m = re.fullmatch(re.escape(NS_PREFIX) + r"(\d+)-(\d+)-\w+", name)
        if m and m.group(1) == ours and not _pid_alive(int(m.group(2))):
            _ip("netns", "del", name, check=False)
            gone.append(name)
    return gone


def _used_addresses() -> set[str]:
    """IPv4 addresses on the host's interfaces."""
    out = _ip("-o", "-4", "addr", "show", check=False).stdout
    return set(re.findall(r"inet (\d+\.\d+\.\d+\.\d+)", out))


def _subnet(index: int) -> tuple[str, str]:
    """(host address, namespace address) of /30 number `index` in SUBNET_BASE's /16."""
    base = index * 4
    a, b = SUBNET_BASE
    return f"{a}.{b}.{base >> 8}.{(base & 255) + 1}", f"{a}.{b}.{base >> 8}.{(base & 255) + 2}"


def _pick_subnet(n: int) -> tuple[str, str]:
    """A /30 of this process (pid) and link number `n` whose addresses no interface here holds."""
    used = _used_addresses()
    start = (os.getpid() * 16 + n) % SUBNETS
    for k in range(SUBNETS):
        host, ns = _subnet((start + k) % SUBNETS)
        if host not in used and ns not in used:
            return host, ns
    raise LinkError(f"no free /30 left in {SUBNET_BASE[0]}.{SUBNET_BASE[1]}.0.0/16")


def _start_relay(settings: LinkSettings, host_dev: str, ns_dev: str) -> subprocess.Popen:
    """The forwarder, once it has created both devices (it prints `ready`)."""
    src = str(Path(__file__).resolve().parents[2])
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (src, os.environ.get("PYTHONPATH", "")) if p))
    proc = subprocess.Popen([sys.executable, "-m", "psao.eval.linkrelay", host_dev, ns_dev,
                             *settings.relay_arguments()], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True, env=env)
    try:
        line = _readline(proc, READY_TIMEOUT_S)
    except BaseException:
        _stop(proc)
        raise
    if line.strip() != "ready":
        _stop(proc)
        raise LinkError(f"link forwarder did not start: {(proc.stderr.read() or line).strip()[-300:]}")
    return proc


def _readline(proc: subprocess.Popen, timeout: float) -> str:
    import selectors

    with selectors.DefaultSelector() as sel:
        sel.register(proc.stdout, selectors.EVENT_READ)
        if not sel.select(timeout):
            raise LinkError(f"link forwarder said nothing within {timeout:g} s")
    return proc.stdout.readline()


def _stop(proc: subprocess.Popen) -> dict:
    """Stop the forwarder (its stdin closed, then SIGKILL); its last packet counts (empty if it printed none)."""
    counters = {}
    if proc.poll() is None:
        try:
            out, _ = proc.communicate(timeout=5.0)
            lines = out.strip().splitlines()
            counters = json.loads(lines[-1]) if lines and lines[-1].startswith("{") else {}
        except (subprocess.TimeoutExpired, ValueError):
            pass
    if proc.poll() is None:
        proc.kill()
    proc.wait(10)
    for f in (proc.stdin, proc.stdout, proc.stderr):
        if f:
            f.close()
    return counters


@contextlib.contextmanager
def impaired_link(settings: LinkSettings = LinkSettings()):
    """A Link: a new namespace joined to the host by a link with `settings` (see the module); everything
    it made is removed on exit, also after errors. LinkError: bad settings, or the link could not be made."""
    settings.check()
    if why := links_unavailable():
        raise LinkError(why)
    remove_stale_namespaces()
    n = next(_counter)
    pid = os.getpid()
    name = f"{NS_PREFIX}{_owner()}-{n}"
    host_dev, ns_dev = f"pl{pid}h{n}"[:15], f"pl{pid}n{n}"[:15]
    host_ip, ns_ip = _pick_subnet(n)
    relay = link = None
    _ip("netns", "add", name)
    try:
        relay = _start_relay(settings, host_dev, ns_dev)
        _ip("link", "set", ns_dev, "netns", name)
        _ip("addr", "add", f"{host_ip}/30", "dev", host_dev)
        _ip("link", "set", host_dev, "up")
        _ip("-n", name, "addr", "add", f"{ns_ip}/30", "dev", ns_dev)
        _ip("-n", name, "link", "set", ns_dev, "up")
        _ip("-n", name, "link", "set", "lo", "up")
        link = Link(name, host_ip, ns_ip, settings, host_dev, _relay=relay)
        yield link
    finally:
        try:
            if relay is not None:
                counters = _stop(relay)  # its TUN devices go with it
                if link is not None:
                    link.counters = counters
        finally:
            _ip("netns", "del", name, check=False)
