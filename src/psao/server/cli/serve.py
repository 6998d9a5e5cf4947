"""`psao serve SCENE`: bake a scene (or load a baked grid) and stream its AO grid to clients.

A thin layer over psao.Server (psao.server.embed): the flags become ServerSettings, SIGINT and SIGTERM stop
it, and --json prints the run's totals once it stopped."""
from __future__ import annotations

import argparse
import dataclasses
import ipaddress
import json
import logging
import os
import signal
import sys
from pathlib import Path

from psao.protocol.codecs import CODEC_NAMES, codec_name
from psao.protocol.updates import LAYOUT_NAMES, layout_name
from psao.options import default
from psao.server.cli.bake import add_bake_arguments, bake_settings
from psao.server.embed import Server, ServerSettings
from psao.server.tick.budget import TICK_HZ_RANGE, BudgetSettings
from psao.server.errors import ConfigError
from psao.server.net.webpage import EXAMPLES
from psao.server.tick.progressive import ProgressiveSettings
from psao.server.settings import FanoutSettings, ServeSettings


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", help="builtin:NAME, a scene .toml, or a mesh file")
    p.add_argument("--host", default=default(ServeSettings, "host"), help="interface to listen on (loopback only by default)")
    p.add_argument("--port", type=int, default=default(ServeSettings, "port"), help="TCP port (0 picks a free one)")
    add_bake_arguments(p)
    p.add_argument("--grid", type=Path, default=None, help="serve this baked grid (.npz from psao bake) instead of baking")
    p.add_argument("--codec", choices=tuple(CODEC_NAMES), default=codec_name(default(ServeSettings, "codec")),
                   help="payload compression: zstd-stream (one zstd stream per connection), zstd (every message "
                        "on its own, as the paper), lz4 or none; the names psao client --codecs takes")
    p.add_argument("--layout", choices=tuple(LAYOUT_NAMES), default=layout_name(default(ServeSettings, "layout")),
                   help="update layout: packed or the paper's plain uint32 layout")
    p.add_argument("--stats-json", type=Path, default=None, metavar="FILE",
                   help="append one JSON line per tick: points considered/traced/changed, dirty rows, stage times, bytes")
    p.add_argument("--json", action="store_true",
                   help="when stopped, print one JSON object as the last line: the run's totals (connections, "
                        "bytes, updates, ...) and tick_stats (ticks, ticks/s, mean/p95/max tick ms, bytes, cells "
                        "and points traced/changed summed over the ticks, peak clients)")
    p.add_argument("--tick-hz", type=float, default=default(ServeSettings, "tick_hz"),
                   help="server ticks per second, {:g}..{:g}".format(*TICK_HZ_RANGE))
    p.add_argument("--token", default="",
                   help="clients must present this token (visible in the process list: prefer PSAO_TOKEN or --token-file)")
    p.add_argument("--token-file", type=Path, default=None, metavar="FILE",
                   help="read the clients' token from FILE (first line); the environment variable PSAO_TOKEN also works")
    p.add_argument("--allow-edits", action="store_true",
                   help="accept SceneEdit (move an instance for everyone) from clients presenting the edit token, "
                        "read from PSAO_EDIT_TOKEN or --edit-token-file, and re-trace what an edit moves through the "
                        "server tick (also with --animate); edits are refused otherwise")
    p.add_argument("--edit-token-file", type=Path, default=None, metavar="FILE",
                   help="read the edit token from FILE (first line)")
    p.add_argument("--allow-origin", action="append", default=[], metavar="ORIGIN",
                   help="a web page origin (e.g. https://example.org) allowed to open a websocket, besides this "
                        "server's own page; repeatable. Clients without an Origin header are always allowed")
    p.add_argument("--web-example", choices=sorted(EXAMPLES), default="",
                   help="serve this example page at / instead of the PSAO page (three: the scene in three.js with "
                        "PSAO beside three.js's GTAOPass and SAOPass; it is also at /three/ always)")
    p.add_argument("--tls-cert", type=Path, default=None, metavar="PEM", help="serve wss:// with this certificate chain")
    p.add_argument("--tls-key", type=Path, default=None, metavar="PEM", help="the private key of --tls-cert")
    p.add_argument("--max-clients", type=int, default=default(ServeSettings, "max_clients"), metavar="N",
                   help="open connections at most; more are refused with SERVER_FULL")
    p.add_argument("--send-buffer", type=int, default=default(ServeSettings, "send_buffer"), metavar="BYTES",
                   help="kernel send buffer per client: a slow client's ticks fold into one update beyond it")
    p.add_argument("--client-mbit", type=float, default=default(FanoutSettings, "client_mbit"), metavar="MBIT",
                   help="the most Mbit/s sent to each client (its messages paced; its own Updates carry the cells "
                        "nearest its camera first and merge the rest later); default: no cap")
    p.add_argument("--no-adapt-rate", action="store_true",
                   help="do not pace a client to its link's estimated throughput (by default a client whose link "
                        "queues is sent what the link carries, the cells nearest its camera first)")
    p.add_argument("--no-cull", action="store_true",
                   help="send every client every change; by default a client gets the cells in its extended view "
                        "and the rest when they enter it")
    p.add_argument("--animate", action="store_true",
                   help="run the server tick: animate the scene, re-trace the points it affects in the clients' views")
    p.add_argument("--tick-rays", type=int, default=None, metavar="R",
                   help="with --animate or --progressive: rays per point per tick round (a divisor of --rays: one slice "
                        f"of the point's ray set), accumulated over ticks up to --rays ({default(BudgetSettings, 'round_rays')} without it); --progressive also traces its "
                        "first grid with them")
    p.add_argument("--tick-budget-ms", type=float, default=default(BudgetSettings, "budget_ms"), metavar="MS",
                   help="with --animate or --progressive: milliseconds of tracing per tick, within (0, 1000/tick-hz] "
                        f"({100 * default(BudgetSettings, 'headroom'):g}%% of the tick period less the other stages without "
                        "it); waiting points queue")
    p.add_argument("--progressive", action=argparse.BooleanOptionalAction, default=None,
                   help="progressive start (the default, except with --grid or --test-edits): stream a coarse first "
                        "grid (--first-points points traced with --tick-rays) as soon as it is baked (with --animate "
                        "its movers posed and traced from the first tick), replace it by the full grid traced with "
                        "--tick-rays when that is baked (clients reconnect to it), then refine that to --rays in the "
                        "ticks' spare budget; --no-progressive: the full grid traced with --rays first")
    p.add_argument("--first-points", type=int, default=default(ProgressiveSettings, "first_points"), metavar="P",
                   help="with --progressive: points of the coarse first grid (uniform, no elimination, no buried-"
                        "surface test); 0, or a full grid under "
                        f"{default(ProgressiveSettings, 'min_ratio'):g}x that, streams the full grid first")
    p.add_argument("--test-edits", type=int, default=None, metavar="K",
                   help="test hook: edit about K points per tick (AO, moves, frees and allocations; none without it)")
    p.add_argument("--digest-log", type=Path, default=None,
                   help="append a state digest (jsonl) after every message that left nothing pending (tests)")


