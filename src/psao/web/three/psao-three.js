// PSAO for three.js. `const ao = await connect(url, renderer, scene, camera, options)` connects to a PSAO
// server (ws:// or http:// URL of `psao serve`), takes its scene (SceneRequest), matches the server's
// instances to the application's meshes by name (or builds the meshes itself: options.build), mirrors the
// grid (Snapshot, Update), sends the three.js camera (Camera messages, options.cameraHz) and gives
// `ao.pass()`, an EffectComposer pass that multiplies the lit colour by the server's AO.
// The protocol, the scene parser and the digest are the web page's own modules and the lookup is the page's
// GLSL (src/psao/protocol/shaders/psao_lookup.glsl with the #define block of /psao_constants.js), all
// imported from the server that serves them, so there is one source of truth for every client.
// The AO pass draws a G-buffer of instance-local position and normal with the page's gbuffer shaders
// (skinned meshes posed at the server time of the last Update, local targets from the rest pose) and runs
// the page's psao.frag over it.
import * as THREE from "three";
import { FullScreenQuad, Pass } from "three/addons/postprocessing/Pass.js";

const SHADERS = ["psao_lookup.glsl", "psao_normals.glsl", "gbuffer.vert", "gbuffer.frag", "fullscreen.vert", "psao.frag"];
const HEAD = "precision highp float;\nprecision highp int;\nprecision highp usampler2D;\n";  // after three's #version 300 es
const RECONNECT_PAUSES = [0.25, 0.5, 1, 2];  // seconds; the last repeats (as the page's)
const LIGHT = { dir: [0.35, 0.9, 0.25], ambient: 0.35, diffuse: 0.65 };  // the page's (render.js) G-buffer light

export class PsaoError extends Error {}

// ws(s)://host/ and http(s)://host/ of one server URL.
function endpoints(url) {
  const u = new URL(url, typeof location !== "undefined" ? location.href : undefined);
  const secure = u.protocol === "https:" || u.protocol === "wss:";
  if (!["http:", "https:", "ws:", "wss:"].includes(u.protocol)) throw new PsaoError(`psao-three: ${url} is not a ws:// or http:// URL`);
  return { ws: `${secure ? "wss" : "ws"}://${u.host}/`, http: `${secure ? "https" : "http"}://${u.host}/`,
           token: u.searchParams.get("token") || "" };
}

// The page's modules from the server (one source of truth for the protocol, the scene and the digest).
async function serverModules(base) {
  const names = ["/psao_constants.js", "/wire.js", "/scene.js", "/digest.js", "/vendor/fzstd.js"];
  const [C, wire, scene, digest, fzstd] = await Promise.all(names.map((n) => import(new URL(n, base).href)));
  const src = Object.fromEntries(await Promise.all(SHADERS.map(async (n) => {
    const r = await fetch(new URL(`/shaders/${n}`, base));
    if (!r.ok) throw new PsaoError(`psao-three: cannot load /shaders/${n} from ${base}: HTTP ${r.status}`);
    return [n, await r.text()];
  })));
  return { C, wire, scene, digest, fzstd, src };
}

// Row-major Float32Array(16) of a three.js Matrix4 (the wire's and the page's convention), and back.
const rowMajor = (m) => new Float32Array(m.clone().transpose().elements);
const fromRowMajor = (m, a) => m.set(...a);

function integerTexture(data, width, height) {
  const t = new THREE.DataTexture(data, width, height, THREE.RGBAIntegerFormat, THREE.UnsignedIntType);
  t.internalFormat = "RGBA32UI";
  t.minFilter = t.magFilter = THREE.NearestFilter;
  t.generateMipmaps = false;
  t.flipY = false;
  t.needsUpdate = true;
  return t;
}

function floatTarget(w, h, count = 1) {
  return new THREE.WebGLRenderTarget(w, h, { count, type: THREE.FloatType, format: THREE.RGBAFormat, depthBuffer: count > 1,
                                             minFilter: THREE.NearestFilter, magFilter: THREE.NearestFilter, generateMipmaps: false });
}

