// PSAO wire protocol in the browser: message framing, the handshake messages, Snapshot/Update grid deltas
// (packed and plain layouts), SceneData, and a client session that mirrors src/psao/protocol/session.py's client
// end (states, chunk order, the zstd stream that lives for the whole connection). Every number comes from
// /psao_constants.js, which the server generates from src/psao/protocol/.
import * as C from "/psao_constants.js";
import { Decompress, decompress } from "/vendor/fzstd.js";

export class ProtocolError extends Error {}
export class RemoteError extends ProtocolError {
  constructor(code, text) {
    const name = Object.keys(C.ErrorCode).find((k) => C.ErrorCode[k] === code) || String(code);
    super(`${name}: ${text}`);
    this.code = code;
    this.codeName = name;
    this.text = text;
  }
}

const T = C.MessageType;
const enc = new TextEncoder();
const dec = new TextDecoder("utf-8", { fatal: true });

// Bounds-checked little-endian reader over a Uint8Array (psao.protocol.updates.Reader).
export class Reader {
  constructor(bytes, what) {
    this.b = bytes;
    this.dv = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
    this.pos = 0;
    this.what = what;
  }
  need(n) {
    if (n < 0 || this.pos + n > this.b.length)
      throw new ProtocolError(`${this.what}: truncated (needs ${n} bytes at offset ${this.pos}, has ${this.b.length})`);
  }
  take(n) { this.need(n); const v = this.b.subarray(this.pos, this.pos + n); this.pos += n; return v; }
  u8() { this.need(1); return this.b[this.pos++]; }
  u16() { this.need(2); const v = this.dv.getUint16(this.pos, true); this.pos += 2; return v; }
  u32() { this.need(4); const v = this.dv.getUint32(this.pos, true); this.pos += 4; return v; }
  f32() { this.need(4); const v = this.dv.getFloat32(this.pos, true); this.pos += 4; return v; }
  f64() { this.need(8); const v = this.dv.getFloat64(this.pos, true); this.pos += 8; return v; }
  u64() { this.need(8); const v = this.dv.getBigUint64(this.pos, true); this.pos += 8; return Number(v); }
  // Typed copies (aligned, little-endian hosts: every browser).
  u32s(n) { return new Uint32Array(this.take(4 * n).slice().buffer); }
  f32s(n) { return new Float32Array(this.take(4 * n).slice().buffer); }
  rest() { return this.take(this.b.length - this.pos); }
  done() {
    if (this.pos !== this.b.length) throw new ProtocolError(`${this.what}: ${this.b.length - this.pos} unexpected bytes after the end`);
  }
}

// version: the header's protocol version (an older one only to test how servers refuse such pages).
export function frame(type, body, version = C.PROTOCOL_VERSION) {
  const out = new Uint8Array(C.HEADER_SIZE + body.length);
  const dv = new DataView(out.buffer);
  out.set(enc.encode(C.MAGIC), 0);
  dv.setUint16(4, version, true);
  out[6] = type;
  out[7] = C.Codec.NONE;
  dv.setUint32(8, body.length, true);
  out.set(body, C.HEADER_SIZE);
  return out;
}

function tokenBytes(token) {
  const t = enc.encode(token || "");
  if (t.length > C.LIMITS.token_bytes) throw new ProtocolError(`token of ${t.length} bytes over the limit`);
  return t;
}

export function helloMessage(sceneHash, codecMask, token, version = C.PROTOCOL_VERSION) {
  const t = tokenBytes(token);
  const body = new Uint8Array(2 + 4 + 32 + 2 + t.length);
  const dv = new DataView(body.buffer);
  dv.setUint16(0, version, true);
  dv.setUint32(2, codecMask, true);
  body.set(sceneHash, 6);
  dv.setUint16(38, t.length, true);
  body.set(t, 40);
  return frame(T.HELLO, body, version);
}

