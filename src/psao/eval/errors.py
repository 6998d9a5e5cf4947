"""Errors of the evaluation package.

    EvalError                base: a benchmark or demo that cannot run (unwritable output, bad metric input)
"""
from __future__ import annotations


class EvalError(Exception):
    pass
