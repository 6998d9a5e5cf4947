"""The web client in a real headless browser (Debian chromium driven by playwright) against real `psao
serve` processes: the page's mirror equals the server's, its PSAO image equals the Python oracle, it draws
skinned meshes posed at the server's time with the rest pose's local targets, and it shows refusals and
lost servers and resyncs after a restart. Screenshots go to out/web_client/ (and the test's tmp_path) for
a person to look at; a module that does not load, a connection the server refuses and a lost WebGL
context are a line on the page too. Skips when chromium or playwright is missing."""
from __future__ import annotations

import base64
import json
import signal
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from psao.protocol import messages as m
from psao.protocol.gridformat import BUCKET_ENTRIES, CELL_WORDS, INSTANCE_DTYPE
from psao.protocol.limits import DEFAULT_LIMITS, HEADER_SIZE
from psao.protocol.reconstruct import reconstruct_ao
from psao.protocol.scenefile import SceneFile
from psao.client.scene_import import scene_from_file
from psao.scene import load_scene
from psao.scene.camera import camera_at, look_at, perspective, scene_camera
from psao.scene.skinning import skin_points_reference
from psao.server.net.scene_export import scene_file
from browser import launched, missing_browser, wait_page
from serving import HANG_S, server_url
from skinned import closest_on_mesh

ROOT = Path(__file__).resolve().parents[1]
SHOTS = ROOT / "out" / "web_client"
W, H = 200, 150

pytestmark = pytest.mark.skipif(missing_browser() is not None, reason=str(missing_browser()))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """A `psao serve` process; waits until it listens."""

    def __init__(self, tmp: Path, *args: str, port: int = 0, name: str = "serve"):
        self.err = tmp / f"{name}.err"
        self.digests = tmp / f"{name}.jsonl"
        self.proc = subprocess.Popen([sys.executable, "-m", "psao", "serve", *args, "--port", str(port),
                                      "--digest-log", str(self.digests)], cwd=ROOT, stdout=subprocess.DEVNULL,
                                     stderr=open(self.err, "w"))
        self.port = int(server_url(self.proc, self.err, timeout=HANG_S).rsplit(":", 1)[1])

    def server_digests(self) -> dict:
        return {(d["conn"], d["seq"]): d["digest"] for d in map(json.loads, self.digests.read_text().splitlines())}

    def stop(self, sig=signal.SIGTERM) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            self.proc.wait(30)


@pytest.fixture(scope="module")
def browser():
    with launched() as b:
        yield b


def shot(page, tmp_path: Path, name: str, canvas_only: bool = False) -> None:
    """The page as PNG; `canvas_only`: the WebGL canvas's last frame (a streaming page's main thread is
    busy with updates, and a page screenshot waits for a compositor frame)."""
    SHOTS.mkdir(parents=True, exist_ok=True)
    if canvas_only:
        url = page.evaluate("document.getElementById('view').toDataURL('image/png')")
        png = base64.b64decode(url.split(",", 1)[1])
    else:
        png = page.screenshot()
    for d in (tmp_path, SHOTS):
        (d / f"{name}.png").write_bytes(png)


def fixed_camera(spec: str, t: float = 0.0):
    scene = load_scene(spec)
    eye, target = camera_at(scene_camera(scene), t)
    lo, hi = scene.world_bounds()
    far = 4.0 * float(np.linalg.norm(hi - lo)) + 1.0
    proj = perspective(scene_camera(scene).fov_y, W / H, far * 1e-4, far)
    return look_at(eye, target).astype(np.float32).reshape(-1).tolist(), proj.astype(np.float32).reshape(-1).tolist()


def decode(b64: str, dtype) -> np.ndarray:
    return np.frombuffer(base64.b64decode(b64), dtype=dtype)


def page_vs_oracle(frame: dict) -> tuple[float, int]:
    """Fraction of covered pixels where the page's PSAO equals src/psao/protocol/reconstruct.py within 2/255."""
    n = frame["width"] * frame["height"]
    local = decode(frame["local"], np.float32).reshape(n, 4)
    normal = decode(frame["normal"], np.float32).reshape(n, 4)
    ao = decode(frame["ao"], np.float32).reshape(n, 4)[:, 0]
    instances = decode(frame["instances"], np.uint8).view(INSTANCE_DTYPE)
    buckets = decode(frame["buckets"], np.uint32).reshape(-1, BUCKET_ENTRIES, 2)
    cells = decode(frame["cells"], np.uint32).reshape(-1, CELL_WORDS)
    covered = local[:, 3] > 0.5
    ids = np.rint(local[covered, 3]).astype(np.int64) - 1
    expect, _ = reconstruct_ao(instances, buckets, cells, ids, local[covered, :3], normal[covered, :3],
                               back=normal[covered, 3] > 0.5)
    close = np.abs(ao[covered] - expect) <= 2.0 / 255.0
    return float(close.mean()), int(covered.sum())