export function sceneRequestMessage(cachedHash, token, version = C.PROTOCOL_VERSION) {
  const t = tokenBytes(token);
  const body = new Uint8Array(32 + 2 + t.length);
  body.set(cachedHash || new Uint8Array(32), 0);
  new DataView(body.buffer).setUint16(32, t.length, true);
  body.set(t, 34);
  return frame(T.SCENE_REQUEST, body, version);
}

// view, projection: row-major Float32Array(16) each (psao.protocol.messages.Camera).
export function cameraMessage(view, projection) {
  const body = new Uint8Array(128);
  body.set(new Uint8Array(Float32Array.from(view).buffer), 0);
  body.set(new Uint8Array(Float32Array.from(projection).buffer), 64);
  return frame(T.CAMERA, body);
}

export const byeMessage = () => frame(T.BYE, new Uint8Array(0));

// ------------------------------------------------------------------------------------ grid deltas

function varints(bytes, count, what) {
  const out = new Uint32Array(count);
  let k = 0, v = 0, shift = 0, len = 0;
  for (let i = 0; i < bytes.length; i++) {
    const b = bytes[i];
    if (k >= count) throw new ProtocolError(`${what}: varint section holds more than ${count} values`);
    v += (b & 0x7f) * 2 ** shift;
    shift += 7;
    if (++len > 5) throw new ProtocolError(`${what}: varint longer than 5 bytes`);
    if (b < 0x80) {
      if (v > 0xffffffff) throw new ProtocolError(`${what}: varint value beyond 32 bits`);
      out[k++] = v; v = 0; shift = 0; len = 0;
    }
  }
  if (k !== count || len) throw new ProtocolError(`${what}: varint section does not hold exactly ${count} values`);
  return out;
}

function gaps(bytes, count, what) {
  const d = varints(bytes, count, what);
  let prev = -1;
  for (let i = 0; i < count; i++) {
    prev = prev + d[i] + 1;
    if (prev > 0xffffffff) throw new ProtocolError(`${what}: index beyond 32 bits`);
    d[i] = prev;
  }
  return d;
}

// Byte planes (psao.protocol.updates.planes) -> values; `size` bytes per value. 2- and 4-byte values (all the
// packed layout has) are assembled a whole value at a time.
function unplanes(r, size, count) {
  const raw = r.take(size * count);
  const plane = (b) => raw.subarray(b * count, (b + 1) * count);
  if (size === 4) {
    const out = new Uint32Array(count), [p0, p1, p2, p3] = [0, 1, 2, 3].map(plane);
    for (let i = 0; i < count; i++) out[i] = (p0[i] | (p1[i] << 8) | (p2[i] << 16) | (p3[i] << 24)) >>> 0;
    return out.buffer;
  }
  if (size === 2) {
    const out = new Uint16Array(count), [p0, p1] = [0, 1].map(plane);
    for (let i = 0; i < count; i++) out[i] = p0[i] | (p1[i] << 8);
    return out.buffer;
  }
  const out = new Uint8Array(size * count);
  for (let b = 0; b < size; b++) {
    const p = plane(b);
    for (let i = 0; i < count; i++) out[i * size + b] = p[i];
  }
  return out.buffer;
}

function readCounts(r, n, most, what) {
  const counts = r.take(n).slice();
  for (const c of counts) if (c > most && c !== C.RAW) throw new ProtocolError(`${what}: entry count above ${most}`);
  return counts;
}

