"""`psao serve SCENE`: bake a scene (or load a baked grid) and stream its AO grid to clients."""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import ipaddress
import json
import logging
import os
import signal
import socket
import sys
from pathlib import Path

from psao.protocol.codecs import CODEC_NAMES, codec_name
from psao.protocol.updates import LAYOUT_NAMES, layout_name
from psao.options import default
from psao.server.cli.bake import add_bake_arguments, bake_settings
from psao.server.tick.budget import TICK_HZ_RANGE, BudgetSettings, fitting_round_rays
from psao.server.errors import ConfigError
from psao.server.net.webpage import EXAMPLES
from psao.server.tick.progressive import ProgressiveSettings
from psao.server.settings import BakeSettings, FanoutSettings, ServeSettings, TickSettings


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


def _budget(args) -> BudgetSettings:
    """The tick's time budget from --tick-hz, --tick-budget-ms and --tick-rays (without it the default round,
    or the largest divisor of --rays below it), checked against --rays (BudgetSettings.check: ConfigError)."""
    round_rays = args.tick_rays if args.tick_rays is not None else fitting_round_rays(args.rays)
    b = BudgetSettings(budget_ms=args.tick_budget_ms, round_rays=round_rays)
    b.check_rate(args.tick_hz)
    b.check(args.rays)
    return b


def _check_modes(args) -> None:
    """Resolve --progressive's default and refuse the combinations that cannot run, before listening."""
    if args.progressive is None:  # on, unless the grid comes from a file or the test hook edits it
        args.progressive = args.grid is None and not args.test_edits
    if not (args.animate or args.progressive or args.allow_edits):
        if args.tick_budget_ms is not None or args.tick_rays is not None:
            raise ConfigError("--tick-budget-ms and --tick-rays need --animate, --progressive or --allow-edits (no "
                              "tick runs otherwise)")
        return
    flag = "--animate" if args.animate else "--progressive" if args.progressive else "--allow-edits"
    if args.grid is not None:
        raise ConfigError(f"{flag} bakes the scene itself: it cannot serve a --grid file")
    if args.test_edits:
        raise ConfigError(f"{flag} and --test-edits both edit the grid: choose one")
    if args.first_points < 0:
        raise ConfigError(f"--first-points must be >= 0, got {args.first_points}")
    _budget(args)


def _ticking(args, bake_with: BakeSettings, scene, report=None):
    """(grid, tick) with the time-budgeted server tick on a fresh bake (it needs the bake's point sets):
    animating the scene with --animate, refining a first few-ray grid with --progressive, re-tracing what
    scene edits move with --allow-edits. `report(fraction, text)`: the bake's progress."""
    from psao.server.bake import bake_scene
    from psao.server.tick.server_tick import AtRest, ServerTick

    budget = _budget(args)
    bake_rays = budget.round_rays if args.progressive else args.rays
    bake = bake_scene(scene, dataclasses.replace(bake_with, rays=bake_rays), report=report)
    # The bake's AO counts as that many rays of every point's history: with --rays it is converged, with
    # --progressive the ticks' spare budget refines it.
    # With --progressive the bake's tracer (its cluster with --cluster) also refines waiting static points,
    # in batches, beside the ticks.
    settings = TickSettings.serving(bake_with, budget)
    refiner = None
    if args.progressive:  # the bake's tracer (a cluster's, or local worker processes) refines beside the ticks
        from psao.server.tick.refine import BackgroundTracer, ClusterRefiner
        refiner = ClusterRefiner(bake.tracer if bake_with.cluster is not None else BackgroundTracer(bake.tracer))
    # closes the bake's tracer (unless the refiner keeps its cluster), starts its own
    tick = ServerTick(bake, settings, close_bake_tracer=refiner is None, refiner=refiner, tick_hz=args.tick_hz)
    if not args.animate:
        tick = AtRest(tick)
    logging.getLogger("psao.serve").info(
        "baked %s at N=%g with %d rays: %d points; server tick on (%d rays per point per round, up to %d)",
        scene.name, bake.stats["density"], bake_rays, bake.stats["points_kept"], budget.round_rays, args.rays)
    return tick.grid, tick