def streamed_frame(page, spec: str) -> dict:
    """The page's PSAO frame (readPsao) for the scene's fixed camera, drawn once it streams and has had 3
    Updates; the page stays paused (window.psao: setCamera, renderOnce, readPsao, as main.js and the three.js
    example give them)."""
    wait_page(page, "!!(window.psao && window.psao.setCamera)")
    page.evaluate("([v, p]) => window.psao.setCamera(v, p)", fixed_camera(spec))
    wait_page(page, "window.psao.state === 'streaming' && window.psao.updates >= 3 && window.psao.frames >= 1")
    return page.evaluate("() => { const a = window.psao; a.paused = true; a.renderOnce(); return a.readPsao(); }")


def check_digests(log: list, server: Server, least: int) -> None:
    """Every digest the page and the server both logged for the same message is equal."""
    ref = server.server_digests()
    both = [d for d in log if (d["conn"], d["seq"]) in ref]
    assert len(both) >= least, (len(log), len(ref))
    assert all(ref[(d["conn"], d["seq"])] == d["digest"] for d in both)


def open_page(browser, server: Server):
    """A page on the server's web client with digests on, and the list its script errors go to."""
    page = browser.new_page(viewport={"width": W + 40, "height": H + 40})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(f"http://127.0.0.1:{server.port}/?width={W}&height={H}&digests=1", wait_until="commit")
    return page, errors


# --no-cull: every message then leaves nothing pending, so the server logs a digest for each; with culling
# it logs one only after a message that leaves nothing out of view waiting, and how many those are depends
# on how the edits fall between the page's camera messages.
@pytest.mark.parametrize("spec, serve_args, name", [
    ("builtin:courtyard", ["--density", "4", "--rays", "8", "--test-edits", "20", "--tick-hz", "10", "--no-cull"], "courtyard"),
    ("builtin:robots", ["--density", "8", "--rays", "4", "--animate", "--tick-rays", "4", "--tick-hz", "5", "--no-cull"], "robots"),
])
def test_page_mirrors_the_server_and_matches_the_oracle(browser, tmp_path, spec, serve_args, name):
    mirrors_and_matches(browser, tmp_path, spec, serve_args, name, modes=("ssao",))


def mirrors_and_matches(browser, tmp_path, spec, serve_args, name, modes, prefix=""):
    """The page `psao serve SPEC SERVE_ARGS` serves at / mirrors the server (digests), its PSAO for the fixed
    camera equals the oracle, and (robots) its skinned close-up is posed with rest-pose targets; a screenshot
    of the PSAO frame and one of each of `modes` go to out/web_client/PREFIX*.png."""
    server = Server(tmp_path, spec, *serve_args)
    page, errors = open_page(browser, server)
    try:
        frame = streamed_frame(page, spec)
        shot(page, tmp_path, f"{prefix}{name}_psao", canvas_only=True)
        # A page with digests on hashes its mirror after every message; on a busy machine it falls behind the
        # stream, and every later evaluate waits behind that backlog. The server stops here, so the draws
        # below wait for nothing: they draw the mirror the frame above was drawn from.
        server.stop()
        wait_page(page, "window.psao.state === 'server gone'")
        for mode in modes:
            page.evaluate("(m) => { window.psao.mode = m; window.psao.renderOnce(); }", mode)
            shot(page, tmp_path, f"{prefix}{name}_{mode}", canvas_only=True)
        log = page.evaluate("window.psao.digestLog")
        if name == "robots":
            close_up = skinned_close_up(page, load_scene(spec), tmp_path, prefix)
    finally:
        page.close()
        server.stop()
    assert not errors, errors
    check_digests(log, server, least=3)  # the snapshot and at least two updates (edited or animated grid)
    match, covered = page_vs_oracle(frame)
    assert covered > 0.2 * W * H
    assert match >= 0.995, match
    if name == "robots":
        assert_skinned_drawn_posed_with_rest_targets(*close_up)