// A G-buffer geometry over the drawn attributes (posed) and the rest pose's (the lookup's local targets).
function gbufferGeometry(posed, rest, index) {
  const g = new THREE.BufferGeometry();
  g.setAttribute("position", posed.position);
  g.setAttribute("in_position", posed.position);
  g.setAttribute("in_normal", posed.normal);
  g.setAttribute("in_rest_position", rest.position);
  g.setAttribute("in_rest_normal", rest.normal);
  if (index) g.setIndex(index);
  return g;
}

// Interleaved (position, face normal) triangle soup attributes, as the page's triangleSoup gives them.
function soupAttributes(soup, dynamic) {
  const buffer = new THREE.InterleavedBuffer(soup, 6);
  if (dynamic) buffer.setUsage(THREE.DynamicDrawUsage);
  return { buffer, position: new THREE.InterleavedBufferAttribute(buffer, 3, 0), normal: new THREE.InterleavedBufferAttribute(buffer, 3, 3) };
}

function triangles(geometry) {
  return (geometry.index ? geometry.index.count : geometry.getAttribute("position").count) / 3;
}

export class PsaoThree {
  constructor(mods, renderer, scene, camera, options) {
    this.m = mods;
    this.renderer = renderer;
    this.scene = scene;
    this.camera = camera;
    this.options = options;
    this.state = "connecting";
    this.message = "";
    this.mirror = null;
    this.serverScene = null;
    this.updates = 0;
    this.bytes = 0;
    this.seq = 0;
    this.digestLog = [];
    this.targets = [];  // per server instance: { object (the application's or built mesh), gmesh, material }
    this.tables = {};
    this.gridVersion = -1;
    this.skinTime = null;
    this.size = [0, 0];
    const C = mods.C, maxTex = renderer.capabilities.maxTextureSize;
    const widths = Object.keys(C.GLSL_DEFINES).map(Number).sort((a, b) => b - a);
    this.tableWidth = widths.find((w) => w <= maxTex) || widths[widths.length - 1];
    this.gScene = new THREE.Scene();
    this.gScene.matrixWorldAutoUpdate = true;
    this.view = { value: new THREE.Matrix4() };
    this.proj = { value: new THREE.Matrix4() };
    const codes = C.NORMAL_CODES, normals = new Float32Array(codes * 4);
    for (let i = 0; i < codes; i++) normals.set(C.OCT_NORMALS.slice(3 * i, 3 * i + 3), 4 * i);
    this.normalsTexture = new THREE.DataTexture(normals, codes, 1, THREE.RGBAFormat, THREE.FloatType);
    this.normalsTexture.needsUpdate = true;
    const src = mods.src;
    this.psaoQuad = new FullScreenQuad(new THREE.RawShaderMaterial({
      glslVersion: THREE.GLSL3, depthTest: false, depthWrite: false,
      vertexShader: HEAD + src["fullscreen.vert"],
      fragmentShader: HEAD + C.GLSL_DEFINES[this.tableWidth] + src["psao_normals.glsl"] + src["psao_lookup.glsl"] + src["psao.frag"],
      uniforms: { u_local: { value: null }, u_local_normal: { value: null }, u_psao_instances: { value: null },
                  u_psao_buckets: { value: null }, u_psao_cells: { value: null }, u_psao_normals: { value: this.normalsTexture } },
    }));
    this.setSize(1, 1);
  }

  // ------------------------------------------------------------------------------------ connection
  open(urls) {
    return new Promise((resolve, reject) => {
      this.settle = { resolve, reject };
      this.urls = urls;
      this.reconnects = 0;
      this.socket();
    });
  }

