"""One command line: defaults read from the settings dataclasses, the same options wherever the same work
happens, one codec vocabulary, --json on every sub-command that reports figures."""
import argparse
import re

import pytest

from protocol.codecs import CODEC_NAMES, codec_name
from psao.cli import build_parser
from psao_eval.reference import ReferenceSettings
from psao_server.settings import BakeSettings, PointSettings, ServeSettings, TraceSettings

BAKE_OPTIONS = {"--density", "--rays", "--seed", "--spawn-ratio", "--gap-fill", "--gap-fill-ratio", "--tracer", "--workers"}


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def _options(p: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {s: a for a in p._actions for s in a.option_strings}


def _parse(command: str, *argv: str) -> argparse.Namespace:
    return build_parser().parse_args([command, *argv])


def test_defaults_come_from_the_settings():
    bake = _parse("bake", "builtin:cornell")
    assert (bake.density, bake.rays, bake.seed, bake.spawn_ratio) == (BakeSettings.density, BakeSettings.rays,
                                                                      BakeSettings.seed, BakeSettings.spawn_ratio)
    assert (bake.gap_fill, bake.tracer, bake.workers) == (BakeSettings().gap_fill.passes, BakeSettings.tracer,
                                                          BakeSettings.workers)
    # The settings that share a default share it through one field.
    assert BakeSettings.spawn_ratio == PointSettings.spawn_ratio and BakeSettings.rays == TraceSettings.rays
    assert bake.max_points == BakeSettings.max_points and bake.points is None
    serve = _parse("serve", "builtin:cornell")
    assert serve.tick_hz == ServeSettings.tick_hz and serve.tick_rays is None  # None: BudgetSettings.round_rays
    assert serve.codec == codec_name(ServeSettings.codec) and serve.port == ServeSettings.port
    bench = _parse("bench", "builtin:cornell")
    assert bench.spp == ReferenceSettings.spp and bench.rays == BakeSettings.rays


def test_help_never_writes_a_default_by_hand():
    """Defaults are printed by the formatter from the parser's default, so they cannot drift."""
    for name, p in _subparsers().items():
        for action in p._actions:
            assert not re.search(r"\(default\b", action.help or ""), f"psao {name} {action.option_strings}: {action.help}"
        text = p.format_help()
        if "--spawn-ratio" in text:
            assert f"(default: {BakeSettings.spawn_ratio})" in " ".join(text.split())


def test_same_options_wherever_the_same_work_happens():
    subs = _subparsers()
    for name in ("bake", "serve"):
        assert BAKE_OPTIONS <= set(_options(subs[name])), name
    for name in ("client", "render"):
        assert {"--camera-path", "--size", "--ao", "--ssao-samples", "--window"} <= set(_options(subs[name])), name
    for name in ("bake", "serve", "client", "render", "bench"):
        assert "--json" in _options(subs[name]), name
    # The scene is the first positional everywhere but the client, where it follows the server URL.
    for name in ("bake", "serve", "render", "bench", "client"):
        positional = [a.dest for a in subs[name]._actions if not a.option_strings and a.dest != "help"]
        assert positional[-1] in ("scene", "scenes"), (name, positional)


def test_one_codec_vocabulary():
    subs = _subparsers()
    assert set(_options(subs["serve"])["--codec"].choices) == set(CODEC_NAMES)
    client = _parse("client", "ws://127.0.0.1:1", "builtin:cornell")
    assert set(client.codecs.split(",")) == set(CODEC_NAMES)
    assert "--zstd-frames" not in _options(subs["serve"])


@pytest.mark.parametrize("argv", [["bake", "builtin:cornell", "--tracer", "nope"], ["serve", "x", "--codec", "gzip"]])
def test_bad_choice_is_a_usage_error(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(argv)
    assert exc.value.code == 2
