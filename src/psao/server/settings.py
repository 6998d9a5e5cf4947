"""Every server-side setting, its default and its range check, in one place: points, grid, tracer, gap
fill, bake, bake probes, tick, service (the tick's time budget and the tick rate's range are
src/psao/server/tick/budget.py's BudgetSettings and TICK_HZ_RANGE).

Each default is written once: a setting that several stages share (rays, seed, tracer, workers, spawn
ratio, sampling, tick rate) takes its default from the dataclass that owns it (how many points a bake gets by
default is src/psao/server/points/sampling.py's scale-aware density), and the command line (`psao bake`,
`psao serve`, `psao bench`) reads its defaults from these dataclasses (src/psao/options.py). Each range
is checked once, by the owning dataclass's check() (TickSettings.check calls BudgetSettings.check); the
command line builds the dataclasses and calls it, so a bad option gets that one-line ConfigError. This
module imports only numpy, src/psao/protocol/ (codecs, layouts, limits) and the light server modules
errors, tick.budget and points.sampling, so `psao serve --help` reads it without loading Embree, Warp,
scipy or websockets.
"""
from __future__ import annotations

import math

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from psao.protocol.codecs import PAPER_ZSTD, Codec, ZstdSettings
from psao.protocol.limits import DEFAULT_LIMITS, Limits
from psao.protocol.updates import Layout
from psao.server.tick.budget import DEFAULT_TICK_HZ, BudgetSettings, check_tick_hz
from psao.server.errors import ConfigError, GridError, TracerError
from psao.server.points.sampling import SamplingSettings, check_detail_factor


@dataclass
class TraceSettings:
    rays: int = 128  # rays per point
    ao_distance: float = 1.0  # world units
    seed: int = 0
    workers: int = 0  # tracer processes; 0 = all cores
    chunk_points: int = 2048  # points per work item (bounds memory: chunk * rays directions)
    local_rays: int = 16384  # calls with fewer rays than this trace in the calling process (a hand-over to
    # worker processes costs more than tracing them, the more so on a busy machine)
    slices: int = 1  # the `rays`-ray set is dealt into this many interleaved slices (rays j = slice mod slices);
    slice: int = 0  # only this one is traced: the slices of one set together are exactly its full trace

    @property
    def rays_traced(self) -> int:
        """Rays per point this call traces: its slice of the `rays`-ray set."""
        return len(range(self.slice, self.rays, self.slices))


@dataclass
class PointSettings:
    density: float = 256.0  # N: final points per world unit^2 (after elimination); spawn_ratio * N spawned
    min_points: int = 64  # final points per instance and side, so small objects are never empty
    seed: int = 0
    alpha: float = 8.0  # Yuksel's weight exponent
    spawn_ratio: float = 2.0  # spawned / kept; the paper removes half (4 leaves fewer holes, slower)
    weight_limiting: bool = True  # Yuksel's weight limiting (beta, gamma below), as in his reference code
    beta: float = 0.65  # weight limiting: d_min = 2 r_max * (1 - (kept / spawned)^gamma) * beta
    gamma: float = 1.5
    # Neighbours whose normals make a cosine <= this do not weigh on each other, so the two faces of a thin
    # slab (cosine -1) keep their own density instead of sharing one. -1.0 or less turns the gate off.
    normal_cos_min: float = -0.5
    detail_factor: int = 1  # most times `density` a small triangle gets (sampling.level_counts); 1: N everywhere
    # per instance, the factor on `density` its own sampling scale asks for (sampling.instance_factors); empty:
    # `density` on every instance
    instance_factors: tuple[float, ...] = ()

    def check(self) -> None:
        """ConfigError for a setting out of range, naming it."""
        if not np.isfinite(self.density) or self.density <= 0:
            raise ConfigError(f"density must be > 0, got {self.density}")
        check_detail_factor(self.detail_factor)
        if self.min_points < 1:
            raise ConfigError(f"min_points must be >= 1, got {self.min_points}")
        if not self.spawn_ratio >= 1.0:
            raise ConfigError(f"spawn_ratio must be >= 1, got {self.spawn_ratio}")
        if not self.alpha > 0:
            raise ConfigError(f"alpha must be > 0, got {self.alpha}")


