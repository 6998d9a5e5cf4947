// The PSAO web client: connects back to the server that served the page, takes its scene (SceneRequest),
// mirrors the grid (Snapshot, Update), draws PSAO / SSAO, sends its camera, reconnects and resyncs.
// URL parameters: token, width and height (fixed canvas size), mode (psao, ssao, none, psao-only,
// ssao-only), camera (orbit, fly, or path:NAME for a scene camera path), codecs (the codecs to offer,
// e.g. zstd or zstd-stream,zstd,none; default all the page decodes, the server picks), digests=1 (keep the
// mirror's state digest after every Snapshot and Update, as `psao client --digest-log` does: tests),
// protocol=N (speak protocol version N: tests of how a server refuses an old page).
// index.html's entry script imports it and provides window.psaoStatus (the state line and message box).
import * as C from "/psao_constants.js";
import { decompress } from "/vendor/fzstd.js";
import { Controls, cameraAt, lookAt, perspective } from "/camera.js";
import { mirrorDigest } from "/digest.js";
import { MODES, Renderer } from "/render.js";
import { parseScene, worldBounds } from "/scene.js";
import { ClientSession, Mirror, ProtocolError, RemoteError, byeMessage, cameraMessage } from "/wire.js";

const params = new URLSearchParams(location.search);
const canvas = document.getElementById("view");
const statsEl = document.getElementById("stats");
const CAMERA_HZ = 30;
const RECONNECT_PAUSES = [0.25, 0.5, 1, 2];  // seconds; the last repeats

const app = {
  state: "starting", message: "", connection: 0, reconnects: 0, refused: false, halted: false,
  scene: null, sceneHash: null, mirror: null, session: null, ws: null,
  bytes: 0, updates: 0, updateBytes: 0, snapshotBytes: 0, sceneBytes: 0, points: 0, frameMs: 0, decodeMs: [],
  timings: { module: performance.now() }, profile: null, fixedCamera: window.__psaoCamera ? { view: new Float32Array(window.__psaoCamera[0]), proj: new Float32Array(window.__psaoCamera[1]) } : null, mode: MODES[params.get("mode")] !== undefined ? params.get("mode") : "psao",
  frames: 0, seq: 0, digestLog: [],
};
const KEEP_DIGESTS = params.get("digests") === "1";
const SESSION_OPTIONS = {
  ...(params.get("codecs") ? { codecs: params.get("codecs").split(",").map((c) => c.trim()).filter(Boolean) } : {}),
  ...(params.get("protocol") ? { version: Number(params.get("protocol")) } : {}),
};
window.psao = app;  // the tests and the benchmark read and drive the page through this object

function setState(state, message = "", bad = false) {
  if (!app.halted) window.psaoStatus(state, message, bad);
}

// The page stops for good, saying why: no reconnects, no frames, its state and message stay.
function halt(state, message) {
  setState(state, message, true);
  app.halted = true;
  const ws = app.ws;
  app.ws = null;
  if (ws) ws.close();
}

const line = (exc) => String(exc.message || exc).split("\n")[0];

let renderer, controls;
try {
  renderer = new Renderer(canvas);
  controls = new Controls(canvas);
} catch (exc) {
  setState("no WebGL2", line(exc), true);
  throw exc;
}
// The shaders load and compile while the page connects and the scene arrives; the socket's events wait for
// them in this chain, in the order they came.
let inbox = renderer.init().then(() => { app.timings.renderer = performance.now(); },
                                 (exc) => { halt("no WebGL2", line(exc)); console.error(exc); });
canvas.addEventListener("webglcontextlost", () => halt("context lost", "The WebGL context was lost (the GPU was reset or ran "
                                                       + "out of memory); reload the page to start again."));
const [fixedW, fixedH] = [Number(params.get("width")), Number(params.get("height"))];
if (fixedW && fixedH) document.body.classList.add("fixed");
document.getElementById("mode").value = app.mode;
document.getElementById("mode").onchange = (e) => { app.mode = e.target.value; };
document.getElementById("camera").onchange = (e) => { controls.mode = e.target.value; };

