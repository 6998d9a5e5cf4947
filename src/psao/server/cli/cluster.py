"""Command-line options of the dask back-end, shared by every command that bakes (`psao bake`, `psao serve`)."""
from __future__ import annotations

import argparse

from psao.server.errors import ConfigError
from psao.server.settings import SCENE_SOURCES, ClusterSettings

DEFAULTS = ClusterSettings(address="")


def add_cluster_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("Dask cluster (optional extra: pip install 'psao[dask]'; docs/dask.md)")
    g.add_argument("--cluster", metavar="ADDRESS", default=None,
                   help="trace the bake on a Dask cluster: tcp://HOST:PORT of a running scheduler, or local:N "
                        "to start N worker processes here for this command")
    g.add_argument("--cluster-timeout", type=float, default=DEFAULTS.timeout, metavar="SECONDS",
                   help="give up on an unreachable scheduler, or one without workers, after this long")
    g.add_argument("--cluster-scene", choices=SCENE_SOURCES, default=DEFAULTS.scene_source,
                   help="how workers get the scene: spec (each loads it itself: builtin: scenes, or files at the "
                        "same path on every machine), bytes (sent through the scheduler); auto: spec "
                        "for builtin: scenes, else bytes")
    g.add_argument("--tiles", action="store_true",
                   help="shard the trace by spatial tiles: each task carries only the triangles its tile's rays "
                        "can reach, so a worker's memory follows the tile, not the scene")
    g.add_argument("--tile-points", type=int, default=DEFAULTS.tile_points, metavar="P",
                   help="most points per tile with --tiles")


def cluster_settings(args: argparse.Namespace) -> ClusterSettings | None:
    """The ClusterSettings the options ask for, or None for a local trace."""
    tracer = getattr(args, "tracer", None)
    if args.cluster is None:
        if args.tiles:
            raise ConfigError("--tiles shards the trace over a cluster: it needs --cluster")
        if tracer == "dask":
            raise ConfigError("--tracer dask needs --cluster tcp://HOST:PORT or --cluster local:N")
        return None
    if tracer not in (None, "embree", "dask"):
        raise ConfigError(f"--cluster traces with Embree on the cluster's workers: it cannot use --tracer {tracer}")
    settings = ClusterSettings(address=args.cluster, timeout=args.cluster_timeout, scene_source=args.cluster_scene,
                               tiles=args.tiles, tile_points=args.tile_points)
    settings.check()
    return settings