@dataclass
class GridSettings:
    radius_factor: float = 2.0  # interpolation radius r = radius_factor * Poisson radius of the instance
    cell_factor: float = 2.0  # cell size s = cell_factor * r; must be >= 2 (DESIGN invariant)
    bucket_factor: float = 4.0  # buckets = next_pow2(bucket_factor * cells / 8), as in the paper
    pool_headroom: float = 0.25  # spare cell slots beyond the initial allocation (fraction)

    def __post_init__(self):
        if self.cell_factor < 2.0:
            raise GridError(f"cell_factor must be >= 2 so the 2x2x2 lookup sees every point within r, got {self.cell_factor}")
        if self.radius_factor <= 0 or self.bucket_factor <= 0:
            raise GridError("radius_factor and bucket_factor must be > 0")


@dataclass
class GapFillSettings:
    passes: int = 0  # candidate rounds; 0 = off (the paper's points only), 4 gets cornell under 0.1% holes
    ratio: float = 4.0  # candidates per kept point (per side) and pass
    spacing: float = 1.0  # added points are at least this many lookup radii apart (within one pass)
    first_step: bool = False  # a gap is where the lookup's first step (radius r, FIRST_T_N) finds no point
    seed: int = 0x6A9F11


@dataclass
class DensifySettings:
    """Points added after the first trace where the lookup misses the AO (src/psao/server/points/densify.py). Off by
    default: tracing the candidates that are not quiet and asking the lookup's oracle about them each round
    costs several first traces, which a scene whose AO the even points already follow does not need;
    `psao bake --densify 5` for scenes with much detail finer than the point spacing (the README gives
    what it does on Sponza)."""

    rounds: int = 0  # rounds of additions; 0 = off (the paper's evenly spread points only); 5 where used
    ratio: float = 8.0  # candidates per kept point of an instance (drawn once, looked at every round)
    threshold: float = 0.03  # a candidate is added where the lookup misses its traced AO (0..1) by more
    spacing: float = 0.25  # candidates added in one round are at least this many lookup radii apart
    quiet_spread: float = 0.05  # a candidate is not traced where the kept points' AO near it spans at most
    # this (and one of its own face lies within r): the lookup cannot be far off there; 0 traces all
    quiet_reach: float = 1.5  # "near it": within this many lookup radii
    min_rays: int = 64  # rays per point below which the traced AO is too noisy to tell where it varies: off
    seed: int = 0xD3E5

    def check(self) -> None:
        if self.rounds < 0 or not self.ratio > 0 or not self.threshold > 0 or not self.spacing >= 0:
            raise ConfigError(f"densify needs rounds >= 0, ratio > 0, threshold > 0 and spacing >= 0, got "
                              f"{self.rounds}, {self.ratio}, {self.threshold}, {self.spacing}")
        if not self.quiet_spread >= 0 or not self.quiet_reach > 0:
            raise ConfigError(f"densify needs quiet_spread >= 0 and quiet_reach > 0, got {self.quiet_spread}, "
                              f"{self.quiet_reach}")

    def runs_with(self, rays: int) -> bool:
        return self.rounds > 0 and rays >= self.min_rays


LOCAL_PREFIX = "local:"
SCENE_SOURCES = ("auto", "spec", "bytes")


@dataclass
class ClusterSettings:
    address: str  # tcp://HOST:PORT of a running scheduler, or local:N for N worker processes started here
    timeout: float = 10.0  # seconds to reach the scheduler, and to wait for its first worker
    scene_source: str = "auto"  # how workers get the scene: spec (load it), bytes (shipped); auto: spec for builtin:
    chunk_points: int = 16384  # points per task (a task costs the scheduler about a millisecond)
    tiles: bool = False  # shard by spatial tiles: each task carries its tile's triangles, workers hold no scene
    tile_points: int = 65536  # most points per tile

    def check(self) -> None:
        if not self.address:
            raise TracerError("the dask back-end needs a cluster address (tcp://HOST:PORT or local:N)")
        if self.address.startswith(LOCAL_PREFIX):
            local_workers(self.address)
        if not (np.isfinite(self.timeout) and self.timeout > 0):
            raise TracerError(f"cluster timeout must be > 0 seconds, got {self.timeout}")
        if self.scene_source not in SCENE_SOURCES:
            raise TracerError(f"unknown cluster scene source {self.scene_source!r} (known: {', '.join(SCENE_SOURCES)})")
        if self.chunk_points < 1 or self.tile_points < 1:
            raise TracerError(f"chunk and tile points must be >= 1, got {self.chunk_points}, {self.tile_points}")


