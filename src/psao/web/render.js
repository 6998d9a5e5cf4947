// WebGL2 renderer: G-buffer (4 targets), PSAO pass (GLSL ES port of the desktop lookup, grid tables as
// RGBA32UI textures read with texelFetch, NEAREST), SSAO + blur, composite. Skinned meshes are posed on
// the CPU at the server time of the last Update and re-uploaded; the G-buffer's local position and normal
// come from a second, fixed buffer of the rest pose (where the server keeps a skinned mesh's AO points).
import * as C from "/psao_constants.js";
import { posedVertices, triangleSoup } from "/scene.js";

const LIGHT = { dir: [0.35, 0.9, 0.25], ambient: 0.35, diffuse: 0.65 };  // gbuffer.LightSettings
const BACKGROUND = [0.62, 0.74, 0.88];  // composite.BACKGROUND
const TABLE_WIDTHS = Object.keys(C.GLSL_DEFINES).map(Number).sort((a, b) => b - a);  // widest first
export const MODES = { psao: 0, ssao: 1, none: 2, "psao-only": 3, "ssao-only": 4 };

export class RenderError extends Error {}

async function source(path) {
  const r = await fetch(path);
  if (!r.ok) throw new RenderError(`cannot load ${path}: HTTP ${r.status}`);
  return r.text();
}

function transpose3(m) { return [m[0], m[3], m[6], m[1], m[4], m[7], m[2], m[5], m[8]]; }

// Inverse transpose of the upper 3x3 of a row-major 4x4, as a column-major mat3 for uniformMatrix3fv.
function normalMatrix(m) {
  const a = [m[0], m[1], m[2], m[4], m[5], m[6], m[8], m[9], m[10]];
  const c = [a[4] * a[8] - a[5] * a[7], a[5] * a[6] - a[3] * a[8], a[3] * a[7] - a[4] * a[6],
             a[2] * a[7] - a[1] * a[8], a[0] * a[8] - a[2] * a[6], a[1] * a[6] - a[0] * a[7],
             a[1] * a[5] - a[2] * a[4], a[2] * a[3] - a[0] * a[5], a[0] * a[4] - a[1] * a[3]];
  const det = a[0] * c[0] + a[1] * c[1] + a[2] * c[2];
  // c is the cofactor matrix (row-major): inverse transpose = c / det; column-major upload = transpose.
  return { matrix: new Float32Array(transpose3(c.map((v) => v / det))), mirrored: det < 0 };
}

export class Renderer {
  constructor(canvas) {
    const gl = canvas.getContext("webgl2", { antialias: false, preserveDrawingBuffer: true, depth: false });
    if (!gl) throw new RenderError("this browser has no WebGL2");
    if (!gl.getExtension("EXT_color_buffer_float")) throw new RenderError("WebGL2 without EXT_color_buffer_float: float G-buffers cannot be rendered");
    this.gl = gl;
    this.canvas = canvas;
    const maxTex = gl.getParameter(gl.MAX_TEXTURE_SIZE);
    this.maxTexture = maxTex;
    // The widest grid table row the browser allows (2048 is always allowed): taller tables fit then.
    this.tableWidth = TABLE_WIDTHS.find((w) => w <= maxTex) || TABLE_WIDTHS[TABLE_WIDTHS.length - 1];
    this.meshes = [];
    this.tables = {};
    this.size = [0, 0];
  }

