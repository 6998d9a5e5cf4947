"""Command-line options that read their defaults from the settings dataclasses (one source per default).

    p.add_argument("--density", type=float, default=default(BakeSettings, "density"), help="points per unit^2")

`psao` builds every sub-command parser with `DefaultsFormatter`, so `--help` prints each default after
its help text; help texts never write a default out themselves.
"""
from __future__ import annotations

import argparse
import dataclasses


class DefaultsFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """argparse's defaults formatter, without '(default: None)' and '(default: False)' on options whose
    absence means 'off' or 'derived'."""

    def _get_help_string(self, action: argparse.Action) -> str:
        if action.default is None or action.default is False or action.default == "" or action.help is None:
            return action.help or ""
        return super()._get_help_string(action)


def comma_list(values) -> str:
    """A tuple default as the comma-separated text its option takes: (128, 256.0) -> '128,256'."""
    return ",".join(f"{v:g}" if isinstance(v, float) else str(v) for v in values)


def default(settings_class: type, name: str):
    """Default of field `name` of a settings dataclass (a dotted name reaches into nested settings)."""
    head, _, rest = name.partition(".")
    f = {f.name: f for f in dataclasses.fields(settings_class)}[head]
    value = f.default if f.default is not dataclasses.MISSING else f.default_factory()
    return default(type(value), rest) if rest else value