def skinned_close_up(page, scene, tmp_path: Path, prefix: str = "") -> tuple:
    """The page's G-buffer of the skinned instance furthest from its rest pose at the server time of the
    last Update, seen from its side with a depth range that holds only it. The page's server has stopped
    (mirrors_and_matches), so no Update moves the mirror between reading its time and transforms and
    drawing them. Returns that mesh as the page received it, its posed vertices (numpy), the instance's
    index and transform, the camera and the frame."""
    t, transforms = page.evaluate("[window.psao.mirror.serverTime, Array.from(window.psao.mirror.transforms)]")
    assert t is not None, "no Update gave the page a server time to pose skinned meshes at"
    delivered = scene_from_file(SceneFile.parse(scene_file(scene).serialize()))
    posed = {}
    for i, inst in enumerate(delivered.instances):
        mesh = delivered.meshes[inst.mesh]
        if mesh.skin is not None:
            posed[i] = skin_points_reference(mesh.skin.skinning_matrices(t), mesh.vertices, mesh.skin.joints,
                                             mesh.skin.weights)
    i = max(posed, key=lambda k: np.abs(posed[k] - delivered.meshes[delivered.instances[k].mesh].vertices).max())
    model = np.asarray(transforms, np.float64).reshape(-1, 4, 4)[i]
    lo, hi = posed[i].min(axis=0), posed[i].max(axis=0)
    centre, radius = model[:3, :3] @ ((lo + hi) / 2) + model[:3, 3], float(np.linalg.norm(hi - lo)) / 2
    side = model[:3, :3] @ [1.0, 0.0, 0.0]
    side[1] = 0.0
    side /= np.linalg.norm(side)
    if side @ (np.mean(delivered.world_bounds(), axis=0) - centre) < 0:  # look from the room's side of it
        side = -side
    fov = 50.0
    distance = 1.05 * radius / np.sin(np.radians(fov / 2))
    view = look_at(centre + distance * side, centre)
    proj = perspective(fov, W / H, distance - radius, distance + radius)
    frame = page.evaluate("([v, p]) => { const a = window.psao; a.setCamera(v, p); a.renderOnce(); return a.readPsao(); }",
                          [view.astype(np.float32).reshape(-1).tolist(), proj.astype(np.float32).reshape(-1).tolist()])
    shot(page, tmp_path, f"{prefix}robots_skinned_close_up", canvas_only=True)
    return delivered.meshes[delivered.instances[i].mesh], posed[i], i, model, proj @ view, frame