def local_workers(address: str) -> int:
    text = address[len(LOCAL_PREFIX):]
    if not text.isdigit() or int(text) < 1:
        raise TracerError(f"bad cluster {address!r}: local:N needs a worker count N >= 1")
    return int(text)


@dataclass
class BakeSettings:
    density: float | None = SamplingSettings.density  # N, final points per world unit^2; None: sampling.default_density (scale-aware)
    points: float | None = SamplingSettings.points  # total point budget instead of a density
    max_points: float = SamplingSettings.max_points  # refuse a setting whose estimate exceeds this many points
    # most times the density a small triangle gets (sampling.py), 1: off; None: on with the default density or
    # a point budget, off with an explicit density
    detail_factor: int | None = SamplingSettings.detail_factor
    rays: int = TraceSettings.rays  # rays per point
    seed: int = 0  # points and rays
    tracer: str = "embree"  # back-end name, see psao.server.tracer
    workers: int = TraceSettings.workers  # tracer processes; 0 = all cores
    min_points: int = PointSettings.min_points  # per instance and side
    spawn_ratio: float = PointSettings.spawn_ratio  # spawned / kept before elimination
    grid: GridSettings = field(default_factory=GridSettings)
    gap_fill: GapFillSettings = field(default_factory=GapFillSettings)  # add points where lookups find none (off by default)
    densify: DensifySettings = field(default_factory=DensifySettings)  # add points where the AO varies fast
    skip_buried: bool = True  # no points on surfaces inside closed static geometry (src/psao/server/points/buried.py)
    # keep which rays of each static point the static scene occludes (rays / 8 bytes a point, only for scenes
    # with moving instances): the budgeted tick then re-traces a static point near movers whole at a
    # fraction of its cost (src/psao/server/tracer/static_hits.py)
    keep_static_hits: bool = True
    cluster: ClusterSettings | None = None  # trace on a Dask cluster (the dask back-end) instead of `tracer`

    def check(self) -> None:
        # The scene limits are read when checked: the command line reads these defaults without loading psao.scene.
        from psao.scene import limits as scene_limits

        self.sampling().check()
        if self.workers < 0:
            raise ConfigError(f"workers must be >= 0 (0: all cores), got {self.workers}")
        lim = scene_limits.current()
        if not 1.0 <= self.spawn_ratio <= lim.max_spawn_ratio:
            raise ConfigError(f"spawn ratio must be within 1..{lim.max_spawn_ratio:g}, got {self.spawn_ratio} "
                              f"(psao --scene-limit max_spawn_ratio=X raises the limit)")
        if not 1 <= self.rays <= lim.max_rays:
            raise ConfigError(f"rays must be within 1..{lim.max_rays}, got {self.rays} "
                              f"(psao --scene-limit max_rays=N raises the limit)")
        if self.gap_fill.passes < 0 or not self.gap_fill.ratio > 0:
            raise ConfigError(f"gap fill passes must be >= 0 and ratio > 0, got {self.gap_fill.passes}, {self.gap_fill.ratio}")
        self.densify.check()

    def sampling(self) -> SamplingSettings:
        return SamplingSettings(density=self.density, points=self.points, max_points=self.max_points,
                                detail_factor=self.detail_factor)


@dataclass
class ProbeSettings:
    """`psao bake`'s accuracy check: AO reconstructed at random surface probes against a fine trace."""

    probes: int = 20000  # random surface probes for recon_mae (0 = skip)
    rays: int = 1024  # rays per probe for the ground truth

    def check(self) -> None:
        if self.probes < 0 or self.rays < 1:
            raise ConfigError(f"probes must be >= 0 and probe rays >= 1, got {self.probes}, {self.rays}")


@dataclass
class ViewSettings:
    fov_margin: float = 20.0  # degrees added to the horizontal and vertical field of view
    distance_margin: float = 1.0  # world units the frustum's planes are pushed outwards