function decodePacked(r, d) {
  const { k, nb, nc } = d;
  const lt = r.u32(), lb = r.u32(), lc = r.u32();
  d.transformIds = gaps(r.take(lt), k, "transform ids");
  d.transforms = new Float32Array(unplanes(r, 4, 16 * k));
  d.bucketIds = gaps(r.take(lb), nb, "bucket ids");
  const bCount = readCounts(r, nb, C.BUCKET_ENTRIES, "bucket");
  let nEntries = 0, nRawB = 0;
  for (const c of bCount) c === C.RAW ? nRawB++ : (nEntries += c);
  const keys = new Uint32Array(unplanes(r, 4, nEntries));
  const slots = new Uint32Array(unplanes(r, 4, nEntries));
  const rawB = new Uint32Array(unplanes(r, 4, nRawB * 2 * C.BUCKET_ENTRIES));
  const W = 2 * C.BUCKET_ENTRIES;
  d.buckets = new Uint32Array(nb * W).fill(C.EMPTY);
  for (let i = 0, e = 0, q = 0; i < nb; i++) {
    if (bCount[i] === C.RAW) { d.buckets.set(rawB.subarray(q * W, (q + 1) * W), i * W); q++; continue; }
    for (let j = 0; j < bCount[i]; j++, e++) { d.buckets[i * W + 2 * j] = keys[e]; d.buckets[i * W + 2 * j + 1] = slots[e]; }
  }
  d.cellSlots = gaps(r.take(lc), nc, "cell slots");
  const P = C.POINTS_PER_CELL, CW = C.CELL_WORDS;
  const cCount = readCounts(r, nc, P, "cell");
  const keyWords = new Uint32Array(unplanes(r, 4, nc));
  let nPoints = 0, nRawC = 0;
  for (const c of cCount) c === C.RAW ? nRawC++ : (nPoints += c);
  const pos = new Uint16Array(unplanes(r, 2, nPoints));
  const normal = r.take(nPoints), ao = r.take(nPoints);
  const rawC = new Uint32Array(unplanes(r, 4, nRawC * P));
  d.cells = new Uint32Array(nc * CW);
  for (let i = 0, p = 0, q = 0; i < nc; i++) {
    d.cells[i * CW + C.KEY_WORD] = keyWords[i];
    if (cCount[i] === C.RAW) { d.cells.set(rawC.subarray(q * P, (q + 1) * P), i * CW); q++; continue; }
    for (let j = 0; j < cCount[i]; j++, p++) {
      if (pos[p] > 0x7fff) throw new ProtocolError("cell: position field above 15 bits");
      d.cells[i * CW + j] = (C.ALLOCATED_BIT | (pos[p] << 16) | (normal[p] << 8) | ao[p]) >>> 0;
    }
  }
}

function decodePlain(r, d) {
  const { k, nb, nc } = d;
  d.transformIds = r.u32s(k);
  d.transforms = r.f32s(16 * k);
  d.bucketIds = r.u32s(nb);
  d.buckets = r.u32s(nb * 2 * C.BUCKET_ENTRIES);
  d.cellSlots = r.u32s(nc);
  d.cells = r.u32s(nc * C.CELL_WORDS);
}

function sortedUnique(ids, what) {
  for (let i = 1; i < ids.length; i++) if (ids[i] <= ids[i - 1]) throw new ProtocolError(`${what} indices are not sorted and unique`);
}

// One grid delta from the payload, checked -> { layout, capacity, transformIds, transforms, bucketIds, buckets, cellSlots, cells }.
function decodeOne(r) {
  const layout = r.u8();
  const d = { layout, capacity: r.u32(), k: r.u32(), nb: r.u32(), nc: r.u32() };
  const L = C.LIMITS;
  if (d.capacity > L.max_cell_capacity || d.k > L.max_instances || d.nb > L.max_buckets_per_message || d.nc > L.max_cells_per_message)
    throw new ProtocolError("grid delta: a count is over its limit");
  if (layout === C.Layout.PACKED) decodePacked(r, d);
  else if (layout === C.Layout.PLAIN) decodePlain(r, d);
  else throw new ProtocolError(`unknown grid delta layout ${layout}`);
  checkDelta(d);
  return d;
}