# what ServerSettings.check calls a setting in its refusals: the flag that sets it
FLAGS = {"animate": "--animate", "progressive": "--progressive", "allow_edits": "--allow-edits", "grid": "--grid",
         "test_edits": "--test-edits", "first_points": "--first-points", "tick_rays": "--tick-rays",
         "tick_budget_ms": "--tick-budget-ms", "cluster": "--cluster"}


def server_settings(args) -> ServerSettings:
    """The flags as psao.Server's settings, checked (ConfigError naming the flag) before anything listens."""
    if args.test_edits is not None and args.test_edits < 0:
        raise ConfigError(f"--test-edits must be >= 0, got {args.test_edits}")
    edit_token = secret("edit token", "", "PSAO_EDIT_TOKEN", args.edit_token_file) if args.allow_edits else ""
    serve = ServeSettings(host=args.host, port=args.port, tick_hz=args.tick_hz, codec=CODEC_NAMES[args.codec],
                          layout=LAYOUT_NAMES[args.layout],
                          token=secret("token", args.token, "PSAO_TOKEN", args.token_file),
                          allow_edits=args.allow_edits, edit_token=edit_token, max_clients=args.max_clients,
                          allow_origins=tuple(args.allow_origin), tls_cert=args.tls_cert, tls_key=args.tls_key,
                          web_example=args.web_example, digest_log=args.digest_log, stats_json=args.stats_json,
                          send_buffer=args.send_buffer,
                          fanout=FanoutSettings(cull=not args.no_cull, client_mbit=args.client_mbit,
                                                adapt_rate=not args.no_adapt_rate))
    serve.check()
    progressive = args.progressive
    if progressive is None:  # on, unless the grid comes from a file or the test hook edits it
        progressive = args.grid is None and not args.test_edits
    s = ServerSettings(serve=serve, bake=bake_settings(args), animate=args.animate, progressive=progressive,
                       first_points=args.first_points, tick_rays=args.tick_rays, tick_budget_ms=args.tick_budget_ms,
                       tick_at_rest=False, grid=args.grid, test_edits=args.test_edits, fast_scene_first=True)
    s.check(FLAGS)
    return s


