"""One command line: defaults read from the settings dataclasses, the same options wherever the same work
happens, one codec vocabulary, --json on every sub-command that reports figures."""
import argparse
import ast
import re
from pathlib import Path

import pytest

from psao.protocol.codecs import CODEC_NAMES, codec_name
from psao.cli import build_parser
from psao.client.settings import FrameSettings
from psao.eval.reference import ReferenceSettings
from psao.eval.settings import BenchSettings
from psao.server.settings import BakeSettings, PointSettings, ServeSettings, TraceSettings
from support.cli import parser_actions, subparsers

BAKE_OPTIONS = {"--density", "--rays", "--seed", "--spawn-ratio", "--gap-fill", "--gap-fill-ratio", "--tracer", "--workers"}


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    return subparsers(build_parser())


def _options(p: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {s: a for a in parser_actions(p) for s in a.option_strings}


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
        for action in parser_actions(p):
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
        positional = [a.dest for a in parser_actions(subs[name]) if not a.option_strings and a.dest != "help"]
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


ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("src/psao",)
OFF = (None, False, "")  # defaults that mean "not given": off, derived or empty


def _literal_defaults(path: Path) -> list[str]:
    """`add_argument(..., default=X)` calls whose X is written out in the module: a number or string
    literal anywhere in X (but the field name of default(Settings, "name") and the separator of a
    "sep".join(...)), or a name the module itself binds to a literal."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    bound = {t.id for node in tree.body if isinstance(node, ast.Assign) for t in node.targets
             if isinstance(t, ast.Name) and not any(isinstance(n, ast.Name) for n in ast.walk(node.value))}
    allowed: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "default":
            allowed.update(id(a) for a in node.args[1:])
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "join":
            allowed.add(id(node.func.value))
    found = []
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "add_argument"):
            continue
        for kw in node.keywords:
            if kw.arg != "default":
                continue
            value = kw.value
            if isinstance(value, ast.Constant) and value.value in OFF or isinstance(value, (ast.List, ast.Tuple)) and not value.elts:
                continue
            written = [n for n in ast.walk(value) if isinstance(n, ast.Constant) and id(n) not in allowed
                       and isinstance(n.value, (int, float, str)) and not isinstance(n.value, bool)]
            names = [n for n in ast.walk(value) if isinstance(n, ast.Name) and n.id in bound]
            if written or names:
                found.append(f"{path.name}:{node.lineno}: default={ast.unparse(value)}")
    return found


def test_no_literal_default_in_a_command_line_module():
    """Every option's default comes from a settings dataclass (src/psao/server/settings.py,
    src/psao/client/settings.py, src/psao/eval/settings.py, ...), never a number or string written in the CLI."""
    modules = [p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py")) if "add_argument(" in p.read_text(encoding="utf-8")]
    assert len(modules) >= 8
    bad = [line for path in modules for line in _literal_defaults(path)]
    assert not bad, "literal defaults:\n" + "\n".join(bad)


def test_the_literal_default_check_catches_one(tmp_path):
    probe = tmp_path / "probe_cli.py"
    probe.write_text('SIZE = "640x360"\n\ndef add_arguments(p):\n    p.add_argument("--frames", type=int, default=4)\n'
                     '    p.add_argument("--size", default=SIZE)\n    p.add_argument("--ok", default=default(S, "f"))\n')
    found = _literal_defaults(probe)
    assert [f.split(": ", 1)[1] for f in found] == ["default=4", "default=SIZE"]


def test_help_prints_the_settings_defaults():
    subs = _subparsers()
    bench = " ".join(subs["bench"].format_help().split())
    assert f"(default: {','.join(f'{d:g}' for d in BenchSettings.densities)})" in bench
    client = " ".join(subs["client"].format_help().split())
    assert f"(default: {FrameSettings.fps})" in client and f"(default: {FrameSettings.size})" in client
    for method, p in subparsers(subs["train"]).items():  # psao train METHOD: the nested parsers print their defaults too
        assert "--steps STEPS" in p.format_help() and "(default:" in p.format_help(), method