function checkDelta(d) {
  sortedUnique(d.transformIds, "transform");
  sortedUnique(d.bucketIds, "bucket");
  sortedUnique(d.cellSlots, "cell");
  const L = C.LIMITS;
  if (d.k > L.max_instances || d.nb > L.max_buckets_per_message || d.nc > L.max_cells_per_message)
    throw new ProtocolError("grid delta: a count is over its limit");
  if (d.nc && d.cellSlots[d.nc - 1] >= d.capacity) throw new ProtocolError("cell slot outside the capacity");
  for (const v of d.transforms) if (!Number.isFinite(v)) throw new ProtocolError("instance transform with NaN or infinity");
}

// The rest of a Snapshot payload: one grid delta.
export function decodeDelta(r) {
  const d = decodeOne(r);
  r.done();
  return d;
}

// The rest of an Update payload: one or more grid deltas (parts) for disjoint indices, as their union
// (psao.protocol.updates.union_of_parts).
export function decodeDeltaParts(r) {
  const parts = [decodeOne(r)];
  while (r.pos < r.b.length) {
    const d = decodeOne(r);
    if (d.layout !== parts[0].layout) throw new ProtocolError("grid delta parts in different layouts");
    parts.push(d);
  }
  return unionOfParts(parts);
}

function unionOfParts(parts) {
  if (parts.length === 1) return parts[0];
  const capacity = parts[0].capacity;
  if (parts.some((p) => p.capacity !== capacity)) throw new ProtocolError("grid delta parts with different cell capacities");
  const u = { layout: parts[0].layout, capacity };
  const kinds = [["transformIds", "transforms", 16, Float32Array, "k"], ["bucketIds", "buckets", 2 * C.BUCKET_ENTRIES, Uint32Array, "nb"],
                 ["cellSlots", "cells", C.CELL_WORDS, Uint32Array, "nc"]];
  for (const [idsName, rowsName, w, Rows, count] of kinds) {
    const n = parts.reduce((a, p) => a + p[idsName].length, 0);
    const owner = [];
    for (const p of parts) for (let i = 0; i < p[idsName].length; i++) owner.push([p[idsName][i], p, i]);
    owner.sort((a, b) => a[0] - b[0]);
    const ids = new Uint32Array(n), rows = new Rows(n * w);
    owner.forEach(([id, p, i], j) => {
      if (j && id === ids[j - 1]) throw new ProtocolError(`grid delta parts overlap: ${idsName} ${id} in two parts`);
      ids[j] = id;
      rows.set(p[rowsName].subarray(i * w, (i + 1) * w), j * w);
    });
    u[idsName] = ids;
    u[rowsName] = rows;
    u[count] = n;
  }
  checkDelta(u);
  return u;
}

// ------------------------------------------------------------------------------------------ session

export const State = { AWAIT_SCENE: "await scene", AWAIT_WELCOME: "await welcome", SNAPSHOT: "snapshot",
                       STREAMING: "streaming", CLOSED: "closed" };
// The codecs this page decodes, by the command line's names (psao.protocol.codecs.Codec, lower case, '-').
export const PAGE_CODECS = ["zstd-stream", "zstd", "none"];

// "zstd,none" -> the Hello's codec mask; a name the page cannot decode is a ProtocolError.
export function codecMask(names) {
  let mask = 0;
  for (const name of names) {
    if (!PAGE_CODECS.includes(name)) throw new ProtocolError(`codec '${name}' is not one this page decodes (${PAGE_CODECS.join(", ")})`);
    mask |= 1 << C.Codec[name.toUpperCase().replace("-", "_")];
  }
  return mask;
}

const ZSTD_FRAME_MAGIC = [0x28, 0xb5, 0x2f, 0xfd];
const startsFrame = (b) => b.length >= 4 && ZSTD_FRAME_MAGIC.every((x, i) => b[i] === x);