  async init() {
    const names = ["psao_lookup.glsl", "psao_normals.glsl", "gbuffer.vert", "gbuffer.frag", "fullscreen.vert", "psao.frag", "ssao.frag", "ssao_blur.frag", "composite.frag"];
    const src = Object.fromEntries(await Promise.all(names.map(async (n) => [n, await source(`/shaders/${n}`)])));
    const head = "#version 300 es\nprecision highp float;\nprecision highp int;\nprecision highp usampler2D;\n";
    const psaoHead = head + C.GLSL_DEFINES[this.tableWidth] + src["psao_normals.glsl"];
    this.progs = {
      gbuffer: this.program(head + src["gbuffer.vert"], head + src["gbuffer.frag"], "gbuffer"),
      psao: this.program(head + src["fullscreen.vert"], psaoHead + src["psao_lookup.glsl"] + src["psao.frag"], "psao"),
      ssao: this.program(head + src["fullscreen.vert"], head + `#define SSAO_SAMPLES ${C.SSAO_SAMPLES}\n` + src["ssao.frag"], "ssao"),
      blur: this.program(head + src["fullscreen.vert"], head + src["ssao_blur.frag"], "ssao_blur"),
      composite: this.program(head + src["fullscreen.vert"], head + src["composite.frag"], "composite"),
    };
    const gl = this.gl;
    this.emptyVao = gl.createVertexArray();
    const codes = C.NORMAL_CODES;
    this.normals = this.texture(gl.RGBA32F, codes, 1, gl.RGBA, gl.FLOAT,
                                new Float32Array(codes * 4).map((_, i) => (i % 4 === 3 ? 0 : C.OCT_NORMALS[3 * (i >> 2) + (i % 4)])));
    // The desktop SSAO's kernel and noise (psao.protocol.ssao_kernel, served in psao_constants.js).
    this.noise = this.texture(gl.RGBA32F, 4, 4, gl.RGBA, gl.FLOAT, new Float32Array(C.SSAO_NOISE));
    this.kernel = new Float32Array(C.SSAO_KERNEL);
  }

  program(vs, fs, name) {
    const gl = this.gl;
    const p = gl.createProgram();
    for (const [type, text] of [[gl.VERTEX_SHADER, vs], [gl.FRAGMENT_SHADER, fs]]) {
      const s = gl.createShader(type);
      gl.shaderSource(s, text);
      gl.compileShader(s);
      if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new RenderError(`GLSL error in ${name}: ${gl.getShaderInfoLog(s)}`);
      gl.attachShader(p, s);
    }
    gl.linkProgram(p);
    if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new RenderError(`GLSL link error in ${name}: ${gl.getProgramInfoLog(p)}`);
    const loc = {};
    const n = gl.getProgramParameter(p, gl.ACTIVE_UNIFORMS);
    for (let i = 0; i < n; i++) {
      const u = gl.getActiveUniform(p, i);
      loc[u.name.replace(/\[0\]$/, "")] = gl.getUniformLocation(p, u.name);
    }
    return { p, loc };
  }

