"""A real headless browser for the web client: Debian's chromium driven by playwright's Python API (no
browser download; `make browser` installs chromium), WebGL2 on SwiftShader. The tests and the benchmarks
that load the page (bench_web, bench_progressive) launch it from here."""
from __future__ import annotations

import contextlib
import os
import shutil

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
# Without the background-networking flags chromium keeps trying hosts this machine cannot reach.
CHROMIUM_ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--headless",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run"]


def missing_browser() -> str | None:
    """Why no page can be driven here (a skip reason), or None."""
    if not os.path.exists(CHROMIUM):
        return "chromium is not installed (make browser)"
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "playwright is not installed (pip install '.[test]')"
    return None


@contextlib.contextmanager
def launched():
    """A headless chromium, closed on the way out."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            b.close()