def assert_skinned_drawn_posed_with_rest_targets(mesh, posed, instance: int, model, view_proj, frame: dict) -> None:
    """Where the page drew the skinned instance it drew the posed mesh, and its local targets hold the rest
    place of the drawn point (same triangle, same barycentrics: where the server keeps the points) and the
    rest face's normal. So each target lies on the rest mesh, and posed as the server posed it, placed by
    the instance's transform and projected it lands on the pixel that holds it; and the pose matters here:
    a target projected unposed lands elsewhere for many pixels."""
    n = W * H
    local = decode(frame["local"], np.float32).reshape(n, 4)
    normal = decode(frame["normal"], np.float32).reshape(n, 4)
    pixels = np.flatnonzero(np.rint(local[:, 3]) == instance + 1)
    assert len(pixels) >= 1000, f"the skinned instance covers only {len(pixels)} pixels"
    pick = np.random.default_rng(0).choice(pixels, 300, replace=False)
    target = local[pick, :3].astype(np.float64)
    dist, face, bary = closest_on_mesh(mesh.vertices, mesh.faces, target)
    assert np.quantile(dist, 0.99) < 1e-4, f"local targets off the rest mesh by {np.quantile(dist, 0.99):.2e} m"

    def pixel_of(points):  # instance-local points -> window coordinates (rows bottom-up, as the frame)
        clip = np.c_[points @ model[:3, :3].T + model[:3, 3], np.ones(len(points))] @ view_proj.T
        return (clip[:, :2] / clip[:, 3:] + 1) / 2 * [W, H]

    centre = np.c_[pick % W, pick // W] + 0.5
    drawn = np.einsum("pk,pkj->pj", bary, posed[mesh.faces[face]])  # the rest place posed
    off = np.linalg.norm(pixel_of(drawn) - centre, axis=1)
    unposed = np.linalg.norm(pixel_of(target) - centre, axis=1)
    assert np.quantile(off, 0.99) < 0.25, f"1% of the targets, posed, land {np.quantile(off, 0.99):.2f}+ px from their pixel"
    assert np.mean(unposed > 3.0) > 0.2, f"the pose moves only {np.mean(unposed > 3.0):.0%} of pixels: no test of posing"
    flip = np.where(normal[pick, 3] > 0.5, -1.0, 1.0)[:, None]  # the back side of a double-sided mesh
    agree = np.einsum("ij,ij->i", flip * normal[pick, :3], mesh.face_normals()[face]) > 0.999
    assert np.mean(agree) > 0.95, f"only {np.mean(agree):.0%} of the normal targets are the rest face's normal"


def test_refused_token_lost_server_and_resync(browser, tmp_path):
    port = free_port()
    args = ("builtin:cornell", "--density", "16", "--rays", "8", "--token", "s3cret", "--tick-hz", "10")
    server = Server(tmp_path, *args, port=port, name="first")
    page = browser.new_page(viewport={"width": W + 40, "height": H + 40})
    try:
        page.goto(f"http://127.0.0.1:{port}/?width={W}&height={H}&token=guess", wait_until="commit")
        wait_page(page, "window.psao && window.psao.state === 'refused'")
        assert "wrong token" in page.inner_text("#message")
        shot(page, tmp_path, "refused")
        page.goto(f"http://127.0.0.1:{port}/?width={W}&height={H}&token=s3cret&digests=1", wait_until="commit")
        wait_page(page, "window.psao && window.psao.state === 'streaming' && window.psao.frames >= 1")
        first = page.evaluate("window.psao.digestLog.at(-1)")
        server.stop(signal.SIGKILL)
        wait_page(page, "window.psao.state === 'server gone'")
        assert "reconnecting" in page.inner_text("#message")
        shot(page, tmp_path, "server_gone")
        server = Server(tmp_path, *args, port=port, name="second")
        wait_page(page, "window.psao.state === 'streaming' && window.psao.reconnects >= 1 && window.psao.frames >= 2")
        shot(page, tmp_path, "resynced", canvas_only=True)
        again = page.evaluate("window.psao.digestLog.at(-1)")
        assert page.evaluate("window.psao.sceneBytes") > 0 and page.evaluate("window.psao.connection") >= 2
        log = page.evaluate("window.psao.digestLog")
    finally:
        page.close()
        server.stop()
    # The snapshot of the restarted server (same scene, same bake) rebuilt the same mirror, and the
    # page's digest equals what the new server logged for that message.
    assert again["digest"] == first["digest"]
    check_digests(log, server, least=1)


def test_page_follows_a_grid_replacement(browser, tmp_path):
    """`serve --progressive`: the page streams the coarse first grid, is closed with GRID_REPLACED_CLOSE when
    the full grid is ready, reconnects at once (not as a lost server) and mirrors the full grid exactly."""
    server = Server(tmp_path, "builtin:courtyard", "--progressive", "--density", "16", "--rays", "8",
                    "--tick-rays", "2", "--first-points", "2000", "--tick-hz", "10", "--no-cull")
    page, errors = open_page(browser, server)
    try:
        wait_page(page, "window.psao && window.psao.state === 'streaming' && window.psao.frames >= 1")
        # the full grid's snapshot is what is compared on the second connection: how many refinement Updates
        # follow it depends on how the refiner's batches fall between ticks (all in one on a busy machine)
        wait_page(page, "window.psao.gridReplacements === 1 && window.psao.connection === 2 && "
                        "window.psao.state === 'streaming'")
        shot(page, tmp_path, "replaced_grid", canvas_only=True)
        assert page.evaluate("window.psao.reconnects") == 0  # a replacement is not a lost server
        log = page.evaluate("window.psao.digestLog")
    finally:
        page.close()
        server.stop()
    assert not errors
    assert "grid replaced" in server.err.read_text()
    check_digests(log, server, least=2)
    ref = server.server_digests()
    assert len({d["conn"] for d in log if (d["conn"], d["seq"]) in ref}) == 2  # compared on both grids


def refusal(port: int, data: bytes) -> tuple[m.Error, int]:
    """Send one raw message as a websocket client would; the server's Error reply and its close code."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    with connect(f"ws://127.0.0.1:{port}/", max_size=None, open_timeout=HANG_S) as ws:
        ws.send(data)
        reply = ws.recv(timeout=HANG_S)
        try:
            ws.recv(timeout=HANG_S)
        except ConnectionClosed as closed:
            code = closed.rcvd.code
    header = m.Header.parse(reply, DEFAULT_LIMITS.server_payload_bytes)
    assert header.type == m.MessageType.ERROR
    return m.Error.parse(reply[HEADER_SIZE:], DEFAULT_LIMITS), code


def test_old_page_and_bad_scene_requests_are_refused_while_a_page_streams(browser, tmp_path):
    server = Server(tmp_path, "builtin:cornell", "--density", "16", "--rays", "8", "--test-edits", "10", "--tick-hz", "10")
    url = f"http://127.0.0.1:{server.port}/?width={W}&height={H}"
    good, old = (browser.new_page(viewport={"width": W + 40, "height": H + 40}) for _ in range(2))
    try:
        good.goto(url + "&digests=1", wait_until="commit")
        wait_page(good, "window.psao && window.psao.state === 'streaming' && window.psao.updates >= 1")
        # A page that speaks the previous protocol version: refused, and the page says why.
        old.goto(url + f"&protocol={m.PROTOCOL_VERSION - 1}", wait_until="commit")
        wait_page(old, "window.psao && window.psao.state === 'refused'")
        text = old.inner_text("#message")
        assert f"unsupported protocol version {m.PROTOCOL_VERSION - 1}" in text and "BAD_HEADER" in text, text
        shot(old, tmp_path, "old_protocol_refused")
        # Scene requests from websocket clients: one cut short, one over the message size limit.
        short = m.frame(m.MessageType.SCENE_REQUEST, m.Codec.NONE, bytes(20))
        err, code = refusal(server.port, short)
        assert err.code == m.ErrorCode.BAD_PAYLOAD and "SceneRequest" in err.text and code >= 1002, (err, code)
        big = m.frame(m.MessageType.SCENE_REQUEST, m.Codec.NONE, bytes(DEFAULT_LIMITS.client_message_bytes))
        err, code = refusal(server.port, big)
        assert err.code == m.ErrorCode.TOO_LARGE and "over the limit" in err.text, (err, code)
        # The first page kept streaming through all of it, its mirror equal to the server's, and a new
        # page speaking the current version is served as well.
        after = good.evaluate("window.psao.updates")
        old.goto(url, wait_until="commit")
        wait_page(old, "window.psao && window.psao.state === 'streaming' && window.psao.frames >= 1")
        wait_page(good, f"window.psao.updates >= {after + 3} && window.psao.state === 'streaming'")
        log = good.evaluate("window.psao.digestLog")
        assert good.evaluate("window.psao.connection") == 1
    finally:
        good.close()
        old.close()
        server.stop()
    check_digests(log, server, least=after + 3)


def test_page_decodes_updates_made_of_parts(browser, tmp_path):
    """The page's decoder reads an Update of several parts (as the server sends clients whose views
    differ: tiles compressed apart, several zstd frames in one message) as their union, as
    psao.protocol.messages.Update.parse does, and refuses parts that overlap."""
    from psao.protocol.codecs import Codec, FrameCodec
    from psao.protocol.updates import GridDelta, Layout, encode_delta

    cells = (np.arange(24, dtype=np.uint32).reshape(3, 8) * 7919) & 0x7FFFFFFF
    t = np.eye(4, dtype=np.float32)[None] * 2
    parts = [GridDelta(16, np.array([1], np.uint32), t, cell_slots=np.array([2, 9], np.uint32), cells=cells[:2]),
             GridDelta(16, cell_slots=np.array([4], np.uint32), cells=cells[2:])]
    payload = m.Update(5, 0.25, parts[0], Layout.PACKED).serialize() + encode_delta(parts[1], Layout.PACKED)
    frames = b"".join(FrameCodec(Codec.ZSTD).compress(p) for p in (payload[:30], payload[30:]))
    overlap = payload + encode_delta(parts[1], Layout.PACKED)
    want = m.Update.parse(payload).delta
    server = Server(tmp_path, "builtin:courtyard", "--density", "4", "--rays", "4")
    page = browser.new_page()
    try:
        page.goto(f"http://127.0.0.1:{server.port}/wire.js", wait_until="commit")
        got = page.evaluate("""async ([frames, overlap]) => {
            const w = await import("/wire.js");
            const { decompress } = await import("/vendor/fzstd.js");
            const bytes = (hex) => Uint8Array.from(hex.match(/../g), (h) => parseInt(h, 16));
            const p = new w.Reader(decompress(bytes(frames)), "payload");
            const tick = p.u64(), time = p.f64();
            const d = w.decodeDeltaParts(p);
            let refused = "";
            try { const q = new w.Reader(bytes(overlap), "payload"); q.u64(); q.f64(); w.decodeDeltaParts(q); }
            catch (e) { refused = e.message; }
            return { tick, time, ids: [...d.transformIds], transforms: [...d.transforms], slots: [...d.cellSlots],
                     cells: [...d.cells], refused };
        }""", [frames.hex(), overlap.hex()])
    finally:
        page.close()
        server.stop()
    assert (got["tick"], got["time"]) == (5, 0.25)
    assert got["ids"] == want.transform_ids.tolist() and got["transforms"] == want.transforms.reshape(-1).tolist()
    assert got["slots"] == [2, 4, 9] == want.cell_slots.tolist()
    assert got["cells"] == want.cells.reshape(-1).tolist()
    assert "overlap" in got["refused"]


def test_page_reports_a_module_that_does_not_load(browser, tmp_path):
    """A module of the page that answers 404 (the decoder here, through the browser's request routing: the
    server serves it) or does not parse is one line on the page naming it, not a page stuck at 'starting'."""
    server = Server(tmp_path, "builtin:cornell", "--density", "16", "--rays", "8")
    url = f"http://127.0.0.1:{server.port}/?width={W}&height={H}"
    missing, broken = (browser.new_page(viewport={"width": W + 40, "height": H + 40}) for _ in range(2))
    try:
        missing.route("**/vendor/fzstd.js", lambda route: route.fulfill(status=404, body="404", content_type="text/plain"))
        missing.goto(url, wait_until="commit")
        wait_page(missing, "window.psao && window.psao.state === 'page failed'")
        text = missing.inner_text("#message")
        shot(missing, tmp_path, "module_missing")
        broken.route("**/scene.js", lambda route: route.fulfill(status=200, body="export const = ;",
                                                                content_type="text/javascript"))
        broken.goto(url, wait_until="commit")
        wait_page(broken, "window.psao && window.psao.state === 'page failed'")
        syntax = broken.inner_text("#message")
    finally:
        missing.close()
        broken.close()
        server.stop()
    assert text == "A module of the page did not load: /vendor/fzstd.js answered 404 Not Found (imported by /main.js).", text
    assert "SyntaxError" in syntax and "\n" not in syntax, syntax


def test_page_reports_a_lost_context_and_a_refused_connection(browser, tmp_path):
    """A lost WebGL context stops the page with a line saying so (no more frames, no reconnects); a server
    that is gone and refuses the reconnects is a line on the other page naming the address it tries."""
    server = Server(tmp_path, "builtin:cornell", "--density", "16", "--rays", "8", "--tick-hz", "10")
    url = f"http://127.0.0.1:{server.port}/?width={W}&height={H}"
    lost, gone = (browser.new_page(viewport={"width": W + 40, "height": H + 40}) for _ in range(2))
    errors: list[str] = []
    try:
        for page in (lost, gone):
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(url, wait_until="commit")
            wait_page(page, "window.psao && window.psao.state === 'streaming' && window.psao.frames >= 1")
        lost.evaluate("document.getElementById('view').getContext('webgl2').getExtension('WEBGL_lose_context').loseContext()")
        wait_page(lost, "window.psao.state === 'context lost'")
        context_text = lost.inner_text("#message")
        frames = lost.evaluate("window.psao.frames")
        server.stop()
        wait_page(gone, "window.psao.state === 'server gone' && window.psao.message.startsWith('Cannot connect')")
        refused_text = gone.inner_text("#message")
        shot(gone, tmp_path, "connection_refused")
        assert lost.evaluate("[window.psao.state, window.psao.frames, window.psao.connection]") == ["context lost", frames, 1]
    finally:
        lost.close()
        gone.close()
        server.stop()
    assert not errors
    assert context_text.startswith("The WebGL context was lost"), context_text
    assert refused_text.startswith(f"Cannot connect to the server at 127.0.0.1:{server.port} (close code 1006); "
                                   "reconnecting in "), refused_text
