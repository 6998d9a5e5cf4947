"""The three.js integration (psao-three.js) in a real headless chromium against `psao serve --web-example
three`: the example page's mirror digest equals the server's for the same messages, and its PSAO image
for a fixed camera (its G-buffer through the page's lookup) equals the Python oracle within 2/255 on
>= 99.5% of covered pixels, on the courtyard and on the skinned robots (whose close-up G-buffer holds the
rest pose's local targets of the posed mesh); the GTAOPass and SAOPass of the same frame draw. Screenshots go to
out/web_client/. Skips when chromium or playwright is missing."""
from __future__ import annotations

import pytest

from browser import launched, missing_browser, wait_page
from test_web_client import H, W, Server, mirrors_and_matches

pytestmark = pytest.mark.skipif(missing_browser() is not None, reason=str(missing_browser()))


@pytest.fixture(scope="module")
def browser():
    with launched() as b:
        yield b


@pytest.mark.parametrize("spec, serve_args, name", [
    ("builtin:courtyard", ["--density", "64", "--rays", "8", "--test-edits", "20", "--tick-hz", "10", "--no-cull"],
     "courtyard"),
    ("builtin:robots", ["--density", "8", "--rays", "4", "--animate", "--tick-rays", "4", "--tick-hz", "5", "--no-cull"],
     "robots"),
])
def test_three_page_mirrors_the_server_and_matches_the_oracle(browser, tmp_path, spec, serve_args, name):
    mirrors_and_matches(browser, tmp_path, spec, [*serve_args, "--web-example", "three"], name,
                        modes=("gtao", "sao", "psao-only"), prefix="three_")


def test_a_scene_that_does_not_match_is_one_error(browser, tmp_path):
    """connect() to a server whose instances the application's scene does not hold rejects with one line."""
    server = Server(tmp_path, "builtin:cornell", "--density", "8", "--rays", "4")
    page = browser.new_page()
    try:
        page.goto(f"http://127.0.0.1:{server.port}/three/?width={W}&height={H}", wait_until="commit")
        wait_page(page, "window.psao && window.psao.state === 'streaming'")
        text = page.evaluate("""async () => {
          const THREE = await import('three');
          const { connect } = await import('/three/psao-three.js');
          const r = new THREE.WebGLRenderer(), scene = new THREE.Scene();
          scene.add(Object.assign(new THREE.Mesh(new THREE.BoxGeometry()), { name: 'not-in-the-scene' }));
          try { await connect(location.href, r, scene, new THREE.PerspectiveCamera()); return 'connected'; }
          catch (e) { return `${e.name}: ${e.message}`; }
        }""")
    finally:
        page.close()
        server.stop()
    assert "does not match the server's" in text and "have no mesh of that name" in text, text