// Client end of one connection (a reconnect starts a new one); receive(bytes) -> event object.
// codecs: names to offer (PAGE_CODECS order); version: the protocol version it speaks (tests only).
export class ClientSession {
  constructor(token, cachedHash, { codecs = PAGE_CODECS, version = C.PROTOCOL_VERSION } = {}) {
    this.token = token;
    this.offered = codecMask(codecs);
    this.version = version;
    this.cached = cachedHash || new Uint8Array(32);
    this.state = State.AWAIT_SCENE;
    this.sceneParts = [];
    this.stream = null;
    this.streamOut = [];
    this.nextChunk = 0;
    this.payloadBytes = 0;
    this.decodeMs = 0;  // decompression + parsing of the last Snapshot/Update
    this.decompressMs = 0;  // of which decompression
  }
  sceneRequest() { return sceneRequestMessage(this.cached, this.token, this.version); }
  hello() { return helloMessage(this.sceneHash, this.offered, this.token, this.version); }

  payload(codec, body) {
    const cap = C.LIMITS.server_payload_bytes;
    if (codec === C.Codec.NONE) return body;
    if (codec === C.Codec.ZSTD) {
      const out = decompress(body);
      if (out.length > cap) throw new ProtocolError("zstd payload over the limit");
      return out;
    }
    if (codec === C.Codec.ZSTD_STREAM) {
      if (!this.stream) throw new ProtocolError("zstd-stream payload on a connection that did not negotiate it");
      // A payload that begins a zstd frame starts the stream anew (the server switched encoders).
      if (this.streamMessages++ > 0 && startsFrame(body)) this.stream = new Decompress((chunk) => this.streamOut.push(chunk));
      this.streamOut = [];
      this.stream.push(body);
      let n = 0;
      for (const c of this.streamOut) n += c.length;
      if (n > cap) throw new ProtocolError("zstd stream payload over the limit");
      if (this.streamOut.length === 1) return this.streamOut[0];
      const out = new Uint8Array(n);
      let o = 0;
      for (const c of this.streamOut) { out.set(c, o); o += c.length; }
      return out;
    }
    throw new ProtocolError(`codec ${codec} is not offered by this client`);
  }

  receive(data) {
    const t0 = performance.now();
    const b = new Uint8Array(data);
    if (b.length > C.LIMITS.server_message_bytes) throw new ProtocolError("message over the size limit");
    const r = new Reader(b, "header");
    const magic = String.fromCharCode(...r.take(4));
    const version = r.u16(), type = r.u8(), codec = r.u8(), length = r.u32();
    if (magic !== C.MAGIC) throw new ProtocolError(`bad magic ${magic}`);
    if (version !== C.PROTOCOL_VERSION)
      throw new RemoteError(C.ErrorCode.BAD_HEADER, `the server speaks protocol version ${version}, this page ${C.PROTOCOL_VERSION}`);
    if (length !== b.length - C.HEADER_SIZE) throw new ProtocolError(`header says ${length} payload bytes, message carries ${b.length - C.HEADER_SIZE}`);
    const tz = performance.now();
    const payload = this.payload(codec, b.subarray(C.HEADER_SIZE));
    this.decompressMs = performance.now() - tz;
    const p = new Reader(payload, "payload");
    if (type === T.ERROR) {
      const code = p.u16(), n = p.u16();
      this.state = State.CLOSED;
      throw new RemoteError(code, dec.decode(p.take(n)));
    }
    if (type === T.BYE) { this.state = State.CLOSED; return { kind: "bye" }; }
    if (type === T.STATUS && this.state !== State.CLOSED) return this.status(codec, p);
    if (this.state === State.AWAIT_SCENE && type === T.SCENE_DATA) return this.sceneChunk(p);
    if (this.state === State.AWAIT_WELCOME && type === T.WELCOME) return this.welcome(p);
    if (this.state === State.SNAPSHOT && type === T.SNAPSHOT) {
      this.payloadBytes += payload.length;
      const chunk = p.u32(), n = p.u32();
      if (chunk !== this.nextChunk || n === 0 || (this.nChunks && n !== this.nChunks))
        throw new ProtocolError(`snapshot chunk ${chunk} of ${n}, expected ${this.nextChunk}`);
      this.nChunks = n;
      this.nextChunk++;
      const delta = decodeDelta(p);
      const complete = this.nextChunk === n;
      if (complete) this.state = State.STREAMING;
      this.decodeMs = performance.now() - t0;
      return { kind: "snapshot", chunk, n, delta, complete };
    }
    if (this.state === State.STREAMING && type === T.UPDATE) {
      this.payloadBytes += payload.length;
      const tick = p.u64(), serverTime = p.f64();
      const delta = decodeDeltaParts(p);
      this.decodeMs = performance.now() - t0;
      return { kind: "update", tick, serverTime, delta };
    }
    throw new ProtocolError(`unexpected message type ${type} in state ${this.state}`);
  }

