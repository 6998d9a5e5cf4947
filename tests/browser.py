"""Test helper for pages in a real headless browser: Debian's chromium driven by playwright's Python API
(no browser download; `make browser` installs chromium), WebGL2 on SwiftShader."""
from __future__ import annotations

import contextlib
import os
import shutil

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
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


def wait_page(page, predicate: str, timeout: float = 600.0):
    """Wait until the JS expression is truthy (an event, not a duration: the timeout only bounds a hang);
    fails with the page's state and message (window.psao) when it is not."""
    try:
        page.wait_for_function(predicate, timeout=timeout * 1000, polling=250)
    except Exception:
        state = page.evaluate("window.psao && [window.psao.state, window.psao.message, window.psao.frames, "
                              "window.psao.updates, window.psao.bytes]")
        raise AssertionError(f"page never reached {predicate}: state {state}") from None
