// Camera matrices (row-major 4x4, column vectors, OpenGL conventions as src/psao/scene/camera.py), the
// scene's camera paths (Catmull-Rom in time, as camera_at), and orbit / fly controls.
const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const norm = (a) => { const l = Math.hypot(...a) || 1; return [a[0] / l, a[1] / l, a[2] / l]; };
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];

export function lookAt(eye, target, up = [0, 1, 0]) {
  const f = norm(sub(target, eye));
  let s = cross(f, up);
  if (Math.hypot(...s) < 1e-12) s = cross(f, Math.abs(f[0]) < 0.9 ? [1, 0, 0] : [0, 0, 1]);
  s = norm(s);
  const u = cross(s, f);
  return new Float32Array([s[0], s[1], s[2], -dot(s, eye), u[0], u[1], u[2], -dot(u, eye),
                           -f[0], -f[1], -f[2], dot(f, eye), 0, 0, 0, 1]);
}

export function perspective(fovYDeg, aspect, near, far) {
  const f = 1 / Math.tan((fovYDeg * Math.PI) / 360);
  return new Float32Array([f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) / (near - far), (2 * far * near) / (near - far),
                           0, 0, -1, 0]);
}

function closed(path) {
  const a = path.keys[0], b = path.keys[path.keys.length - 1];
  const near = (x, y) => x.every((v, i) => Math.abs(v - y[i]) <= 1e-8 + 1e-5 * Math.abs(y[i]));
  return path.loop && path.keys.length > 2 && near(a.eye, b.eye) && near(a.target, b.target);
}

// (eye, target) of a camera path at time t seconds (psao.scene.camera.camera_at, Catmull-Rom).
export function cameraAt(path, t) {
  const keys = path.keys, n = keys.length;
  const pts = keys.map((k) => [...k.eye, ...k.target]), times = keys.map((k) => k.time);
  if (n === 1) return [pts[0].slice(0, 3), pts[0].slice(3)];
  const t0 = times[0], t1 = times[n - 1];
  t = t1 <= t0 ? t0 : path.loop ? t0 + ((((t - t0) % (t1 - t0)) + (t1 - t0)) % (t1 - t0)) : Math.min(Math.max(t, t0), t1);
  let i = 0;
  while (i < n - 2 && times[i + 1] <= t) i++;
  const span = times[i + 1] - times[i], u = span <= 0 ? 0 : (t - times[i]) / span;
  const isClosed = closed(path), period = t1 - t0;
  const key = (j) => {
    if (isClosed && j < 0) return [times[n - 1 + j] - period, pts[n - 1 + j]];
    if (isClosed && j >= n) return [times[j - n + 1] + period, pts[j - n + 1]];
    j = Math.min(Math.max(j, 0), n - 1);
    return [times[j], pts[j]];
  };
  const tangent = (j) => { const [ta, pa] = key(j - 1), [tb, pb] = key(j + 1); return pa.map((v, q) => (pb[q] - v) / (tb - ta)); };
  const m1 = tangent(i), m2 = tangent(i + 1);
  const h00 = 2 * u ** 3 - 3 * u ** 2 + 1, h10 = u ** 3 - 2 * u ** 2 + u, h01 = -2 * u ** 3 + 3 * u ** 2, h11 = u ** 3 - u ** 2;
  const p = pts[i].map((v, q) => h00 * v + h10 * m1[q] * span + h01 * pts[i + 1][q] + h11 * m2[q] * span);
  return [p.slice(0, 3), p.slice(3)];
}

// Orbit (drag: rotate, right drag / shift drag: pan, wheel: zoom) and fly (WASD/QE, drag: look) on a canvas.
export class Controls {
  constructor(canvas) {
    this.mode = "orbit";
    this.target = [0, 0, 0];
    this.distance = 10;
    this.yaw = 0.6;
    this.pitch = 0.35;
    this.eye = [0, 0, 10];
    this.keys = new Set();
    this.dragging = null;
    canvas.addEventListener("contextmenu", (e) => e.preventDefault());
    canvas.addEventListener("pointerdown", (e) => { this.dragging = { x: e.clientX, y: e.clientY, pan: e.button === 2 || e.shiftKey }; canvas.setPointerCapture(e.pointerId); });
    canvas.addEventListener("pointerup", () => { this.dragging = null; });
    canvas.addEventListener("pointermove", (e) => this.drag(e));
    canvas.addEventListener("wheel", (e) => { e.preventDefault(); this.distance *= Math.exp(e.deltaY * 0.001); }, { passive: false });
    window.addEventListener("keydown", (e) => this.keys.add(e.key.toLowerCase()));
    window.addEventListener("keyup", (e) => this.keys.delete(e.key.toLowerCase()));
  }
  frame(lo, hi) {
    this.target = lo.map((v, i) => (v + hi[i]) / 2);
    this.distance = Math.hypot(...sub(hi, lo)) * 0.8;
    this.speed = Math.hypot(...sub(hi, lo)) * 0.15;
    this.eye = this.orbitEye();
  }
  forward() { return [-Math.cos(this.pitch) * Math.sin(this.yaw), -Math.sin(this.pitch), -Math.cos(this.pitch) * Math.cos(this.yaw)]; }
  orbitEye() { const f = this.forward(); return this.target.map((v, i) => v - f[i] * this.distance); }
  drag(e) {
    if (!this.dragging) return;
    const dx = e.clientX - this.dragging.x, dy = e.clientY - this.dragging.y;
    this.dragging.x = e.clientX;
    this.dragging.y = e.clientY;
    if (this.dragging.pan && this.mode === "orbit") {
      const f = this.forward(), s = norm(cross(f, [0, 1, 0])), u = cross(s, f), k = this.distance * 0.0015;
      this.target = this.target.map((v, i) => v - s[i] * dx * k + u[i] * dy * k);
      return;
    }
    this.yaw -= dx * 0.005;
    this.pitch = Math.max(-1.5, Math.min(1.5, this.pitch + dy * 0.005 * (this.mode === "orbit" ? 1 : -1)));
  }
  // World -> view matrix after dt seconds of key input.
  view(dt) {
    if (this.mode === "fly") {
      const f = this.forward(), s = norm(cross(f, [0, 1, 0])), step = (this.speed || 1) * dt;
      const k = this.keys, mv = (dir, sign) => { this.eye = this.eye.map((v, i) => v + dir[i] * sign * step); };
      if (k.has("w")) mv(f, 1);
      if (k.has("s")) mv(f, -1);
      if (k.has("d")) mv(s, 1);
      if (k.has("a")) mv(s, -1);
      if (k.has("e")) mv([0, 1, 0], 1);
      if (k.has("q")) mv([0, 1, 0], -1);
      return lookAt(this.eye, this.eye.map((v, i) => v + f[i]));
    }
    this.eye = this.orbitEye();
    return lookAt(this.eye, this.target);
  }
}