  // One connection (SceneRequest with the scene already held, so a reconnect is not sent it again). A lost
  // connection after the scene arrived reconnects after RECONNECT_PAUSES; GRID_REPLACED_CLOSE at once.
  socket() {
    const { C, wire } = this.m, urls = this.urls;
    this.session = new wire.ClientSession(this.options.token ?? urls.token, this.sceneHash || null,
                                          this.options.codecs ? { codecs: this.options.codecs } : {});
    const ws = new WebSocket(urls.ws);
    ws.binaryType = "arraybuffer";
    this.ws = ws;
    let opened = false;
    ws.onopen = () => { opened = true; ws.send(this.session.sceneRequest()); };
    ws.onmessage = (e) => {
      if (this.ws !== ws) return;
      this.bytes += e.data.byteLength;
      try {
        this.handle(this.session.receive(e.data));
      } catch (exc) {
        this.fail(exc);
      }
    };
    ws.onclose = (e) => {
      if (this.ws !== ws) return;
      this.ws = null;
      clearInterval(this.cameraTimer);
      const what = opened ? `the connection to ${urls.ws} closed (code ${e.code})` : `cannot connect to ${urls.ws} (code ${e.code})`;
      if (!this.serverScene) { this.fail(new PsaoError(`psao-three: ${what}`), "server gone"); return; }
      if (e.code === C.GRID_REPLACED_CLOSE) { this.gridReplacements = (this.gridReplacements || 0) + 1; this.socket(); return; }
      const pause = RECONNECT_PAUSES[Math.min(this.reconnects, RECONNECT_PAUSES.length - 1)];
      this.state = "server gone";
      this.message = `psao-three: ${what}; reconnecting in ${pause} s (attempt ${this.reconnects + 1})`;
      if (this.options.onError) this.options.onError(this);
      this.retry = setTimeout(() => { this.reconnects++; this.socket(); }, pause * 1000);
    };
  }

  fail(exc, state = "error") {
    const { RemoteError } = this.m.wire;
    this.state = state;
    this.message = exc instanceof RemoteError ? `the server refused: ${exc.text} (${exc.codeName})` : String(exc.message || exc);
    if (this.settle) { this.settle.reject(exc instanceof PsaoError ? exc : new PsaoError(`psao-three: ${this.message}`)); this.settle = null; }
    if (this.ws) { const ws = this.ws; this.ws = null; ws.close(); }
    clearInterval(this.cameraTimer);
    if (this.options.onError) this.options.onError(this);
  }

  handle(ev) {
    if (!ev) return;
    const { C, wire } = this.m;
    if (ev.kind === "scene") {
      if (ev.blob && this.serverScene) throw new PsaoError("psao-three: the server now serves another scene; connect again");
      if (ev.blob) {
        const raw = this.m.fzstd.decompress(ev.blob);
        if (raw.length > C.LIMITS.scene_payload_bytes) throw new wire.ProtocolError("scene over the size limit");
        this.serverScene = this.m.scene.parseScene(raw);
        this.attach();  // a mismatch throws here: connect() rejects with it
      }
      this.sceneHash = ev.hash;
      this.ws.send(this.session.hello());
      this.state = "loading snapshot";
      if (this.settle) { this.settle.resolve(this); this.settle = null; }
    } else if (ev.kind === "welcome") {
      this.seq = 0;
      this.mirror = new wire.Mirror(ev.welcome);
      this.gridVersion = -1;  // a new connection's snapshot: every table written again
      this.connectionId = ev.welcome.connectionId;
      this.startCameras();
    } else if (ev.kind === "snapshot") {
      this.mirror.apply(ev.delta);
      if (ev.complete) {
        this.state = "streaming";
        if (this.options.onStreaming) this.options.onStreaming(this);
      }
    } else if (ev.kind === "update") {
      this.mirror.apply(ev.delta);
      this.mirror.tick = ev.tick;
      this.mirror.serverTime = ev.serverTime;
      this.updates++;
      if (this.options.onUpdate) this.options.onUpdate(this);
    } else if (ev.kind === "bye") {
      this.state = "server gone";
    }
    if (ev.kind === "welcome" || ev.kind === "snapshot" || ev.kind === "update") {
      if (this.options.digests && ev.kind !== "welcome") this.digestLog.push({ conn: this.connectionId, seq: this.seq, tick: this.mirror.tick, digest: this.digest() });
      this.seq++;
    }
  }