  texture(internal, w, h, format, type, data, filter) {
    const gl = this.gl;
    const t = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, t);
    gl.texImage2D(gl.TEXTURE_2D, 0, internal, w, h, 0, format, type, data || null);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, filter || gl.NEAREST);  // integer and float tables: NEAREST
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, filter || gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    return t;
  }

  // ---------------------------------------------------------------------------------------- scene
  setScene(scene) {
    const gl = this.gl;
    for (const m of this.meshes) {
      gl.deleteBuffer(m.buffer);
      if (m.rest !== m.buffer) gl.deleteBuffer(m.rest);
      gl.deleteVertexArray(m.vao);
    }
    this.scene = scene;
    this.skinTime = null;
    // Attributes 0, 1: the drawn triangles (posed); 2, 3: the rest pose (the same buffer without a skin).
    const bind = (buffer, first) => {
      gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
      gl.enableVertexAttribArray(first);
      gl.vertexAttribPointer(first, 3, gl.FLOAT, false, 24, 0);
      gl.enableVertexAttribArray(first + 1);
      gl.vertexAttribPointer(first + 1, 3, gl.FLOAT, false, 24, 12);
    };
    this.meshes = scene.meshes.map((mesh) => {
      const vao = gl.createVertexArray();
      const soup = triangleSoup(mesh.vertices, mesh.faces);
      const rest = gl.createBuffer();
      gl.bindBuffer(gl.ARRAY_BUFFER, rest);
      gl.bufferData(gl.ARRAY_BUFFER, soup, gl.STATIC_DRAW);
      let buffer = rest;
      if (mesh.skin) {
        buffer = gl.createBuffer();
        gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
        gl.bufferData(gl.ARRAY_BUFFER, soup, gl.DYNAMIC_DRAW);
      }
      gl.bindVertexArray(vao);
      bind(buffer, 0);
      bind(rest, 2);
      gl.bindVertexArray(null);
      return { vao, buffer, rest, count: mesh.faces.length };
    });
  }

  // Pose skinned meshes' drawn triangles at scene time t (null: rest pose), as the server posed the points it traced.
  setSkinTime(t) {
    if (t === this.skinTime || !this.scene) return;
    const gl = this.gl;
    this.scene.meshes.forEach((mesh, i) => {
      if (!mesh.skin) return;
      gl.bindBuffer(gl.ARRAY_BUFFER, this.meshes[i].buffer);
      gl.bufferSubData(gl.ARRAY_BUFFER, 0, triangleSoup(posedVertices(mesh, t), mesh.faces));
    });
    this.skinTime = t;
  }

  // ------------------------------------------------------------------------------------ grid tables
  tableFor(name, rows, rowWords) {
    const gl = this.gl;
    const texelsPerRow = rowWords / 4;
    const nTexels = Math.max(rows.length / rowWords, 1) * texelsPerRow;
    const height = Math.ceil(nTexels / this.tableWidth);
    if (height > this.maxTexture)
      throw new RenderError(`grid ${name} table of ${rows.length / rowWords} rows exceeds this browser's texture limit (${this.maxTexture})`);
    const data = new Uint32Array(height * this.tableWidth * 4);
    data.set(rows);
    if (name === "buckets") data.fill(C.EMPTY, rows.length);
    if (name === "cells") for (let i = rows.length + C.KEY_WORD; i < data.length; i += C.CELL_WORDS) data[i] = C.EMPTY;
    const old = this.tables[name];
    if (old) gl.deleteTexture(old.texture);
    const texture = this.texture(gl.RGBA32UI, this.tableWidth, height, gl.RGBA_INTEGER, gl.UNSIGNED_INT, data);
    this.tables[name] = { texture, rowWords, height, rows: rows.length / rowWords };
  }

  uploadGrid(mirror) {
    this.tableFor("instances", new Uint32Array(mirror.instances.slice().buffer), C.INSTANCE_BYTES / 4);
    this.tableFor("buckets", mirror.buckets, 2 * C.BUCKET_ENTRIES);
    this.tableFor("cells", mirror.cells, C.CELL_WORDS);
    mirror.dirtyBuckets = [];
    mirror.dirtyCells = [];
    mirror.resized = false;
    this.uploadedBytes = mirror.buckets.byteLength + mirror.cells.byteLength;
  }

  // Write only the rows that changed (runs of nearby rows are merged), or everything after a resize.
  updateGrid(mirror) {
    if (mirror.resized || !this.tables.cells) return this.uploadGrid(mirror);
    this.writeDirty("buckets", mirror.buckets, mirror.dirtyBuckets);
    this.writeDirty("cells", mirror.cells, mirror.dirtyCells);
    mirror.dirtyBuckets = [];
    mirror.dirtyCells = [];
  }

  writeDirty(name, rows, dirtyLists) {
    if (!dirtyLists.length) return;
    const all = new Uint32Array(dirtyLists.reduce((n, l) => n + l.length, 0));
    let o = 0;
    for (const l of dirtyLists) { all.set(l, o); o += l.length; }
    all.sort();
    const gl = this.gl, t = this.tables[name], W = this.tableWidth, tpr = t.rowWords / 4;
    gl.bindTexture(gl.TEXTURE_2D, t.texture);
    let i = 0;
    while (i < all.length) {
      let j = i;
      while (j + 1 < all.length && all[j + 1] - all[j] <= 32) j++;
      const first = all[i] * tpr, last = (all[j] + 1) * tpr;
      let pos = first;
      while (pos < last) {
        const x = pos % W, y = Math.floor(pos / W);
        let count, w, h;
        if (x === 0 && last - pos >= W) { h = Math.floor((last - pos) / W); w = W; count = w * h; }
        else { count = Math.min(W - x, last - pos); w = count; h = 1; }
        gl.texSubImage2D(gl.TEXTURE_2D, 0, x, y, w, h, gl.RGBA_INTEGER, gl.UNSIGNED_INT, rows.subarray(pos * 4, (pos + count) * 4));
        pos += count;
      }
      i = j + 1;
    }
  }

  // ------------------------------------------------------------------------------------------ frame
  resize(w, h) {
    if (this.size[0] === w && this.size[1] === h) return;
    const gl = this.gl;
    this.size = [w, h];
    this.canvas.width = w;
    this.canvas.height = h;
    for (const t of this.targets || []) gl.deleteTexture(t);
    const f32 = () => this.texture(gl.RGBA32F, w, h, gl.RGBA, gl.FLOAT, null);
    const f16 = () => this.texture(gl.RGBA16F, w, h, gl.RGBA, gl.HALF_FLOAT, null);
    this.g = [f32(), f32(), f32(), f16()];
    this.aoTex = f32();
    this.ssaoRaw = f16();
    this.ssaoTex = f16();
    this.targets = [...this.g, this.aoTex, this.ssaoRaw, this.ssaoTex];
    if (this.depth) gl.deleteRenderbuffer(this.depth);
    this.depth = gl.createRenderbuffer();
    gl.bindRenderbuffer(gl.RENDERBUFFER, this.depth);
    gl.renderbufferStorage(gl.RENDERBUFFER, gl.DEPTH_COMPONENT24, w, h);
    this.fbo = this.framebuffer(this.g, this.depth);
    this.aoFbo = this.framebuffer([this.aoTex]);
    this.ssaoRawFbo = this.framebuffer([this.ssaoRaw]);
    this.ssaoFbo = this.framebuffer([this.ssaoTex]);
  }

  framebuffer(textures, depth) {
    const gl = this.gl;
    const fb = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, fb);
    textures.forEach((t, i) => gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0 + i, gl.TEXTURE_2D, t, 0));
    if (depth) gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, gl.RENDERBUFFER, depth);
    gl.drawBuffers(textures.map((_, i) => gl.COLOR_ATTACHMENT0 + i));
    const status = gl.checkFramebufferStatus(gl.FRAMEBUFFER);
    if (status !== gl.FRAMEBUFFER_COMPLETE) throw new RenderError(`framebuffer incomplete (0x${status.toString(16)})`);
    return fb;
  }

  bind(prog, textures) {
    const gl = this.gl;
    gl.useProgram(prog.p);
    Object.entries(textures).forEach(([name, tex], unit) => {
      gl.activeTexture(gl.TEXTURE0 + unit);
      gl.bindTexture(gl.TEXTURE_2D, tex);
      if (prog.loc[name]) gl.uniform1i(prog.loc[name], unit);
    });
  }

  fullscreen(fbo) {
    const gl = this.gl;
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
    gl.viewport(0, 0, this.size[0], this.size[1]);
    gl.bindVertexArray(this.emptyVao);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
  }

  // draw()'s passes on the grid uploaded so far (none yet: an empty one), showing the colour without AO.
  preview(transforms, view, proj, mode) {
    if (!this.tables.cells) this.uploadGrid({ instances: new Uint8Array(C.INSTANCE_BYTES), buckets: new Uint32Array(0), cells: new Uint32Array(0) });
    this.draw(transforms, view, proj, mode, true);
  }

  // transforms: Float32Array(16 n) row-major local -> world; view, proj: row-major Float32Array(16);
  // colourOnly: the AO is computed but not shown (preview).
  draw(transforms, view, proj, mode, colourOnly = false) {
    const gl = this.gl, [w, h] = this.size;
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.fbo);
    gl.viewport(0, 0, w, h);
    for (let i = 0; i < 4; i++) gl.clearBufferfv(gl.COLOR, i, [0, 0, 0, 0]);
    gl.clearBufferfi(gl.DEPTH_STENCIL, 0, 1, 0);
    gl.enable(gl.DEPTH_TEST);
    gl.disable(gl.CULL_FACE);  // single-sided meshes may be seen from behind
    const g = this.progs.gbuffer, L = g.loc;
    gl.useProgram(g.p);
    gl.uniformMatrix4fv(L.u_view, true, view);
    gl.uniformMatrix4fv(L.u_proj, true, proj);
    const ld = LIGHT.dir, ll = Math.hypot(...ld);
    gl.uniform3f(L.u_light_dir, ld[0] / ll, ld[1] / ll, ld[2] / ll);
    gl.uniform1f(L.u_ambient, LIGHT.ambient);
    gl.uniform1f(L.u_diffuse, LIGHT.diffuse);
    this.scene.instances.forEach((inst, i) => {
      const mesh = this.scene.meshes[inst.mesh], gm = this.meshes[inst.mesh];
      if (!gm.count) return;
      const model = transforms.subarray(16 * i, 16 * i + 16);
      const nm = normalMatrix(model);
      gl.uniformMatrix4fv(L.u_model, true, model);
      gl.uniformMatrix3fv(L.u_normal_matrix, false, nm.matrix);
      gl.uniform1i(L.u_mirrored, nm.mirrored ? 1 : 0);
      gl.uniform1i(L.u_double_sided, mesh.doubleSided ? 1 : 0);
      gl.uniform3fv(L.u_albedo, mesh.color);
      gl.uniform1f(L.u_instance, i + 1);
      gl.bindVertexArray(gm.vao);
      gl.drawArrays(gl.TRIANGLES, 0, gm.count);
    });
    gl.disable(gl.DEPTH_TEST);
    const usePsao = mode === "psao" || mode === "psao-only";
    const useSsao = mode === "ssao" || mode === "ssao-only";
    let ao = null;
    if (usePsao && this.tables.cells) {
      this.bind(this.progs.psao, { u_local: this.g[0], u_local_normal: this.g[1], u_psao_instances: this.tables.instances.texture,
                                   u_psao_buckets: this.tables.buckets.texture, u_psao_cells: this.tables.cells.texture,
                                   u_psao_normals: this.normals });
      this.fullscreen(this.aoFbo);
      ao = this.aoTex;
    } else if (useSsao) {
      const s = this.progs.ssao, radius = this.scene.aoDistance;
      this.bind(s, { u_normal_depth: this.g[2], u_noise: this.noise });
      gl.uniformMatrix4fv(s.loc.u_view, true, view);
      gl.uniformMatrix4fv(s.loc.u_proj, true, proj);
      gl.uniform3fv(s.loc.u_kernel, this.kernel);
      gl.uniform1f(s.loc.u_radius, radius);
      gl.uniform1f(s.loc.u_bias, radius * 0.025);
      gl.uniform4f(s.loc.u_unproject, 1 / proj[0], 1 / proj[5], proj[2], proj[6]);
      this.fullscreen(this.ssaoRawFbo);
      this.bind(this.progs.blur, { u_ao: this.ssaoRaw, u_normal_depth: this.g[2] });
      gl.uniform1f(this.progs.blur.loc.u_radius, radius);
      this.fullscreen(this.ssaoFbo);
      ao = this.ssaoTex;
    }
    const c = this.progs.composite;
    this.bind(c, { u_color: this.g[3], u_ao: ao || this.aoTex });
    gl.uniform3fv(c.loc.u_background, BACKGROUND);
    gl.uniform1i(c.loc.u_mode, colourOnly ? 1 : mode.endsWith("-only") ? 2 : ao ? 0 : 1);
    this.fullscreen(null);
  }

  // Float32 RGBA pixels of a render target, bottom-up rows (tests compare them with the oracle).
  read(texture) {
    const gl = this.gl, [w, h] = this.size;
    const fb = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, fb);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, texture, 0);
    const out = new Float32Array(w * h * 4);
    gl.readPixels(0, 0, w, h, gl.RGBA, gl.FLOAT, out);
    gl.deleteFramebuffer(fb);
    return out;
  }
}
