"""A benchmark's command line as the tests read it: its --help text and the options it names."""
from __future__ import annotations

import contextlib
import importlib
import io
import re

import pytest


def benchmark_help(module: str) -> str:
    """What `python -m MODULE --help` prints (the benchmark's main(["--help"]))."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
        importlib.import_module(module).main(["--help"])
    return out.getvalue()


def help_options(module: str) -> set[str]:
    """The --options the benchmark's --help lists."""
    return set(re.findall(r"(?<![\w-])--[a-z][\w-]*", benchmark_help(module)))