@dataclass
class FanoutSettings:
    """Who is sent what (psao.server.net.fanout): the shared stream and per-client culling of sends."""

    cull: bool = True  # send each client only the cells in its extended view; the rest wait until they enter it
    view: ViewSettings = field(default_factory=ViewSettings)  # the extended view (the tick's selection uses the same)
    join_interval: float = 1.0  # seconds between restarts of the shared stream for clients waiting to join
    max_queued: int = 4  # shared Updates waiting in a client's outbox before it leaves the shared stream
    # messages sent to a client and not yet shown read (a websocket ping sent after them not yet answered)
    # before nothing more is sent to it: its changes wait in its pending sets and go out merged once it has
    # read. Kernel and library buffers on the way can hold seconds of Updates; this bounds how far behind
    # a slow reader's mirror (and the answers to keepalive pings, which queue behind the data) can fall.
    # A count, not a time: a link whose round trip exceeds max_unread ticks holds a fast reader back too.
    max_unread: int = 8
    probe_every: int = 2  # messages sent after the last answered ping before the next ping (one at a time)
    # rows (buckets + cells): a client's own Update of at most this many is encoded on the event loop (well
    # under a millisecond), a bigger one in a worker thread; the thread hop costs more than a small encode
    inline_rows: int = 2048
    # clients off the shared stream from which their Updates are made of shared parts: a part is compressed
    # once for many, but apart from the others and without the history a client's own stream has, so
    # it costs bytes (the courtyard's culled clients: about 0.9 instead of 0.5 of the every-change bytes);
    # a client's own stream costs the server a serialize and a compress per client and tick, which only
    # matters with several clients
    parts_from: int = 4
    tiles_per_axis: int = 8  # the parts' world-space tiles: the placed cells' extent over this, per side
    # ticks: a client on shared parts whose camera moved has its pending cells tested against its view again
    # at most this often (clients send cameras about every tick, and the test runs over all that each one
    # has pending: with 30 clients it took a seventh of the event loop); the extended view's margins hold
    # what the camera reaches meanwhile
    catch_up_every: int = 3
    # Mbit/s: the most sent to each client (every message paced by a token bucket of pace_burst seconds;
    # its own Updates then carry what a tick's share of the rate holds, the cells nearest its camera first,
    # the rest merged later); None: no cap (the ping flow control above still holds a slow reader back)
    client_mbit: float | None = None
    pace_burst: float = 0.05  # seconds of the pacing rate a client idle for that long may be sent at once
    # estimate each client's throughput from its ping answers and pace it to that (psao.server.net.rate):
    # a client whose link builds a queue is sent what the link carries; the others are not paced
    adapt_rate: bool = True
    queue_target: float = 0.1  # seconds a ping's round trip exceeds the client's least when its link is queueing
    rate_window: float = 0.25  # seconds: the least span of one delivery sample (bytes shown read over time)
    rate_samples: int = 4  # a link-limited client's estimate: from the largest of this many last samples
    drain_share: float = 0.9  # a link-limited client's estimate: this share of what its link carried
    probe_gain: float = 1.5  # the estimate grows by this each window without a queue that used half of it
    unset_mbit: float = 1000.0  # Mbit/s: an estimate grown past this is dropped (the client is not paced)


@dataclass
class TickSettings:
    threshold: int = 2  # AO codes (of 255): a traced point is written only when |new - stored| > threshold
    rays: int = 32  # rays per traced point
    seed: int = BakeSettings.seed  # ray seed; equal to the bake's so a synced bake needs no re-trace
    selection: bool = True  # False: re-trace every visible point every tick (the baseline)
    view: ViewSettings = field(default_factory=ViewSettings)
    tracer: str = BakeSettings.tracer  # back-end name
    workers: int = BakeSettings.workers  # tracer processes, 0 = all cores
    block: float = 0.0  # world units of the static-point block index; 0 = a quarter of the AO distance (a box
    # query then gathers few points outside the box)
    near_margin: float = 0.25  # share of the AO distance a mover's reach is grown by when its nearby static
    # points are gathered (selection.NearCache): they serve the following ticks until it moves that far
    history: int = 3600  # TickStats kept in stats_history (a minute at 60 Hz); older ones are dropped
    budget: BudgetSettings | None = None  # None: unbudgeted (trace every selected visible point fully each tick)

    @classmethod
    def serving(cls, bake: BakeSettings, budget: BudgetSettings) -> "TickSettings":
        """The time-budgeted, selecting server tick of a server that baked with `bake` (psao serve and
        psao.Server): the bake's rays, seed, tracer and workers; a Dask bake's tick traces with Embree here
        (a Dask task's scheduling does not fit a tick)."""
        return cls(rays=bake.rays, seed=bake.seed, budget=budget, selection=True,
                   tracer="embree" if bake.tracer == "dask" else bake.tracer, workers=bake.workers)

    def check(self) -> None:
        if not 0 <= self.threshold <= 255:
            raise ConfigError(f"tick threshold must be within 0..255 AO codes, got {self.threshold}")
        if self.rays < 1:
            raise ConfigError(f"tick rays must be >= 1, got {self.rays}")
        if self.budget is not None:
            self.budget.check(self.rays)
        if not (0 <= self.view.fov_margin < 180 and self.view.distance_margin >= 0):
            raise ConfigError(f"view margins out of range: {self.view}")