def secret(what: str, given: str, env: str, path: Path | None) -> str:
    """A token from the command line, else from FILE's first line, else from the environment."""
    if given:
        return given
    if path is not None:
        try:
            lines = path.read_text(encoding="utf-8").splitlines()
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError(f"cannot read the {what} from {path}: {getattr(exc, 'strerror', None) or exc}") from None
        if not lines or not lines[0].strip():
            raise ConfigError(f"{path} holds no {what} (empty first line)")
        return lines[0].strip()
    return os.environ.get(env, "").strip()


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def setup_logging() -> None:
    if sys.stderr.isatty():
        from rich.logging import RichHandler
        handler: logging.Handler = RichHandler(show_path=False, log_time_format="%H:%M:%S")
        fmt = "%(message)s"
    else:
        handler = logging.StreamHandler(sys.stderr)
        fmt = "%(asctime)s psao serve: %(message)s"
    handler.setFormatter(logging.Formatter(fmt, datefmt="%H:%M:%S"))
    log = logging.getLogger("psao")
    log.handlers[:] = [handler]
    log.setLevel(logging.INFO)
    log.propagate = False


def run(args: argparse.Namespace) -> int:
    """Serve until SIGINT or SIGTERM: psao.Server with the flags' settings; the port is bound before the
    scene is loaded, and a failure of the start-up stops the server and is raised here."""
    setup_logging()
    settings = server_settings(args)
    if not settings.serve.token and not is_loopback(settings.serve.host):
        logging.getLogger("psao.serve").warning(
            "listening on %s without a token: anyone who can reach this machine may connect "
            "(set PSAO_TOKEN or --token-file)", settings.serve.host)
    server = Server(args.scene, settings)
    got: list[str] = []

    def on_signal(signum, _frame) -> None:
        got.append(signal.Signals(signum).name)
        server.request_stop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)
    server.start(wait=False)
    server.wait()
    c = server.service.counters
    stopped_by = got[0] if got else "request"
    logging.getLogger("psao.serve").info(
        "stopped on %s after %d ticks: %d connections, %d rejected, %.1f MB sent",
        stopped_by, c.ticks, c.connections, c.rejected, c.bytes_out / 1e6)
    if args.json:
        totals = {k: v for k, v in dataclasses.asdict(c).items() if isinstance(v, (int, float))}
        print(json.dumps({"stopped_by": stopped_by, **totals, "tick_stats": server.service.summary.to_dict()}),
              flush=True)
    return 0
