// The three.js example page (`psao serve --web-example three`): the delivered scene drawn by three.js
// (psao-three builds its meshes), with PSAO from the server or three.js's own GTAOPass / SAOPass on the
// same frame (the AO select). URL parameters: width and height (fixed canvas size), mode (psao, gtao,
// sao, none, psao-only), digests=1 (keep the mirror's digest after every Snapshot and Update: tests).
// window.psao holds the state for the tests and the benchmark.
import * as THREE from "three";
import { EffectComposer } from "three/addons/postprocessing/EffectComposer.js";
import { GTAOPass } from "three/addons/postprocessing/GTAOPass.js";
import { OutputPass } from "three/addons/postprocessing/OutputPass.js";
import { RenderPass } from "three/addons/postprocessing/RenderPass.js";
import { SAOPass } from "three/addons/postprocessing/SAOPass.js";
import { connect } from "psao-three";
import { cameraAt, lookAt } from "/camera.js";
import { worldBounds } from "/scene.js";

const params = new URLSearchParams(location.search);
const canvas = document.getElementById("view");
const statsEl = document.getElementById("stats");
const BACKGROUND = [0.62, 0.74, 0.88];  // the page's sky (composite.frag)
const MODES = ["psao", "gtao", "sao", "none", "psao-only"];
const [fixedW, fixedH] = [Number(params.get("width")), Number(params.get("height"))];
if (fixedW && fixedH) document.body.classList.add("fixed");

const app = { state: "starting", message: "", mode: MODES.includes(params.get("mode")) ? params.get("mode") : "psao",
              frames: 0, frameMs: 0, fixedCamera: null, paused: false };
window.psao = app;
const stateEl = document.getElementById("state"), messageEl = document.getElementById("message");
function status(state, message = "", bad = false) {
  Object.assign(app, { state, message });
  stateEl.textContent = state;
  stateEl.className = bad ? "bad" : "";
  messageEl.hidden = !message;
  messageEl.textContent = message;
}
addEventListener("unhandledrejection", (e) => status("error", String((e.reason && e.reason.message) || e.reason), true));

const renderer = new THREE.WebGLRenderer({ canvas, antialias: false, preserveDrawingBuffer: true });
const size = () => [fixedW || Math.max(1, canvas.clientWidth * devicePixelRatio | 0), fixedH || Math.max(1, canvas.clientHeight * devicePixelRatio | 0)];
renderer.setPixelRatio(1);
renderer.setSize(...size(), false);
const scene = new THREE.Scene();
scene.background = new THREE.Color().setRGB(...BACKGROUND, THREE.LinearSRGBColorSpace);
scene.add(new THREE.HemisphereLight(0xffffff, 0x404040, 1.2));
const sun = new THREE.DirectionalLight(0xffffff, 2.0);
sun.position.set(0.35, 0.9, 0.25);
scene.add(sun);
const camera = new THREE.PerspectiveCamera(60, 1, 0.01, 100);

// A row-major view and projection (the wire's convention) onto the three.js camera.
function setThreeCamera(view, proj) {
  camera.matrixAutoUpdate = false;
  camera.matrix.set(...view).invert();
  camera.matrixWorldNeedsUpdate = true;
  camera.projectionMatrix.set(...proj);
  camera.projectionMatrixInverse.copy(camera.projectionMatrix).invert();
}

status("connecting");
const ao = await connect(location.href, renderer, scene, camera, {
  build: true, digests: params.get("digests") === "1",
  onStreaming: () => status("streaming"),
  onError: (a) => status(a.state, a.message, true),
});
app.ao = ao;
app.scene = ao.serverScene;
const [lo, hi] = worldBounds(ao.serverScene);
const far = 4 * Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]) + 1;
const path = ao.serverScene.cameraPaths[0] || null;
camera.near = far * 1e-4;
camera.far = far;
camera.fov = path ? path.fovY : 60;
const centre = lo.map((v, i) => (v + hi[i]) / 2);
const radius = Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]) / 2;

function placeCamera(t) {
  if (app.fixedCamera) return setThreeCamera(app.fixedCamera.view, app.fixedCamera.proj);
  const [w, h] = size();
  camera.aspect = w / h;
  camera.matrixAutoUpdate = true;
  camera.updateProjectionMatrix();
  const [eye, target] = path ? cameraAt(path, t) : [[centre[0] + 1.5 * radius * Math.cos(t / 8), centre[1] + 0.6 * radius, centre[2] + 1.5 * radius * Math.sin(t / 8)], centre];
  const m = new THREE.Matrix4().set(...lookAt(eye, target)).invert();
  m.decompose(camera.position, camera.quaternion, camera.scale);
}
placeCamera(0);