  // A starting server's Status (StatusPhase, progress 0..1, a line of text), in any state; the state stays.
  status(codec, p) {
    if (codec !== C.Codec.NONE) throw new ProtocolError(`Status with codec ${codec}: it is sent uncompressed`);
    const phase = p.u8(), progress = p.f32(), n = p.u16();
    const name = Object.keys(C.StatusPhase).find((k) => C.StatusPhase[k] === phase);
    if (!name) throw new ProtocolError(`Status: unknown phase ${phase}`);
    if (!(progress >= 0 && progress <= 1)) throw new ProtocolError(`Status: progress ${progress} is not within 0..1`);
    if (n > C.LIMITS.error_text_bytes) throw new ProtocolError("Status: text over the limit");
    const text = dec.decode(p.take(n));
    p.done();
    return { kind: "status", phase: name, progress, text };
  }

  sceneChunk(p) {
    const hash = p.take(32).slice(), chunk = p.u32(), n = p.u32(), total = p.u32();
    if (total > C.LIMITS.scene_bytes) throw new ProtocolError(`scene of ${total} bytes over the limit`);
    if (n === 0) {
      if (!equalBytes(hash, this.cached)) throw new ProtocolError("'cached scene is current' for a scene this page does not hold");
      return this.sceneDone(hash, null, 0);
    }
    if (chunk !== this.sceneParts.length || chunk >= n) throw new ProtocolError(`scene chunk ${chunk} of ${n} out of order`);
    this.sceneParts.push(p.rest().slice());
    let got = 0;
    for (const part of this.sceneParts) got += part.length;
    if (got > total) throw new ProtocolError("scene chunks hold more bytes than announced");
    if (chunk < n - 1) return { kind: "scene-progress", got, total };
    if (got !== total) throw new ProtocolError("scene chunks hold fewer bytes than announced");
    const blob = new Uint8Array(total);
    let o = 0;
    for (const part of this.sceneParts) { blob.set(part, o); o += part.length; }
    return this.sceneDone(hash, blob, total);
  }

  sceneDone(hash, blob, total) {
    this.sceneHash = hash;
    this.sceneParts = [];
    this.state = State.AWAIT_WELCOME;
    return { kind: "scene", hash, blob, total };
  }

  welcome(p) {
    const hash = p.take(32).slice();
    const w = { connectionId: p.u32(), codec: p.u8(), layout: p.u8() };
    p.u16();
    w.tickHz = p.f32();
    const nInst = p.u32();
    w.nBuckets = p.u32();
    w.capacity = p.u32();
    const L = C.LIMITS;
    if (nInst > L.max_instances || w.nBuckets > L.max_buckets || w.capacity > L.max_cell_capacity)
      throw new ProtocolError("Welcome: a table size over its limit");
    w.instances = p.take(nInst * C.INSTANCE_BYTES).slice();
    w.nInstances = nInst;
    p.done();
    if (!equalBytes(hash, this.sceneHash)) throw new RemoteError(C.ErrorCode.SCENE_MISMATCH, "Welcome names another scene");
    if (!(this.offered & (1 << w.codec))) throw new ProtocolError(`server chose codec ${w.codec}, not offered`);
    if (w.codec === C.Codec.ZSTD_STREAM) {
      this.stream = new Decompress((chunk) => this.streamOut.push(chunk));
      this.streamMessages = 0;
    }
    this.state = State.SNAPSHOT;
    return { kind: "welcome", welcome: w };
  }
}