  startCameras() {
    const ws = this.ws, hz = this.options.cameraHz || 30;
    clearInterval(this.cameraTimer);
    this.cameraTimer = setInterval(() => {
      if (ws.readyState !== WebSocket.OPEN || ws !== this.ws) { clearInterval(this.cameraTimer); return; }
      this.camera.updateMatrixWorld();
      ws.send(this.m.wire.cameraMessage(rowMajor(this.camera.matrixWorldInverse), rowMajor(this.camera.projectionMatrix)));
    }, 1000 / hz);
  }

  close() {
    clearInterval(this.cameraTimer);
    clearTimeout(this.retry);
    const ws = this.ws;
    this.ws = null;
    if (ws && ws.readyState === WebSocket.OPEN) { ws.send(this.m.wire.byeMessage()); ws.close(); }
    this.state = "closed";
  }

  digest() { return this.mirror ? this.m.digest.mirrorDigest(this.mirror) : null; }

  // -------------------------------------------------------------------------------------- meshes
  // Each server instance gets a mesh: the application's object named as the instance (or options.match's),
  // or one built from the delivered scene (options.build) and added to the application's scene.
  attach() {
    const sc = this.serverScene, byName = new Map();
    if (!this.options.build) this.scene.traverse((o) => { if (o.isMesh && o.name && !byName.has(o.name)) byName.set(o.name, o); });
    const built = this.options.build ? this.buildMeshes() : null;
    const missing = [], wrong = [];
    const pairs = sc.instances.map((inst, i) => {
      const mesh = sc.meshes[inst.mesh];
      if (built) return { object: built(inst, i), geometry: built.gbuffer[inst.mesh] };
      const object = this.options.match ? this.options.match(inst, mesh, this.scene) : byName.get(inst.name);
      if (!object || !object.isMesh) { missing.push(inst.name); return null; }
      if (object.isSkinnedMesh) throw new PsaoError(`psao-three: '${inst.name}' is a three.js SkinnedMesh; connect with { build: true } for skinned scenes`);
      if (triangles(object.geometry) !== mesh.faces.length / 3) { wrong.push(`${inst.name} (${triangles(object.geometry)} triangles, the server's ${mesh.faces.length / 3})`); return null; }
      const a = { position: object.geometry.getAttribute("position"), normal: object.geometry.getAttribute("normal") };
      if (!a.normal) { object.geometry.computeVertexNormals(); a.normal = object.geometry.getAttribute("normal"); }
      return { object, geometry: gbufferGeometry(a, a, object.geometry.index) };
    });
    if (missing.length || wrong.length)
      throw new PsaoError(`psao-three: the three.js scene does not match the server's '${sc.name}': `
                          + (missing.length ? `${missing.length} of ${sc.instances.length} instances have no mesh of that name (${missing.slice(0, 3).join(", ")}${missing.length > 3 ? ", ..." : ""})` : "")
                          + (missing.length && wrong.length ? "; " : "")
                          + (wrong.length ? `${wrong.length} meshes differ from the server's (${wrong.slice(0, 3).join(", ")})` : ""));
    const head = HEAD;
    const src = this.m.src, ld = LIGHT.dir, ll = Math.hypot(...ld);
    const shared = { u_view: this.view, u_proj: this.proj, u_mirrored: { value: false },  // three turns the winding of mirrored objects itself
                     u_light_dir: { value: new THREE.Vector3(ld[0] / ll, ld[1] / ll, ld[2] / ll) },
                     u_ambient: { value: LIGHT.ambient }, u_diffuse: { value: LIGHT.diffuse } };
    this.targets = pairs.map(({ object, geometry }, i) => {
      const mesh = sc.meshes[sc.instances[i].mesh];
      const material = new THREE.RawShaderMaterial({
        glslVersion: THREE.GLSL3, side: THREE.DoubleSide, vertexShader: head + src["gbuffer.vert"], fragmentShader: head + src["gbuffer.frag"],
        uniforms: { ...shared, u_model: { value: new THREE.Matrix4() }, u_normal_matrix: { value: new THREE.Matrix3() },
                    u_double_sided: { value: mesh.doubleSided }, u_albedo: { value: new THREE.Vector3(...mesh.color) }, u_instance: { value: i + 1 } },
      });
      const gmesh = new THREE.Mesh(geometry, material);
      gmesh.matrixAutoUpdate = false;
      gmesh.frustumCulled = false;
      this.gScene.add(gmesh);
      return { object, gmesh, material };
    });
  }