const composer = new EffectComposer(renderer);
const [w0, h0] = size();
composer.setPixelRatio(1);
composer.setSize(w0, h0);
const passes = { render: new RenderPass(scene, camera), psao: ao.pass(), gtao: new GTAOPass(scene, camera, w0, h0), sao: new SAOPass(scene, camera),
                 output: new OutputPass() };
// three.js's AO at the scene's AO distance (their defaults are for scenes a few units across).
const aoDistance = ao.serverScene.aoDistance;
passes.gtao.updateGtaoMaterial({ radius: aoDistance });
Object.assign(passes.sao.params, { saoScale: far / aoDistance, saoKernelRadius: 16 });
for (const p of Object.values(passes)) composer.addPass(p);

document.getElementById("mode").value = app.mode;
document.getElementById("mode").onchange = (e) => { app.mode = e.target.value; };

function drawFrame() {
  const [w, h] = size();
  if (w !== composer.renderTarget1.width || h !== composer.renderTarget1.height) { renderer.setSize(w, h, false); composer.setSize(w, h); }
  placeCamera(performance.now() / 1000);
  passes.psao.enabled = app.mode === "psao" || app.mode === "psao-only";
  passes.psao.aoOnly = app.mode === "psao-only";
  passes.gtao.enabled = app.mode === "gtao";
  passes.sao.enabled = app.mode === "sao";
  const t0 = performance.now();
  composer.render();
  renderer.getContext().readPixels(0, 0, 1, 1, renderer.getContext().RGBA, renderer.getContext().UNSIGNED_BYTE, new Uint8Array(4));  // waits for the frame
  app.frameMs = performance.now() - t0;
  app.frames++;
}

const b64 = (a) => { const b = new Uint8Array(a.buffer, a.byteOffset, a.byteLength); let s = ""; for (let i = 0; i < b.length; i += 8192) s += String.fromCharCode(...b.subarray(i, i + 8192)); return btoa(s); };
app.renderOnce = () => { drawFrame(); return app.frameMs; };
app.setCamera = (view, proj) => { app.fixedCamera = view ? { view: Array.from(view), proj: Array.from(proj) } : null; };
app.digest = () => ao.digest();
Object.defineProperty(app, "digestLog", { get: () => ao.digestLog });
Object.defineProperty(app, "updates", { get: () => ao.updates });
Object.defineProperty(app, "mirror", { get: () => ao.mirror });
Object.defineProperty(app, "reconnects", { get: () => ao.reconnects });
// The PSAO pass's G-buffer inputs and output and the mirror, as base64 (bottom-up rows), as the page's readPsao.
app.readPsao = () => {
  const m = ao.mirror;
  return { width: ao.size[0], height: ao.size[1], local: b64(ao.read(0)), normal: b64(ao.read(1)), ao: b64(ao.read(null)),
           instances: b64(m.instances), buckets: b64(m.buckets), cells: b64(m.cells), transforms: b64(m.transforms),
           serverTime: m.serverTime, tick: m.tick };
};

// Each method's AO term of the frame (visibility, 1 unoccluded, bottom-up rows, red channel), as the
// benchmark scores it against RTAO: PSAO's AO target, GTAOPass's denoised AO, SAOPass's blurred SAO (the
// buffers each pass multiplies the lit frame by). One frame is drawn in each mode; the mode is left as it was.
app.readAoTerms = () => {
  const [w, h] = ao.size, was = app.mode, out = {};
  const read = (target) => {
    const half = target.texture.type === THREE.HalfFloatType;
    const buf = half ? new Uint16Array(w * h * 4) : new Float32Array(w * h * 4);
    renderer.readRenderTargetPixels(target, 0, 0, w, h, buf);
    return { dtype: half ? "float16" : "float32", data: b64(buf) };
  };
  for (const [mode, target] of [["psao", () => ao.aoTarget], ["gtao", () => passes.gtao.pdRenderTarget], ["sao", () => passes.sao.saoRenderTarget]]) {
    app.mode = mode;
    drawFrame();
    out[mode] = read(target());
  }
  app.mode = was;
  return out;
};

let lastStats = performance.now();
function loop(now) {
  if (ao.state === "streaming" && !app.paused) {
    try { drawFrame(); } catch (exc) { status("error", `Drawing a frame failed: ${exc.message}`, true); return; }
  }
  if (now - lastStats >= 1000) {
    statsEl.innerHTML = [["frame ms", app.frameMs.toFixed(1)], ["updates", ao.updates], ["tick", ao.mirror ? ao.mirror.tick : "-"], ["AO", app.mode]]
      .map(([k, v]) => `<tr><td>${k}</td><td>${v}</td></tr>`).join("");
    lastStats = now;
  }
  requestAnimationFrame(loop);
}
requestAnimationFrame(loop);
if (ao.state !== "streaming") status(ao.state);
