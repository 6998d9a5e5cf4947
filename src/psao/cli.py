"""The `psao` command: one entry point, sub-commands owned by the packages that implement them.

Each sub-command module exposes `add_arguments(parser)` and `run(args) -> int`. Only the module of the
sub-command named on the command line is imported, its defaults come from light settings modules, and
heavy imports (Embree, Warp, moderngl, websockets) stay inside `run`, so `psao COMMAND --help` is quick. Known errors become one line on stderr
and exit status 2; anything else is a bug and keeps its traceback.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from psao.options import DefaultsFormatter

SUBCOMMANDS = {
    "bake": ("psao.server.cli.bake", "generate points, trace AO and write the grid"),
    "serve": ("psao.server.cli.serve", "bake a scene and stream its AO to clients over websockets"),
    "client": ("psao.client.cli", "connect to a server, mirror its grid, optionally render frames"),
    "render": ("psao.client.render_cli", "render frames offline from a baked grid, no server"),
    "bench": ("psao.eval.bench_cli", "quality, bandwidth and runtime benchmarks against an RTAO reference"),
    "train": ("psao.eval.train_cli", "train a learned AO baseline (mlp, nnao, aogan) and write its weights"),
    "demo": ("psao.eval.demo", "serve the animated courtyard, render it headless, report and chart"),
}

# Base classes of the errors that deserve a one-line message rather than a traceback.
ERROR_BASES = [
    ("psao.protocol.errors", "ProtocolError"),
    ("psao.scene.errors", "SceneError"),
    ("psao.server.errors", "ServerError"),
    ("psao.client.errors", "ClientError"),
    ("psao.eval.errors", "EvalError"),
]


def _known_errors() -> tuple[type[BaseException], ...]:
    found: list[type[BaseException]] = [FileNotFoundError, PermissionError, IsADirectoryError, NotADirectoryError]
    for module, name in ERROR_BASES:
        try:
            found.append(getattr(importlib.import_module(module), name))
        except (ImportError, AttributeError):
            pass
    return tuple(found)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser of every sub-command, or with `command` of that one alone (the others are listed but
    not imported)."""
    parser = argparse.ArgumentParser(prog="psao", description="Point-based split rendering of ray-traced AO.")
    parser.add_argument("--scene-limit", action="append", default=[], metavar="NAME=VALUE",
                        help="raise a size limit of scene loading and baking (psao.scene.limits.SceneLimits: "
                             "max_instances, max_coordinate, max_rays, ...); repeatable")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module_name, help_text) in SUBCOMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text, formatter_class=DefaultsFormatter)
        if command is None or name == command:
            module = importlib.import_module(module_name)
            module.add_arguments(p)
            p.set_defaults(_run=module.run)
    return parser


def named_command(argv: list[str]) -> str | None:
    """The sub-command argv names (the first word after the global options), None when it names none."""
    words = iter(argv)
    for word in words:
        if word == "--scene-limit":
            next(words, None)
        elif not word.startswith("-"):
            return word if word in SUBCOMMANDS else None
    return None


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser(named_command(argv)).parse_args(argv)
    try:
        if args.scene_limit:
            from psao.scene import limits

            limits.set_limits(limits.parse_overrides(args.scene_limit))
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        print("psao: interrupted", file=sys.stderr)
        return 130
    except _known_errors() as exc:
        print(f"psao {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