  // Meshes of the delivered scene (flat face normals, the scene's colours) for a scene that has none.
  buildMeshes() {
    const sc = this.serverScene, { triangleSoup } = this.m.scene;
    this.skinned = [];
    const visible = [], gbuffer = [];
    sc.meshes.forEach((mesh, k) => {
      const restSoup = triangleSoup(mesh.vertices, mesh.faces), rest = soupAttributes(restSoup, false);
      const posed = mesh.skin ? soupAttributes(restSoup.slice(), true) : rest;
      if (mesh.skin) this.skinned.push({ mesh, buffer: posed.buffer });
      const g = new THREE.BufferGeometry();
      g.setAttribute("position", posed.position);
      g.setAttribute("normal", posed.normal);
      visible.push(g);
      gbuffer.push(gbufferGeometry(posed, rest, null));
    });
    this.group = new THREE.Group();
    this.group.name = `psao:${sc.name}`;
    this.scene.add(this.group);
    const make = (inst, i) => {
      const mesh = sc.meshes[inst.mesh];
      const material = new THREE.MeshLambertMaterial({ color: new THREE.Color().setRGB(...mesh.color, THREE.LinearSRGBColorSpace),
                                                      side: mesh.doubleSided ? THREE.DoubleSide : THREE.FrontSide });
      const object = new THREE.Mesh(visible[inst.mesh], material);
      object.name = inst.name;
      object.frustumCulled = !mesh.skin;
      fromRowMajor(object.matrix, inst.transform);
      object.matrixAutoUpdate = false;
      this.group.add(object);
      return object;
    };
    make.gbuffer = gbuffer;
    return make;
  }

  // The server's transforms onto the meshes (options.follow, default on) and skinned meshes posed at the
  // server time of the last Update.
  sync() {
    const mir = this.mirror;
    if (!mir) return;
    if (this.options.follow !== false) {
      const m = new THREE.Matrix4(), inv = new THREE.Matrix4();
      this.targets.forEach(({ object }, i) => {
        fromRowMajor(m, mir.transforms.subarray(16 * i, 16 * i + 16));
        if (object.parent && object.parent !== this.scene && object.parent !== this.group) {
          object.parent.updateWorldMatrix(true, false);
          m.premultiply(inv.copy(object.parent.matrixWorld).invert());
        }
        object.matrixAutoUpdate = false;
        object.matrix.copy(m);
        object.matrixWorldNeedsUpdate = true;
      });
    }
    if (this.skinned && mir.serverTime !== this.skinTime) {
      const { posedVertices, triangleSoup } = this.m.scene;
      for (const s of this.skinned) {
        s.buffer.array.set(triangleSoup(posedVertices(s.mesh, mir.serverTime), s.mesh.faces));
        s.buffer.needsUpdate = true;
      }
      this.skinTime = mir.serverTime;
    }
  }

