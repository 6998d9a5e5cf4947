"""The `psao` command line as the tests run it: to completion (psao), as a running process (psao_process),
and the check that it refused with one line (one_line_error)."""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

from serving import HANG_S

REPO = Path(__file__).resolve().parents[2]


def psao(*args, timeout: float = HANG_S) -> subprocess.CompletedProcess:
    """`python -m psao ARGS` (each made a str) in the repository root, to completion; output captured as text."""
    return subprocess.run([sys.executable, "-m", "psao", *map(str, args)], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)


def psao_process(*args, stdout=subprocess.PIPE, stderr=None) -> subprocess.Popen:
    """`python -m psao ARGS` started in the repository root (unbuffered, text); the caller waits for it."""
    return subprocess.Popen([sys.executable, "-m", "psao", *map(str, args)], cwd=REPO, stdout=stdout, stderr=stderr,
                            text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})


def one_line_error(proc: subprocess.CompletedProcess, text: str, *, alone: bool = False) -> None:
    """The command refused with exit 2 and one error line holding `text`, without a traceback. The line is
    the one stderr line that says "error"; alone=True: the only non-blank stderr line at all."""
    assert proc.returncode == 2, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if (ln.strip() if alone else "error" in ln)]
    assert len(lines) == 1 and text in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr


def parser_actions(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    """The parser's actions (options and positionals). argparse has no public way to list them: this is
    the one place the tests read its `_actions`."""
    return list(parser._actions)


def subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """The parser's sub-commands by name ({} for a parser without any)."""
    found = [a for a in parser_actions(parser) if isinstance(a, argparse._SubParsersAction)]
    return dict(found[0].choices) if found else {}


def option_strings(parser: argparse.ArgumentParser) -> set[str]:
    """Every --option (and -o) the parser takes."""
    return {s for a in parser_actions(parser) for s in a.option_strings}
