"""The commands the README and every docs/*.md name beside their figures still exist, with every option
they pass: `psao SUB ...` is checked against the sub-command's parser, `python -m benchmarks.X ...`
against the benchmark's --help, `python -m pytest FILE -k NAME` against the test file."""
from __future__ import annotations

import importlib
import re

import pytest

from conftest import REPO
from psao.cli import build_parser
from support.benchmarks import benchmark_help
from support.cli import option_strings, subparsers

DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
_INLINE = re.compile(r"`((?:psao|python -m) [^`]+)`")


def documented_commands() -> list[tuple[str, str]]:
    """(where, command) for every command in backticks or at the start of a code-block line (with its
    backslash continuations)."""
    found = []
    for doc in DOCS:
        text = doc.read_text()
        for m in _INLINE.finditer(text):
            found.append((f"{doc.name}:{text[:m.start()].count(chr(10)) + 1}", m.group(1)))
        for block in re.findall(r"```[\w-]*\n(.*?)```", text, flags=re.S):
            joined = block.replace("\\\n", " ")
            for line in joined.splitlines():
                if line.startswith(("psao ", "python -m ")):
                    found.append((f"{doc.name} (code block)", line))
    return found


def _flags(command: str) -> list[str]:
    return [t.split("=")[0] for t in command.split() if t.startswith("--")]


def _psao_options() -> dict[str, set[str]]:
    out = {}
    for name, p in subparsers(build_parser()).items():
        out[name] = option_strings(p)
        for method, q in subparsers(p).items():  # psao train METHOD
            out[f"{name} {method}"] = option_strings(q)
    return out


@pytest.mark.parametrize("where,command", documented_commands())
def test_documented_command_exists(where, command):
    words = command.split()
    if words[0] == "psao":
        options = _psao_options()
        top = option_strings(build_parser())
        while words[1].startswith("--"):  # options of psao itself, before the sub-command
            assert words[1] in top, f"{where}: psao has no option {words[1]}"
            words = [words[0], *words[3:]] if "=" in words[2] else [words[0], *words[2:]]
        sub = words[1]
        if sub in ("COMMAND", "SUB"):
            return
        if f"{sub} {words[2] if len(words) > 2 else ''}" in options:
            sub = f"{sub} {words[2]}"
        assert sub in options, f"{where}: psao {sub} is not a sub-command"
        unknown = [f for f in _flags(" ".join(words)) if f not in options[sub]]
        assert not unknown, f"{where}: psao {sub} has no option {unknown}"
    elif words[2].startswith("benchmarks."):
        module = words[2]
        assert importlib.util.find_spec(module) is not None, f"{where}: no module {module}"
        text = benchmark_help(module)
        unknown = [f for f in _flags(command) if f not in text]
        assert not unknown, f"{where}: {module} has no option {unknown}"
    elif words[2] == "pytest":
        path = REPO / words[3]
        assert path.is_file(), f"{where}: no test file {words[3]}"
        if "-k" in words:
            name = words[words.index("-k") + 1]
            assert re.search(rf"def test_\w*{re.escape(name)}", path.read_text()), f"{where}: no test matching {name}"
    else:
        pytest.fail(f"{where}: unknown command form {command!r}")


def test_figures_name_their_command():
    """Every figure of docs/results.md sits under a command: each paragraph that starts with a bold title
    and holds a digit names one in backticks."""
    text = (REPO / "docs" / "results.md").read_text()
    for para in re.split(r"\n\s*\n", text):
        if re.match(r"\*\*[^*]+\*\*", para.strip()) and re.search(r"\d", para):
            assert _INLINE.search(para), f"results.md figure without its command: {para[:80]!r}"


def test_every_doc_is_read():
    """Every markdown page is among DOCS and names at least one command (a page without any would mean the
    patterns above no longer match how the docs write commands)."""
    names = {doc.name for doc in DOCS}
    assert {"README.md", "concepts.md", "design.md", "cli.md", "web.md", "protocol.md", "scaling.md",
            "results.md"} <= names
    for doc in DOCS:
        assert any(where.startswith(doc.name) for where, _ in documented_commands()), doc.name