export function equalBytes(a, b) {
  if (!a || !b || a.length !== b.length) return false;
  for (let i = 0; i < a.length; i++) if (a[i] !== b[i]) return false;
  return true;
}

// ------------------------------------------------------------------------------------------- mirror

// table[ids[i]] = rows[i] for rows of `width` values; ids sorted, so each run of consecutive ids (a
// snapshot chunk is mostly one) is one copy.
function writeRows(table, rows, ids, width) {
  for (let i = 0; i < ids.length;) {
    let j = i + 1;
    while (j < ids.length && ids[j] === ids[j - 1] + 1) j++;
    table.set(rows.subarray(width * i, width * j), width * ids[i]);
    i = j;
  }
}

// The page's copy of the server's grid, shaped like psao.client.mirror.Mirror; applying a delta is
// assignment of whole rows, so after every message it equals the server for everything sent.
export class Mirror {
  constructor(w) {
    this.nInstances = w.nInstances;
    this.instances = w.instances;  // INSTANCE_DTYPE records, raw bytes
    const W = 2 * C.BUCKET_ENTRIES;
    this.buckets = new Uint32Array(w.nBuckets * W).fill(C.EMPTY);
    this.cells = Mirror.freeCells(w.capacity);
    this.transforms = new Float32Array(16 * w.nInstances);
    for (let i = 0; i < w.nInstances; i++) for (let j = 0; j < 4; j++) this.transforms[16 * i + 5 * j] = 1;
    this.tick = -1;
    this.serverTime = null;
    this.version = 0;
    this.dirtyBuckets = [];
    this.dirtyCells = [];
    this.resized = true;
  }
  static freeCells(n) {
    const cells = new Uint32Array(n * C.CELL_WORDS);
    for (let i = 0; i < n; i++) cells[i * C.CELL_WORDS + C.KEY_WORD] = C.EMPTY;
    return cells;
  }
  get capacity() { return this.cells.length / C.CELL_WORDS; }
  apply(d) {
    const W = 2 * C.BUCKET_ENTRIES, CW = C.CELL_WORDS;
    if (d.k && d.transformIds[d.k - 1] >= this.nInstances) throw new ProtocolError("transform of a missing instance");
    if (d.nb && d.bucketIds[d.nb - 1] >= this.buckets.length / W) throw new ProtocolError("bucket outside the table");
    if (d.capacity !== this.capacity) {
      const cells = Mirror.freeCells(d.capacity);
      cells.set(this.cells.subarray(0, Math.min(cells.length, this.cells.length)));
      this.cells = cells;
      this.resized = true;
    }
    writeRows(this.transforms, d.transforms, d.transformIds, 16);
    writeRows(this.buckets, d.buckets, d.bucketIds, W);
    writeRows(this.cells, d.cells, d.cellSlots, CW);
    if (d.nb) this.dirtyBuckets.push(d.bucketIds);
    if (d.nc) this.dirtyCells.push(d.cellSlots);
    this.version++;
  }
  allocatedPoints() {
    let n = 0;
    const c = this.cells, CW = C.CELL_WORDS;
    for (let i = 0; i < c.length; i += CW) {
      if (c[i + C.KEY_WORD] === C.EMPTY) continue;
      for (let j = 0; j < C.POINTS_PER_CELL && c[i + j] & C.ALLOCATED_BIT; j++) n++;
    }
    return n;
  }
}