function frameSize() {
  return [fixedW || Math.max(1, Math.floor(canvas.clientWidth * devicePixelRatio)),
          fixedH || Math.max(1, Math.floor(canvas.clientHeight * devicePixelRatio))];
}

function projection() {
  const [lo, hi] = worldBounds(app.scene);
  const far = 4 * Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]) + 1;
  const path = cameraPath();
  const [w, h] = frameSize();
  return perspective(path ? path.fovY : 60, w / h, far * 1e-4, far);
}

function cameraPath() {
  const cam = params.get("camera") || "";
  if (!cam.startsWith("path") || !app.scene) return null;
  const name = cam.slice(5);
  return app.scene.cameraPaths.find((p) => p.name === name) || app.scene.cameraPaths[0] || null;
}

function cameraNow(dt) {
  if (app.fixedCamera) return app.fixedCamera;
  const path = cameraPath();
  const view = path ? lookAt(...cameraAt(path, performance.now() / 1000)) : controls.view(dt);
  return { view, proj: projection() };
}

// ---------------------------------------------------------------------------------------- connection
function connect() {
  app.connection++;
  let session;
  try {
    session = new ClientSession(params.get("token") || "", app.sceneHash, SESSION_OPTIONS);
  } catch (exc) {
    app.refused = true;
    halt("bad URL", line(exc));
    return;
  }
  const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/`);
  ws.binaryType = "arraybuffer";
  app.session = session;
  app.ws = ws;
  app.timings.connect = performance.now();
  if (!app.reconnects) setState("connecting");  // while reconnecting the "server gone" message stays up
  let opened = false;
  ws.onopen = () => { opened = true; ws.send(session.sceneRequest()); if (!app.reconnects) setState("loading scene"); };
  ws.onmessage = (e) => {
    const arrived = performance.now();
    inbox = inbox.then(() => {
      if (ws !== app.ws) return;
      app.arrived = arrived;
      app.bytes += e.data.byteLength;
      try {
        handle(ws, session, session.receive(e.data), e.data.byteLength);
      } catch (exc) {
        fail(ws, exc);
      }
    });
  };
  ws.onclose = (e) => { inbox = inbox.then(() => closed(e)); };
  const closed = (e) => {
    if (ws !== app.ws) return;
    app.ws = null;
    if (e.code === C.GRID_REPLACED_CLOSE) {  // not a loss: the server swapped in a better grid, fetch it now
      app.gridReplacements = (app.gridReplacements || 0) + 1;
      connect();
      return;
    }
    const pause = RECONNECT_PAUSES[Math.min(app.reconnects, RECONNECT_PAUSES.length - 1)];
    const what = opened ? "Connection to the server lost" : `Cannot connect to the server at ${location.host}`;
    setState("server gone", `${what} (close code ${e.code}); reconnecting in ${pause} s (attempt ${app.reconnects + 1}).`, true);
    setTimeout(() => { app.reconnects++; connect(); }, pause * 1000);
  };
}

function fail(ws, exc) {
  const refused = exc instanceof RemoteError && exc.code !== C.ErrorCode.SHUTTING_DOWN;
  if (refused || exc instanceof ProtocolError) {
    app.refused = true;
    halt("refused", exc instanceof RemoteError ? `The server refused this page: ${exc.text} (${exc.codeName})`
                                               : `Bad data from the server: ${exc.message}`);
    return;
  }
  setState("error", line(exc), true);
  ws.close();
}

function handle(ws, session, ev, nbytes) {
  if (!ev) return;
  const t = performance.now();
  if (ev.kind === "status") {  // a starting server's phase: the state line until the page streams
    app.serverPhase = ev.phase.toLowerCase();
    if (app.state !== "streaming")
      setState(`server ${app.serverPhase} ${(100 * ev.progress).toFixed(0)}%${ev.text ? `: ${ev.text}` : ""}`);
  } else if (ev.kind === "scene-progress") {
    setState(`loading scene ${(100 * ev.got / ev.total).toFixed(0)}%`);
  } else if (ev.kind === "scene") {
    app.timings.sceneArrived = app.arrived;
    if (ev.blob) {
      const raw = decompress(ev.blob);
      if (raw.length > C.LIMITS.scene_payload_bytes) throw new ProtocolError("scene over the size limit");
      app.timings.sceneDecompressed = performance.now();
      const first = !app.scene;  // later ones: the server changed its scene (instances added or removed)
      app.scene = parseScene(raw);
      app.sceneBytes = ev.total;
      app.scenes = (app.scenes || 0) + 1;
      app.timings.sceneParsed = performance.now();
      renderer.setScene(app.scene);
      if (first) controls.frame(...worldBounds(app.scene));  // the view stays where it was for a changed scene
    }
    app.sceneHash = ev.hash;
    app.timings.scene = performance.now();
    ws.send(session.hello());
    app.timings.hello = performance.now();
    if (!app.reconnects) setState("loading snapshot");
    if (ev.blob) setTimeout(drawPreview, 0);  // while the server answers the Hello
  } else if (ev.kind === "welcome") {
    app.seq = 0;  // Welcome is message 0 of the grid stream, as the server counts
    app.mirror = new Mirror(ev.welcome);
    app.connectionId = ev.welcome.connectionId;
    app.codec = Object.keys(C.Codec).find((k) => C.Codec[k] === ev.welcome.codec);
    app.snapshotBytes = 0;
    app.timings.welcome = performance.now();
    app.profile = { chunks: 0, decompressMs: 0, parseMs: 0, applyMs: 0, uploadMs: 0 };
    startCameras(ws, session);
  } else if (ev.kind === "snapshot") {
    const prof = app.profile;
    if (!prof.chunks) app.timings.firstChunk = app.arrived;
    prof.chunks++;
    prof.decompressMs += session.decompressMs;
    prof.parseMs += session.decodeMs - session.decompressMs;
    const ta = performance.now();
    app.mirror.apply(ev.delta);
    prof.applyMs += performance.now() - ta;
    app.snapshotBytes += nbytes;
    if (ev.complete) {
      const tu = performance.now();
      renderer.uploadGrid(app.mirror);
      prof.uploadMs = performance.now() - tu;
      app.timings.snapshot = performance.now();
      app.snapshotDigest = null;
      setState("streaming");
    }
  } else if (ev.kind === "update") {
    app.mirror.apply(ev.delta);
    app.mirror.tick = ev.tick;
    app.mirror.serverTime = ev.serverTime;
    app.updates++;
    app.updateBytes += nbytes;
    app.decodeMs.push(session.decodeMs + (performance.now() - t));
    if (app.decodeMs.length > 1000) app.decodeMs.shift();
  }
  if (ev.kind === "welcome" || ev.kind === "snapshot" || ev.kind === "update") {
    if (KEEP_DIGESTS && ev.kind !== "welcome")
      app.digestLog.push({ conn: app.connectionId, seq: app.seq, tick: app.mirror.tick, digest: mirrorDigest(app.mirror) });
    app.seq++;
  }
  if (ev.kind === "bye") {
    setState("server gone", "The server is shutting down; reconnecting when it is back.", true);
  }
}

function startCameras(ws, session) {
  const timer = setInterval(() => {
    if (ws.readyState !== WebSocket.OPEN || !app.scene) { clearInterval(timer); return; }
    const { view, proj } = cameraNow(0);
    ws.send(cameraMessage(view, proj));
  }, 1000 / CAMERA_HZ);
}

window.addEventListener("beforeunload", () => { if (app.ws && app.ws.readyState === WebSocket.OPEN) app.ws.send(byeMessage()); });

// --------------------------------------------------------------------------------------------- frames
const onePixel = new Uint8Array(4);
function drawFrame(dt) {
  const gl = renderer.gl;
  renderer.resize(...frameSize());
  const t0 = performance.now();
  renderer.updateGrid(app.mirror);
  renderer.setSkinTime(app.mirror.serverTime);
  const { view, proj } = cameraNow(dt);
  renderer.draw(app.mirror.transforms, view, proj, app.mode);
  gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, onePixel);  // waits for the frame (finish() need not)
  app.frameMs = performance.now() - t0;
  app.frames++;
  if (app.timings.snapshot && !app.timings.firstDraw) {
    app.timings.firstDraw = performance.now();
    app.timings.firstFrameMs = app.frameMs;
  }
}

// The scene without AO while its grid is on the way: the user sees it, and software GL, which compiles each
// pipeline at its first draw, has done so before the first PSAO frame.
function drawPreview() {
  if (app.halted || app.state === "streaming" || !app.scene) return;
  renderer.resize(...frameSize());
  const { view, proj } = cameraNow(0);
  renderer.preview(new Float32Array(app.scene.instances.flatMap((inst) => [...inst.transform])), view, proj, app.mode);
  renderer.gl.readPixels(0, 0, 1, 1, renderer.gl.RGBA, renderer.gl.UNSIGNED_BYTE, onePixel);
  app.timings.preview = performance.now();
}

// One frame now, outside the animation loop (tests and the benchmark; returns the frame's ms).
app.renderOnce = () => { drawFrame(0); return app.frameMs; };
app.digest = () => (app.mirror ? mirrorDigest(app.mirror) : null);
app.setCamera = (view, proj) => { app.fixedCamera = view ? { view: new Float32Array(view), proj: new Float32Array(proj) } : null; };
const b64 = (a) => { const b = new Uint8Array(a.buffer, a.byteOffset, a.byteLength); let s = ""; for (let i = 0; i < b.length; i += 8192) s += String.fromCharCode(...b.subarray(i, i + 8192)); return btoa(s); };
// The G-buffer inputs of the PSAO pass and its output, and the mirror, as base64 (bottom-up rows).
app.readPsao = () => ({ width: renderer.size[0], height: renderer.size[1], local: b64(renderer.read(renderer.g[0])),
                        normal: b64(renderer.read(renderer.g[1])), ao: b64(renderer.read(renderer.aoTex)),
                        instances: b64(app.mirror.instances), buckets: b64(app.mirror.buckets), cells: b64(app.mirror.cells),
                        transforms: b64(app.mirror.transforms), serverTime: app.mirror.serverTime, tick: app.mirror.tick });

let last = performance.now(), lastStats = last, bytesAtStats = 0, updatesAtStats = 0;
function loop(now) {
  const dt = (now - last) / 1000;
  last = now;
  if (app.scene && app.mirror && app.state === "streaming" && !app.paused) {
    try {
      drawFrame(dt);
    } catch (exc) {
      halt("error", `Drawing a frame failed: ${line(exc)}`);
    }
  }
  if (now - lastStats >= 1000) {
    const s = (now - lastStats) / 1000;
    if (app.mirror) app.points = app.mirror.allocatedPoints();
    const rows = [["Mbit/s", ((8 * (app.bytes - bytesAtStats)) / s / 1e6).toFixed(2)], ["updates/s", ((app.updates - updatesAtStats) / s).toFixed(1)],
                  ["frame ms", app.frameMs.toFixed(1)], ["points", app.points.toLocaleString("en")],
                  ["tick", app.mirror ? app.mirror.tick : "-"], ["codec", app.codec || "-"],
                  ["server", app.serverPhase || "-"]];
    statsEl.innerHTML = rows.map(([k, v]) => `<tr><td>${k}</td><td>${v}</td></tr>`).join("");
    bytesAtStats = app.bytes;
    updatesAtStats = app.updates;
    lastStats = now;
  }
  requestAnimationFrame(loop);
}
requestAnimationFrame(loop);
connect();
