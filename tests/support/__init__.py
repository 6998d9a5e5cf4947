"""Helpers shared by the test modules (tests/ is on sys.path: `from support.cli import psao`)."""