def _coarse_first(args, bake_with: BakeSettings, scene, report=None):
    """(coarse first grid, its tick or None) when --progressive starts from a coarse grid
    (psao.server.tick.progressive), else None. With --animate a server tick of its own poses and traces the
    movers on it from the first tick; without, the coarse grid stands still until the full one comes."""
    from psao.server.bake import bake_scene
    from psao.server.tick.progressive import coarse_bake_settings, wants_coarse_grid
    from psao.server.tick.server_tick import ServerTick
    from psao.server.tracer.embree import numpy_rays

    if not args.progressive or args.allow_edits or bake_with.cluster is not None:
        return None
    budget = _budget(args)
    if not wants_coarse_grid(scene, bake_with, ProgressiveSettings(first_points=args.first_points)):
        return None
    with numpy_rays():  # its few rays stay in this process and thread (workers=1): no worker processes to start
        coarse = bake_scene(scene, coarse_bake_settings(bake_with, args.first_points, budget.round_rays),
                            report=report)
    logging.getLogger("psao.serve").info(
        "coarse first grid of %s: %d points with %d rays in %.1f s; the full grid (N=%s) is baked behind it",
        scene.name, coarse.stats["points_kept"], budget.round_rays,
        sum(v for k, v in coarse.stats.items() if k.startswith("seconds_")),
        f"{bake_with.density:g}" if bake_with.density else "default")
    if not args.animate:
        coarse.tracer.close()
        return coarse.grid, None
    tick = ServerTick(coarse, TickSettings.serving(bake_with, budget), close_bake_tracer=True)
    return tick.grid, tick


def _grid_file(args, bake_with: BakeSettings):
    """(grid, scene hash) of --grid FILE, read before the server listens (a bad file is one line at once),
    or None without --grid."""
    from psao.server.grid import Grid

    if args.grid is None:
        return None
    if bake_with.cluster is not None:
        raise ConfigError("--cluster traces a bake: it has nothing to do with a --grid file")
    grid, scene_hash, _meta = Grid.load(args.grid)
    return grid, scene_hash


def _load(args, bake_with: BakeSettings, scene, from_file=None, report=None):
    """The grid from a bake, or `from_file` (_grid_file's) checked against the scene."""
    from psao.server.bake import bake_scene

    if from_file is not None:
        grid, scene_hash = from_file
        if scene_hash and scene_hash != scene.content_hash():
            raise ConfigError(f"{args.grid} was baked from another scene than {args.scene}")
        if len(grid.instances) != len(scene.instances):
            raise ConfigError(f"{args.grid} has {len(grid.instances)} instances, {args.scene} has {len(scene.instances)}")
        return grid
    result = bake_scene(scene, bake_with, report=report)
    result.tracer.close()
    logging.getLogger("psao.serve").info(
        "baked %s at N=%g: %d points in %d cells", scene.name, result.stats["density"], result.stats["points_kept"],
        result.stats["cells"])
    return result.grid


def _import_bake_modules() -> None:
    """Import what the bake needs (scipy, Embree, the tracer) ahead of it. A failure is left to the bake's
    own import, which raises it where it is reported."""
    with contextlib.suppress(Exception):
        import psao.server.bake  # noqa: F401
        import psao.server.tick.server_tick  # noqa: F401
        import psao.server.tracer.embree  # noqa: F401


def _warn_failed(what: str):
    """A done-callback for a background future: its failure (not Stopped) as one warning line."""
    def done(future) -> None:
        exc = future.exception()
        if exc is not None and type(exc).__name__ != "Stopped":
            logging.getLogger("psao.serve").warning("%s failed: %s", what, exc)
    return done


def _start_up(args, bake_with: BakeSettings, from_file=None):
    """The start-up's work (progressive.Startup), on its own thread once the service listens: load the scene
    and hand its hash and blob over, serve a coarse first grid when progressive start makes one, then the
    full grid with its tick."""
    def work(startup) -> None:
        import concurrent.futures

        import numpy as np

        from psao.protocol.session import scene_hash_bytes
        from psao.scene import load_scene
        from psao.server.net.scene_export import SceneExportSettings, scene_blob
        from psao.server.net.service import StaticTransforms
        from psao.server.tick.testhook import RandomEdits

        background = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="psao-startup")
        background.submit(_import_bake_modules)  # beside the scene's loading
        startup.step(0.0, f"loading {args.scene}")
        scene = load_scene(args.scene)
        # Clients that ask for the scene now get it compressed fast; its strongest zstd level, which takes a
        # while on a large scene, is compressed after the coarse grid, beside the full bake, and sent from then on.
        startup.scene(scene_hash_bytes(scene.content_hash()), scene_blob(scene, level=SceneExportSettings.first_zstd_level))
        resting = StaticTransforms(np.array([i.transform for i in scene.instances], dtype=np.float32))
        startup.step(0.0, "baking the coarse first grid")
        coarse = _coarse_first(args, bake_with, scene, lambda f, text: startup.step(f, f"coarse grid {text}"))
        if coarse is not None:
            grid, tick = coarse
            startup.serve(grid, tick, tick.transforms if tick is not None else resting, final=False)
        strong = background.submit(lambda: startup.scene_blob(scene_blob(scene)))
        strong.add_done_callback(_warn_failed("compressing the scene file at its strongest level"))
        background.shutdown(wait=False)
        startup.step(0.0, "baking the full grid")
        report = lambda f, text: startup.step(f, f"full grid {text}")  # noqa: E731
        if args.animate or args.progressive or args.allow_edits:  # the server tick refines, animates, re-traces edits
            grid, tick = _ticking(args, bake_with, scene, report)
            startup.serve(grid, tick, tick.transforms, final=True)
        else:
            grid = _load(args, bake_with, scene, from_file, report)
            tick = RandomEdits(args.test_edits, seed=args.seed) if args.test_edits else None
            startup.serve(grid, tick, resting, final=True)
    return work


