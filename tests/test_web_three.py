"""The three.js integration (psao-three.js) in a real headless chromium against `psao serve --web-example
three`: the example page's mirror digest equals the server's for the same messages, and its PSAO image
for a fixed camera (its G-buffer through the page's lookup) equals the Python oracle within 2/255 on
>= 99.5% of covered pixels, on the courtyard and on the skinned robots (whose close-up G-buffer holds the
rest pose's local targets of the posed mesh); the GTAOPass and SAOPass of the same frame draw. Screenshots go to
out/web_client/. Skips when chromium or playwright is missing."""
from __future__ import annotations

import signal

import pytest

from browser import launched, missing_browser, wait_page
from test_web_client import H, W, Server, check_digests, free_port, mirrors_and_matches, open_page

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


def test_application_meshes_match_by_name_and_a_scene_that_does_not_is_one_error(browser, tmp_path):
    """connect() to the application's own meshes, named as the server's instances (built here from the scene
    the example received), mirrors the same grid (digest) and draws them into its G-buffer; a scene without
    the server's instances rejects the connect with one line."""
    server = Server(tmp_path, "builtin:cornell", "--density", "8", "--rays", "4")
    page = browser.new_page()
    try:
        page.goto(f"http://127.0.0.1:{server.port}/three/?width={W}&height={H}", wait_until="commit")
        wait_page(page, "window.psao && window.psao.state === 'streaming'")
        same, covered, text = page.evaluate("""async () => {
          const THREE = await import('three');
          const { connect } = await import('/three/psao-three.js');
          const served = window.psao.ao.serverScene, own = new THREE.Scene(), r = new THREE.WebGLRenderer();
          for (const inst of served.instances) {
            const mesh = served.meshes[inst.mesh], g = new THREE.BufferGeometry();
            g.setAttribute('position', new THREE.BufferAttribute(mesh.vertices, 3));
            g.setIndex(new THREE.BufferAttribute(mesh.faces, 1));
            own.add(Object.assign(new THREE.Mesh(g, new THREE.MeshBasicMaterial()), { name: inst.name }));
          }
          const [eye, target] = [served.cameraPaths[0].keys[0].eye, served.cameraPaths[0].keys[0].target];
          const cam = new THREE.PerspectiveCamera(served.cameraPaths[0].fovY, 4 / 3, 0.01, 100);
          cam.position.set(...eye);
          cam.lookAt(...target);
          const ao = await connect(location.href, r, own, cam);
          await new Promise((done) => { const t = setInterval(() => { if (ao.state === 'streaming') { clearInterval(t); done(); } }, 50); });
          ao.setSize(64, 48);
          ao.renderAO();
          const local = ao.read(0);
          let covered = 0;
          for (let i = 3; i < local.length; i += 4) covered += local[i] > 0.5;
          const same = ao.digest() === window.psao.digest();
          ao.close();
          const other = new THREE.Scene();
          other.add(Object.assign(new THREE.Mesh(new THREE.BoxGeometry()), { name: 'not-in-the-scene' }));
          try { await connect(location.href, r, other, cam); return [same, covered, 'connected']; }
          catch (e) { return [same, covered, e.message]; }
        }""")
    finally:
        page.close()
        server.stop()
    assert same
    assert covered > 0.5 * 64 * 48
    assert "does not match the server's" in text and "have no mesh of that name" in text, text


def test_lost_server_reconnects_and_resyncs(browser, tmp_path):
    """A killed server is 'server gone' with the reconnect line; its restart on the same port gives the same
    mirror again (the scene not sent again: the page holds it) and digests equal the new server's."""
    port = free_port()
    args = ("builtin:cornell", "--density", "16", "--rays", "8", "--tick-hz", "10", "--web-example", "three")
    server = Server(tmp_path, *args, port=port, name="first")
    page, errors = open_page(browser, server)
    try:
        wait_page(page, "window.psao && window.psao.state === 'streaming' && window.psao.frames >= 1")
        first = page.evaluate("window.psao.digest()")
        server.stop(signal.SIGKILL)
        wait_page(page, "window.psao.state === 'server gone'")
        assert "reconnecting" in page.inner_text("#message")
        server = Server(tmp_path, *args, port=port, name="second")
        wait_page(page, "window.psao.state === 'streaming' && window.psao.reconnects >= 1")
        again = page.evaluate("window.psao.digest()")
        log = page.evaluate("window.psao.digestLog")
    finally:
        page.close()
        server.stop()
    assert not errors, errors
    assert again == first
    check_digests(log, server, least=1)
