// The server's scene (src/psao/protocol/scenefile.py): parse the decompressed blob, pose skins, build the
// triangle soups the G-buffer draws (flat face normals, as the Python client's geometry pass).
import * as C from "/psao_constants.js";
import { ProtocolError, Reader } from "/wire.js";

const dec = new TextDecoder("utf-8", { fatal: true });
const name = (r) => dec.decode(r.take(r.u16()));

function finite(arr, what) {
  for (const v of arr) if (!Number.isFinite(v)) throw new ProtocolError(`scene: ${what} has NaN or infinite numbers`);
  return arr;
}

export function parseScene(bytes) {
  const r = new Reader(bytes, "scene");
  const magic = String.fromCharCode(...r.take(4));
  if (magic !== C.SCENE_MAGIC) throw new ProtocolError(`scene: bad magic ${magic}`);
  const version = r.u16();
  if (version !== C.SCENE_VERSION) throw new ProtocolError(`scene: format version ${version}, this page reads ${C.SCENE_VERSION}`);
  r.u16();
  const scene = { aoDistance: r.f64(), name: name(r), meshes: [], instances: [], cameraPaths: [] };
  const nMesh = r.u32(), nInst = r.u32(), nPath = r.u32();
  for (let i = 0; i < nMesh; i++) {
    const m = { name: name(r) };
    const flags = r.u8();
    r.take(3);
    m.color = [r.f32(), r.f32(), r.f32()];
    const nv = r.u32(), nf = r.u32();
    m.doubleSided = !!(flags & C.FLAG_DOUBLE_SIDED_MESH);
    m.vertices = finite(r.f32s(3 * nv), `mesh '${m.name}' vertices`);
    m.faces = r.u32s(3 * nf);
    for (const f of m.faces) if (f >= nv) throw new ProtocolError(`scene: mesh '${m.name}' has a face index outside its vertices`);
    if (flags & C.FLAG_SKINNED) {
      const nj = r.u16();
      r.u16();
      const k = r.u32(), period = r.f32();
      const joints = r.take(4 * nv).slice();
      for (const j of joints) if (j >= nj) throw new ProtocolError(`scene: mesh '${m.name}' refers to a joint outside 0..${nj - 1}`);
      m.skin = { nJoints: nj, samples: k, period, joints, weights: finite(r.f32s(4 * nv), "skin weights"),
                 matrices: finite(r.f32s(12 * nj * k), "skin matrices") };
    }
    scene.meshes.push(m);
  }
  for (let i = 0; i < nInst; i++) {
    const inst = { name: name(r), mesh: r.u32() };
    if (inst.mesh >= nMesh) throw new ProtocolError(`scene: instance '${inst.name}' refers to a missing mesh`);
    inst.transform = finite(r.f32s(16), "instance transform");
    scene.instances.push(inst);
  }
  for (let i = 0; i < nPath; i++) {
    const p = { name: name(r), fovY: r.f32(), loop: !!r.u8() };
    r.take(3);
    const k = r.u32();
    if (k === 0) throw new ProtocolError(`scene: camera path '${p.name}' has no keys`);
    const raw = finite(r.f32s(7 * k), "camera path");
    p.keys = [];
    for (let j = 0; j < k; j++) p.keys.push({ time: raw[7 * j], eye: Array.from(raw.subarray(7 * j + 1, 7 * j + 4)),
                                               target: Array.from(raw.subarray(7 * j + 4, 7 * j + 7)) });
    scene.cameraPaths.push(p);
  }
  r.done();
  return scene;
}

// Skinning matrices (J x 3x4, row-major) at time t: the samples around t mod period, blended linearly
// (psao.protocol.scenefile.skin_pose).
export function skinPose(skin, t) {
  const k = skin.samples, J12 = 12 * skin.nJoints;
  let i = 0, j = 0, f = 0;
  if (k > 1 && skin.period > 0) {
    const tt = ((t % skin.period) + skin.period) % skin.period;
    const u = (tt / skin.period) * k;
    i = Math.min(Math.floor(u), k - 1);
    j = (i + 1) % k;
    f = u - i;
  }
  const out = new Float32Array(J12);
  const a = skin.matrices.subarray(i * J12, (i + 1) * J12), b = skin.matrices.subarray(j * J12, (j + 1) * J12);
  for (let q = 0; q < J12; q++) out[q] = a[q] * (1 - f) + b[q] * f;
  return out;
}

// Mesh-local vertex positions at time t (null: the rest pose).
export function posedVertices(mesh, t) {
  if (!mesh.skin || t === null) return mesh.vertices;
  const s = mesh.skin, M = skinPose(s, t), v = mesh.vertices, out = new Float32Array(v.length);
  const m = new Float32Array(12);
  for (let i = 0; i < v.length / 3; i++) {
    m.fill(0);
    for (let k = 0; k < 4; k++) {
      const w = s.weights[4 * i + k];
      if (!w) continue;
      const o = 12 * s.joints[4 * i + k];
      for (let q = 0; q < 12; q++) m[q] += w * M[o + q];
    }
    const x = v[3 * i], y = v[3 * i + 1], z = v[3 * i + 2];
    out[3 * i] = m[0] * x + m[1] * y + m[2] * z + m[3];
    out[3 * i + 1] = m[4] * x + m[5] * y + m[6] * z + m[7];
    out[3 * i + 2] = m[8] * x + m[9] * y + m[10] * z + m[11];
  }
  return out;
}

// Triangle soup of a mesh: interleaved (position xyz, face normal xyz) per corner, float32.
export function triangleSoup(vertices, faces) {
  const out = new Float32Array(faces.length * 6);
  for (let f = 0; f < faces.length; f += 3) {
    const a = 3 * faces[f], b = 3 * faces[f + 1], c = 3 * faces[f + 2];
    const ux = vertices[b] - vertices[a], uy = vertices[b + 1] - vertices[a + 1], uz = vertices[b + 2] - vertices[a + 2];
    const vx = vertices[c] - vertices[a], vy = vertices[c + 1] - vertices[a + 1], vz = vertices[c + 2] - vertices[a + 2];
    let nx = uy * vz - uz * vy, ny = uz * vx - ux * vz, nz = ux * vy - uy * vx;
    const len = Math.hypot(nx, ny, nz) || 1;
    nx /= len; ny /= len; nz /= len;
    for (let k = 0; k < 3; k++) {
      const src = 3 * faces[f + k], o = 6 * (f + k);
      out[o] = vertices[src]; out[o + 1] = vertices[src + 1]; out[o + 2] = vertices[src + 2];
      out[o + 3] = nx; out[o + 4] = ny; out[o + 5] = nz;
    }
  }
  return out;
}

export function worldBounds(scene) {
  const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
  for (const inst of scene.instances) {
    const v = scene.meshes[inst.mesh].vertices, m = inst.transform;
    for (let i = 0; i < v.length; i += 3) {
      for (let r = 0; r < 3; r++) {
        const w = m[4 * r] * v[i] + m[4 * r + 1] * v[i + 1] + m[4 * r + 2] * v[i + 2] + m[4 * r + 3];
        lo[r] = Math.min(lo[r], w);
        hi[r] = Math.max(hi[r], w);
      }
    }
  }
  return [lo, hi];
}
