"""Test helper for pages in a real headless browser (psao.eval.browser: Debian's chromium through playwright),
and the wait for a page's state that fails with what the page says."""
from __future__ import annotations

from psao.eval.browser import CHROMIUM, CHROMIUM_ARGS, launched, missing_browser  # noqa: F401 (re-exported)


def wait_page(page, predicate: str, timeout: float = 600.0):
    """Wait until the JS expression is truthy (an event, not a duration: the timeout only bounds a hang);
    fails with the page's state and message (window.psao) when it is not."""
    try:
        page.wait_for_function(predicate, timeout=timeout * 1000, polling=250)
    except Exception:
        state = page.evaluate("window.psao && [window.psao.state, window.psao.message, window.psao.frames, "
                              "window.psao.updates, window.psao.bytes]")
        raise AssertionError(f"page never reached {predicate}: state {state}") from None