@dataclass
class ServeSettings:
    host: str = "127.0.0.1"
    port: int = 8765  # 0 picks a free port
    tick_hz: float = DEFAULT_TICK_HZ  # ticks per second, within budget.TICK_HZ_RANGE (its tick runs at this rate)
    codec: Codec = Codec.ZSTD_STREAM
    layout: Layout = Layout.PACKED
    zstd: ZstdSettings = PAPER_ZSTD
    token: str = ""  # "" serves anyone
    allow_edits: bool = False  # accept SceneEdit from clients that present edit_token
    edit_token: str = ""  # required (non-empty) with allow_edits
    max_clients: int = 128  # open connections at most (handshake included); more are refused
    # Browser pages allowed to open a websocket (their Origin header), besides this server's own page;
    # connections without an Origin (non-browser clients) are always allowed.
    allow_origins: tuple[str, ...] = ()
    tls_cert: Path | None = None  # PEM certificate chain: serve wss:// (and https://) instead of ws://
    tls_key: Path | None = None  # PEM private key of tls_cert
    web_example: str = ""  # "": GET / is the PSAO page; a name of webpage.EXAMPLES: that example page
    limits: Limits = DEFAULT_LIMITS
    snapshot_cells_per_chunk: int = 16384  # 512 KiB of cells before compression
    hello_timeout: float = 10.0  # seconds a new connection has to send Hello
    # Kernel send buffer per connection (bytes; Linux doubles it). Small enough that a slow reader
    # blocks our send soon and its ticks fold into pending sets instead of queueing stale updates,
    # large enough for ~20 Mbit/s at 100 ms round trip.
    send_buffer: int = 128 * 1024
    stats_interval: float = 1.0  # seconds between live statistics lines
    digest_log: Path | None = None  # jsonl of state digests after every message that drained everything
    stats_json: Path | None = None  # jsonl: one record per tick (the tick's own statistics, dirty rows, bytes)
    fanout: FanoutSettings = field(default_factory=FanoutSettings)  # shared stream and per-client culling

    def check(self) -> None:
        check_tick_hz(self.tick_hz)
        if self.send_buffer < 0:
            raise ConfigError(f"send buffer must be >= 0 bytes (0: the system's default), got {self.send_buffer}")
        if not 0 <= self.port <= 65535:
            raise ConfigError(f"port must be within 0..65535, got {self.port}")
        if not 1 <= self.max_clients <= 100_000:
            raise ConfigError(f"max clients must be within 1..100000, got {self.max_clients}")
        if self.allow_edits and not self.edit_token:
            raise ConfigError("edits need an edit token (PSAO_EDIT_TOKEN or --edit-token-file)")
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ConfigError("TLS needs both a certificate and its key (--tls-cert and --tls-key)")
        if self.allow_edits and self.edit_token == self.token:
            raise ConfigError("the edit token must differ from the viewing token")
        f = self.fanout
        if f.client_mbit is not None and not (math.isfinite(f.client_mbit) and f.client_mbit > 0):
            raise ConfigError(f"client rate cap must be > 0 Mbit/s, got {f.client_mbit}")
        if not (0 < f.queue_target and 0 < f.rate_window and 0 < f.drain_share <= 1 and f.probe_gain > 1
                and f.unset_mbit > 0 and f.rate_samples >= 1):
            raise ConfigError(f"fanout rate estimate out of range: queue_target {f.queue_target} s, rate_window "
                              f"{f.rate_window} s, drain_share {f.drain_share}, probe_gain {f.probe_gain}, "
                              f"unset_mbit {f.unset_mbit}")
        if not 0 < f.pace_burst <= 10:
            raise ConfigError(f"pace burst must be within (0, 10] seconds, got {f.pace_burst}")
        if not 1 <= f.probe_every < f.max_unread:
            raise ConfigError(f"fanout: probe_every ({f.probe_every}) must be >= 1 and below max_unread ({f.max_unread})")