def _settings(args):
    codec = CODEC_NAMES[args.codec]
    if args.test_edits is not None and args.test_edits < 0:
        raise ConfigError(f"--test-edits must be >= 0, got {args.test_edits}")
    edit_token = secret("edit token", "", "PSAO_EDIT_TOKEN", args.edit_token_file) if args.allow_edits else ""
    s = ServeSettings(host=args.host, port=args.port, tick_hz=args.tick_hz, codec=codec,
                      layout=LAYOUT_NAMES[args.layout], token=secret("token", args.token, "PSAO_TOKEN", args.token_file),
                      allow_edits=args.allow_edits, edit_token=edit_token, max_clients=args.max_clients,
                      allow_origins=tuple(args.allow_origin), tls_cert=args.tls_cert, tls_key=args.tls_key, web_example=args.web_example,
                      digest_log=args.digest_log, stats_json=args.stats_json, send_buffer=args.send_buffer,
                      fanout=FanoutSettings(cull=not args.no_cull, client_mbit=args.client_mbit,
                                            adapt_rate=not args.no_adapt_rate))
    s.check()
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


def bind_listener(host: str, port: int) -> socket.socket:
    """The listening socket, bound now (before any bake) so a busy port fails in a second, not after it."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
        family, kind, proto, _, addr = infos[0]
        sock = socket.socket(family, kind, proto)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(addr)
            sock.listen(128)
        except OSError:
            sock.close()
            raise
    except OSError as exc:  # the port is taken, the address is not ours, ...
        raise ConfigError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from None
    sock.setblocking(False)
    return sock


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
    import asyncio

    from psao.server.net.service import Service, tls_context
    from psao.server.tick.progressive import StartupProgress

    setup_logging()
    settings = _settings(args)
    bake = bake_settings(args)  # a bad number fails before anything listens
    _check_modes(args)
    from_file = _grid_file(args, bake)
    if not settings.token and not is_loopback(settings.host):
        logging.getLogger("psao.serve").warning(
            "listening on %s without a token: anyone who can reach this machine may connect "
            "(set PSAO_TOKEN or --token-file)", settings.host)
    if settings.tls_cert is not None:
        tls_context(settings.tls_cert, settings.tls_key)  # a bad certificate fails before the bake
    listener = bind_listener(settings.host, settings.port)
    progress = StartupProgress(f"loading {args.scene}")
    # It listens from here on: connections wait for the scene and a grid, told the start-up's state.
    service = Service(None, None, settings, progress=progress)
    try:
        return asyncio.run(_serve(service, listener, args.json, _start_up(args, bake, from_file), progress))
    finally:
        listener.close()


async def _serve(service, listener: socket.socket, as_json: bool, work, progress) -> int:
    """Serve until SIGINT or SIGTERM, the start-up's `work` on its own thread from the moment the service
    listens; a failure of it stops the server and is raised here."""
    import asyncio

    from psao.server.tick.progressive import Startup

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    got: list[str] = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, lambda s=sig: (got.append(s.name), stop.set()))
    failed: list[BaseException] = []
    startup = Startup(service, work, lambda exc: (failed.append(exc), loop.call_soon_threadsafe(stop.set)), progress)
    try:
        await service.run(stop, ready=lambda port: startup.start(), sock=listener)
    finally:
        startup.close()
    if failed:
        raise failed[0]
    c = service.counters
    logging.getLogger("psao.serve").info(
        "stopped on %s after %d ticks: %d connections, %d rejected, %.1f MB sent",
        got[0] if got else "request", c.ticks, c.connections, c.rejected, c.bytes_out / 1e6)
    if as_json:
        totals = {k: v for k, v in dataclasses.asdict(c).items() if isinstance(v, (int, float))}
        print(json.dumps({"stopped_by": got[0] if got else "request", **totals, "tick_stats": service.summary.to_dict()}),
              flush=True)
    return 0