  // ------------------------------------------------------------------------------------ grid tables
  tableFor(name, rows, rowWords) {
    const C = this.m.C, W = this.tableWidth;
    const nTexels = Math.max(rows.length / rowWords, 1) * (rowWords / 4), height = Math.ceil(nTexels / W);
    if (height > this.renderer.capabilities.maxTextureSize)
      throw new PsaoError(`psao-three: grid ${name} table of ${rows.length / rowWords} rows exceeds this browser's texture limit`);
    let t = this.tables[name];
    if (!t || t.image.height !== height) {
      if (t) t.dispose();
      t = this.tables[name] = integerTexture(new Uint32Array(height * W * 4), W, height);
    }
    const data = t.image.data;
    data.set(rows);
    t.clearUpdateRanges();
    if (name === "buckets") data.fill(C.EMPTY, rows.length);
    if (name === "cells") for (let i = rows.length + C.KEY_WORD; i < data.length; i += C.CELL_WORDS) data[i] = C.EMPTY;
    t.needsUpdate = true;
  }

  // Only the rows a message changed (runs of consecutive rows as one range, split where a texture row ends):
  // three.js then writes just those with texSubImage2D.
  writeDirty(name, rows, dirtyLists, rowWords) {
    const t = this.tables[name], data = t.image.data, line = 4 * this.tableWidth;
    for (const ids of dirtyLists) {
      for (let i = 0; i < ids.length;) {
        let j = i + 1;
        while (j < ids.length && ids[j] === ids[j - 1] + 1) j++;
        const start = rowWords * ids[i], end = rowWords * (ids[j - 1] + 1);
        data.set(rows.subarray(start, end), start);
        for (let a = start; a < end; a = Math.min(end, (Math.floor(a / line) + 1) * line)) t.addUpdateRange(a, Math.min(end, (Math.floor(a / line) + 1) * line) - a);
        i = j;
      }
    }
    if (t.updateRanges.length) t.needsUpdate = true;
  }

  // The mirror's tables as textures: all of them after the snapshot or a resize, else the rows that changed.
  uploadGrid() {
    const C = this.m.C, mir = this.mirror;
    if (!mir || mir.version === this.gridVersion) return;
    if (this.gridVersion < 0 || mir.resized) {
      this.tableFor("instances", new Uint32Array(mir.instances.slice().buffer), C.INSTANCE_BYTES / 4);
      this.tableFor("buckets", mir.buckets, 2 * C.BUCKET_ENTRIES);
      this.tableFor("cells", mir.cells, C.CELL_WORDS);
    } else {
      this.writeDirty("buckets", mir.buckets, mir.dirtyBuckets, 2 * C.BUCKET_ENTRIES);
      this.writeDirty("cells", mir.cells, mir.dirtyCells, C.CELL_WORDS);
    }
    mir.dirtyBuckets = [];
    mir.dirtyCells = [];
    mir.resized = false;
    this.gridVersion = mir.version;
  }

  // ------------------------------------------------------------------------------------------ frame
  setSize(w, h) {
    if (this.size[0] === w && this.size[1] === h) return;
    this.size = [w, h];
    if (this.gTarget) { this.gTarget.dispose(); this.aoTarget.dispose(); }
    this.gTarget = floatTarget(w, h, 4);  // the page's four G-buffer outputs (local, local normal, normal+depth, colour)
    this.aoTarget = floatTarget(w, h);
  }

  // The G-buffer and the PSAO pass of the current frame into aoTarget (r: AO, background 1).
  renderAO() {
    const r = this.renderer, cam = this.camera;
    this.sync();
    this.uploadGrid();
    cam.updateMatrixWorld();
    this.view.value.copy(cam.matrixWorldInverse);
    this.proj.value.copy(cam.projectionMatrix);
    this.scene.updateMatrixWorld();
    for (const { object, gmesh, material } of this.targets) {
      gmesh.matrix.copy(object.matrixWorld);
      material.uniforms.u_model.value.copy(object.matrixWorld);
      material.uniforms.u_normal_matrix.value.getNormalMatrix(object.matrixWorld);
    }
    const before = { target: r.getRenderTarget(), color: r.getClearColor(new THREE.Color()), alpha: r.getClearAlpha(), autoClear: r.autoClear };
    r.setRenderTarget(this.gTarget);
    r.setClearColor(0x000000, 0);
    r.clear(true, true, true);
    r.autoClear = false;
    r.render(this.gScene, cam);
    const u = this.psaoQuad.material.uniforms;
    u.u_local.value = this.gTarget.textures[0];
    u.u_local_normal.value = this.gTarget.textures[1];
    u.u_psao_instances.value = this.tables.instances || null;
    u.u_psao_buckets.value = this.tables.buckets || null;
    u.u_psao_cells.value = this.tables.cells || null;
    r.setRenderTarget(this.aoTarget);
    if (this.tables.cells) this.psaoQuad.render(r);
    else { r.setClearColor(0xffffff, 1); r.clear(true, false, false); }
    r.setRenderTarget(before.target);
    r.setClearColor(before.color, before.alpha);
    r.autoClear = before.autoClear;
  }

  // Float32 RGBA pixels (bottom-up rows) of a G-buffer output (0 local, 1 local normal) or of the AO (null).
  read(index = null) {
    const [w, h] = this.size, out = new Float32Array(w * h * 4);
    this.renderer.readRenderTargetPixels(index === null ? this.aoTarget : this.gTarget, 0, 0, w, h, out, undefined, index || 0);
    return out;
  }

  // An EffectComposer pass: the lit colour of the pass before it times the AO (options.aoOnly: the AO alone).
  pass(options = {}) { return new PsaoPass(this, options); }
}

const COMPOSITE = {
  uniforms: { tDiffuse: { value: null }, tAO: { value: null }, aoOnly: { value: false } },
  vertexShader: "varying vec2 vUv;\nvoid main() { vUv = uv; gl_Position = projectionMatrix * modelViewMatrix * vec4(position, 1.0); }",
  fragmentShader: "uniform sampler2D tDiffuse;\nuniform sampler2D tAO;\nuniform bool aoOnly;\nvarying vec2 vUv;\n"
    + "void main() { vec4 c = texture2D(tDiffuse, vUv); float ao = texture2D(tAO, vUv).r;\n"
    + "  gl_FragColor = aoOnly ? vec4(vec3(ao), 1.0) : vec4(c.rgb * ao, c.a); }",
};

export class PsaoPass extends Pass {
  constructor(ao, { aoOnly = false } = {}) {
    super();
    this.ao = ao;
    this.quad = new FullScreenQuad(new THREE.ShaderMaterial({ ...COMPOSITE, uniforms: THREE.UniformsUtils.clone(COMPOSITE.uniforms), depthTest: false, depthWrite: false }));
    this.aoOnly = aoOnly;
  }
  setSize(w, h) { this.ao.setSize(w, h); }
  render(renderer, writeBuffer, readBuffer) {
    this.ao.renderAO();
    const u = this.quad.material.uniforms;
    u.tDiffuse.value = readBuffer.texture;
    u.tAO.value = this.ao.aoTarget.texture;
    u.aoOnly.value = this.aoOnly;
    renderer.setRenderTarget(this.renderToScreen ? null : writeBuffer);
    if (this.clear) renderer.clear();
    this.quad.render(renderer);
  }
  dispose() { this.quad.dispose(); }
}

// Connects to the PSAO server at `url` and resolves once its scene is matched to the application's meshes
// (or built: options.build) and the grid is on the way; rejects with one PsaoError line when the scene does
// not match, the server refuses or cannot be reached. options: build, match(inst, mesh, scene) -> Object3D,
// follow (the server's transforms onto the meshes, default true), token, codecs, cameraHz (default 30),
// digests (keep the mirror's digest after every Snapshot and Update), onStreaming, onUpdate, onError.
export async function connect(url, renderer, scene, camera, options = {}) {
  const urls = endpoints(url);
  const mods = await serverModules(urls.http);
  const ao = new PsaoThree(mods, renderer, scene, camera, options);
  return ao.open(urls);
}
