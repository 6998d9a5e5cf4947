"""PSAO wire messages: a fixed header, then one payload per message type (DESIGN.md, "Protocol").

Every websocket message is one PSAO message, binary, all numbers little-endian:

    header (12 bytes)  magic b"PSAO" | version u16 | type u8 | codec u8 | payload length u32
    payload            `length` bytes, compressed with `codec` (Snapshot and Update only)

The header is checked entirely (magic, version, type, codec, length against the limit and against the
bytes actually received) before any payload byte is read. Each message type is a dataclass with
`serialize() -> bytes` (the uncompressed payload) and `parse(payload) -> message`; `parse` validates
every field (sizes before allocation, finite matrices, UTF-8 text) and raises protocol errors.

    Hello      client -> server  protocol version, scene hash, accepted codecs, optional token
    Welcome    server -> client  scene hash, connection id, chosen codec, tick rate, table sizes,
                                 instance table (INSTANCE_DTYPE records)
    Snapshot   server -> client  chunk i of n of the full grid (a GridDelta)
    Update     server -> client  tick, server time, a GridDelta
    Camera     client -> server  view and projection matrices, 4x4 float32, row-major
    SceneEdit  client -> server  instance id, 4x4 float32 local-to-world transform
    Error      both              code, text; the sender then closes the connection
    Bye        both              empty; a clean goodbye
    SceneRequest client -> server  before Hello: the scene hash the client has cached (or zeros), token
    SceneData  server -> client  scene hash, chunk i of n of the scene blob (one zstd frame of a
                                 psao.protocol.scenefile); n = 0: the client's cached scene is current
    Status     server -> client  what a starting server is doing (StatusPhase), a progress in 0..1 and a
                                 line of text; before Welcome and at any point after it (codec NONE)
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from psao.protocol.codecs import Codec
from psao.protocol.errors import ErrorCode, HeaderError, LimitError, PayloadError  # noqa: F401 (ErrorCode: the codes of Error)
from psao.protocol.gridformat import INSTANCE_DTYPE
from psao.protocol.limits import DEFAULT_LIMITS, HEADER_SIZE, Limits
from psao.protocol.updates import GridDelta, Layout, Reader, decode_delta, decode_delta_parts, encode_delta

MAGIC = b"PSAO"
PROTOCOL_VERSION = 1
HEADER = struct.Struct("<4sHBBI")
assert HEADER.size == HEADER_SIZE
SCENE_HASH_BYTES = 32  # sha256 digest of Scene.content_hash()


class MessageType(IntEnum):
    HELLO = 1
    WELCOME = 2
    SNAPSHOT = 3
    UPDATE = 4
    CAMERA = 5
    SCENE_EDIT = 6
    ERROR = 7
    BYE = 8
    SCENE_REQUEST = 9
    SCENE_DATA = 10
    STATUS = 11


class StatusPhase(IntEnum):
    """What a server is doing (Status.phase); `progress` is the fraction done of the step named."""

    LOADING = 1  # loading the scene (progress of the loading)
    BAKING = 2  # no grid yet (progress of the first bake: the coarse grid's, or the full grid's without one)
    COARSE = 3  # serving the coarse grid (progress of the full bake behind it)
    READY = 4  # serving the full grid


@dataclass(frozen=True)
class Header:
    version: int
    type: MessageType
    codec: Codec
    length: int

    def serialize(self) -> bytes:
        return HEADER.pack(MAGIC, self.version, int(self.type), int(self.codec), self.length)

    @classmethod
    def parse(cls, data: bytes, max_payload: int) -> "Header":
        """Check a message's header against the limits and the message's real size; read no payload."""
        if len(data) < HEADER_SIZE:
            raise HeaderError(f"truncated header: {len(data)} of {HEADER_SIZE} bytes")
        magic, version, mtype, codec, length = HEADER.unpack_from(data)
        if magic != MAGIC:
            raise HeaderError(f"bad magic {magic!r}, expected {MAGIC!r}")
        if version != PROTOCOL_VERSION:
            raise HeaderError(f"unsupported protocol version {version}, this end speaks {PROTOCOL_VERSION}")
        if mtype not in MessageType._value2member_map_:
            raise HeaderError(f"unknown message type {mtype}")
        if codec not in Codec._value2member_map_:
            raise HeaderError(f"unknown codec {codec}")
        if length > max_payload:
            raise LimitError(f"payload length {length} over the limit of {max_payload}")
        if length != len(data) - HEADER_SIZE:
            raise HeaderError(f"header says {length} payload bytes, message carries {len(data) - HEADER_SIZE}")
        return cls(version, MessageType(mtype), Codec(codec), length)


def frame(mtype: MessageType, codec: Codec, body: bytes) -> bytes:
    """Header + (already compressed) payload."""
    return Header(PROTOCOL_VERSION, mtype, codec, len(body)).serialize() + body


_MATRIX_ENTRIES = 4 * 4  # a 4x4 matrix, float32 on the wire
_MATRIX_BYTES = _MATRIX_ENTRIES * np.dtype("<f4").itemsize


def _matrix(r: Reader, what: str) -> np.ndarray:
    m = r.array("<f4", _MATRIX_ENTRIES).reshape(4, 4)
    if not np.all(np.isfinite(m)):
        raise PayloadError(f"{what} has NaN or infinite entries")
    return m


def _matrix_bytes(m: np.ndarray, what: str) -> bytes:
    m = np.asarray(m, dtype="<f4")
    if m.shape != (4, 4):
        raise PayloadError(f"{what} must be 4x4, got {m.shape}")
    return m.tobytes()


def _text(raw: memoryview, what: str) -> str:
    try:
        return bytes(raw).decode("utf-8")
    except UnicodeDecodeError:
        raise PayloadError(f"{what} is not valid UTF-8") from None


def _bounded_text(r: Reader, n: int, most: int, what: str) -> str:
    """The last field of a message: n bytes of UTF-8 text, at most `most`, and nothing after it."""
    if n > most:
        raise LimitError(f"{what} of {n} bytes over the limit of {most}")
    text = _text(r.take(n), what)
    r.done()
    return text


# ----------------------------------------------------------------------------------------------- messages

_HELLO = struct.Struct("<HI32sH")  # version, codec mask, scene hash, token length


@dataclass
class Hello:
    TYPE = MessageType.HELLO
    scene_hash: bytes
    codec_mask: int
    token: str = ""
    version: int = PROTOCOL_VERSION

    def serialize(self) -> bytes:
        tok = self.token.encode("utf-8")
        if len(self.scene_hash) != SCENE_HASH_BYTES:
            raise PayloadError(f"Hello: scene hash must be {SCENE_HASH_BYTES} bytes, got {len(self.scene_hash)}")
        return _HELLO.pack(self.version, self.codec_mask, self.scene_hash, len(tok)) + tok

    @classmethod
    def parse(cls, payload: bytes, limits: Limits = DEFAULT_LIMITS) -> "Hello":
        r = Reader(payload, "Hello")
        version, mask, scene_hash, n_tok = r.unpack(_HELLO)
        token = _bounded_text(r, n_tok, limits.token_bytes, "Hello: token")
        return cls(scene_hash=scene_hash, codec_mask=mask, token=token, version=version)


_WELCOME = struct.Struct("<32sIBBHfIII")  # hash, connection id, codec, layout, pad, tick Hz, instances, buckets, capacity


@dataclass
class Welcome:
    TYPE = MessageType.WELCOME
    scene_hash: bytes
    connection_id: int
    codec: Codec
    layout: Layout
    tick_hz: float
    n_buckets: int
    cell_capacity: int
    instances: np.ndarray  # INSTANCE_DTYPE (n,)

    def serialize(self) -> bytes:
        inst = np.ascontiguousarray(self.instances, dtype=INSTANCE_DTYPE)
        head = _WELCOME.pack(
            self.scene_hash, self.connection_id, int(self.codec), int(self.layout), 0, self.tick_hz,
            len(inst), self.n_buckets, self.cell_capacity,
        )
        return head + inst.tobytes()

    @classmethod
    def parse(cls, payload: bytes, limits: Limits = DEFAULT_LIMITS) -> "Welcome":
        r = Reader(payload, "Welcome")
        scene_hash, conn, codec, layout, _pad, tick_hz, n_inst, n_buckets, capacity = r.unpack(_WELCOME)
        for what, n, most in (
            ("instances", n_inst, limits.max_instances),
            ("buckets", n_buckets, limits.max_buckets),
            ("cell capacity", capacity, limits.max_cell_capacity),
        ):
            if n > most:
                raise LimitError(f"Welcome: {what} {n} over the limit of {most}")
        if codec not in Codec._value2member_map_ or layout not in Layout._value2member_map_:
            raise PayloadError(f"Welcome: unknown codec {codec} or layout {layout}")
        if not (np.isfinite(tick_hz) and tick_hz > 0):
            raise PayloadError(f"Welcome: tick rate {tick_hz} is not a positive number")
        instances = np.frombuffer(r.take(INSTANCE_DTYPE.itemsize * n_inst), dtype=INSTANCE_DTYPE).copy()
        r.done()
        return cls(scene_hash, conn, Codec(codec), Layout(layout), float(tick_hz), n_buckets, capacity, instances)


_SNAPSHOT = struct.Struct("<II")  # chunk index, chunk count


@dataclass
class Snapshot:
    TYPE = MessageType.SNAPSHOT
    chunk: int
    n_chunks: int
    delta: GridDelta
    layout: Layout = Layout.PACKED

    def serialize(self) -> bytes:
        return _SNAPSHOT.pack(self.chunk, self.n_chunks) + encode_delta(self.delta, self.layout)

    @classmethod
    def parse(cls, payload: bytes, limits: Limits = DEFAULT_LIMITS) -> "Snapshot":
        r = Reader(payload, "Snapshot")
        chunk, n_chunks = r.unpack(_SNAPSHOT)
        if not 0 < n_chunks <= limits.max_snapshot_chunks or chunk >= n_chunks:
            raise PayloadError(f"Snapshot: chunk {chunk} of {n_chunks} is out of range")
        delta, layout = decode_delta(r, limits)
        return cls(chunk, n_chunks, delta, layout)


_UPDATE = struct.Struct("<Qd")  # tick, server time (s)


@dataclass
class Update:
    """Tick, server time, then one or more grid deltas (parts) for disjoint indices, which together are
    the Update's delta (psao.protocol.updates.union_of_parts). `serialize` writes one part; a sender that
    has parts encoded apart appends more (`encode_delta` of each) or, compressed, more zstd frames."""

    TYPE = MessageType.UPDATE
    tick: int
    server_time: float
    delta: GridDelta
    layout: Layout = Layout.PACKED

    def serialize(self) -> bytes:
        return _UPDATE.pack(self.tick, self.server_time) + encode_delta(self.delta, self.layout)

    @classmethod
    def parse(cls, payload: bytes, limits: Limits = DEFAULT_LIMITS) -> "Update":
        r = Reader(payload, "Update")
        tick, server_time = r.unpack(_UPDATE)
        delta, layout = decode_delta_parts(r, limits)
        return cls(tick, server_time, delta, layout)


@dataclass
class Camera:
    TYPE = MessageType.CAMERA
    view: np.ndarray  # (4, 4) float32 world -> view
    projection: np.ndarray  # (4, 4) float32 view -> clip

    def serialize(self) -> bytes:
        return _matrix_bytes(self.view, "Camera view") + _matrix_bytes(self.projection, "Camera projection")

    @classmethod
    def parse(cls, payload: bytes, limits: Limits = DEFAULT_LIMITS) -> "Camera":
        # (a server parses one per client 30 times a second: both matrices in one read and one check)
        if len(payload) != 2 * _MATRIX_BYTES:  # view and projection
            r = Reader(payload, "Camera")
            view, proj = _matrix(r, "Camera view"), _matrix(r, "Camera projection")
            r.done()
            return cls(view, proj)
        both = np.frombuffer(payload, "<f4").astype(np.float32)
        if not np.isfinite(both).all():
            what = "view" if not np.isfinite(both[:_MATRIX_ENTRIES]).all() else "projection"
            raise PayloadError(f"Camera {what} has NaN or infinite entries")
        return cls(both[:_MATRIX_ENTRIES].reshape(4, 4), both[_MATRIX_ENTRIES:].reshape(4, 4))


_EDIT = struct.Struct("<I")


@dataclass
class SceneEdit:
    TYPE = MessageType.SCENE_EDIT
    instance: int
    transform: np.ndarray  # (4, 4) float32 local -> world

    def serialize(self) -> bytes:
        return _EDIT.pack(self.instance) + _matrix_bytes(self.transform, "SceneEdit transform")

    @classmethod
    def parse(cls, payload: bytes, limits: Limits = DEFAULT_LIMITS) -> "SceneEdit":
        r = Reader(payload, "SceneEdit")
        (inst,) = r.unpack(_EDIT)
        if inst >= limits.max_instances:
            raise PayloadError(f"SceneEdit: instance {inst} out of range")
        m = _matrix(r, "SceneEdit transform")
        r.done()
        return cls(inst, m)


_ERROR = struct.Struct("<HH")  # code, text length


@dataclass
class Error:
    TYPE = MessageType.ERROR
    code: int
    text: str

    def serialize(self) -> bytes:
        raw = self.text.encode("utf-8")[: DEFAULT_LIMITS.error_text_bytes]
        raw = raw.decode("utf-8", errors="ignore").encode("utf-8")  # never cut a character in half
        return _ERROR.pack(int(self.code), len(raw)) + raw

    @classmethod
    def parse(cls, payload: bytes, limits: Limits = DEFAULT_LIMITS) -> "Error":
        r = Reader(payload, "Error")
        code, n = r.unpack(_ERROR)
        return cls(code, _bounded_text(r, n, limits.error_text_bytes, "Error: text"))


@dataclass
class Bye:
    TYPE = MessageType.BYE

    def serialize(self) -> bytes:
        return b""

    @classmethod
    def parse(cls, payload: bytes, limits: Limits = DEFAULT_LIMITS) -> "Bye":
        Reader(payload, "Bye").done()
        return cls()


_SCENE_REQUEST = struct.Struct("<32sH")  # cached scene hash (zeros: none), token length
NO_SCENE = bytes(SCENE_HASH_BYTES)


@dataclass
class SceneRequest:
    """Asks for the server's scene before Hello; `cached` is the hash of a scene the client already holds."""

    TYPE = MessageType.SCENE_REQUEST
    cached: bytes = NO_SCENE
    token: str = ""

    def serialize(self) -> bytes:
        if len(self.cached) != SCENE_HASH_BYTES:
            raise PayloadError(f"SceneRequest: cached hash must be {SCENE_HASH_BYTES} bytes, got {len(self.cached)}")
        tok = self.token.encode("utf-8")
        return _SCENE_REQUEST.pack(self.cached, len(tok)) + tok

    @classmethod
    def parse(cls, payload: bytes, limits: Limits = DEFAULT_LIMITS) -> "SceneRequest":
        r = Reader(payload, "SceneRequest")
        cached, n_tok = r.unpack(_SCENE_REQUEST)
        return cls(cached, _bounded_text(r, n_tok, limits.token_bytes, "SceneRequest: token"))


_SCENE_DATA = struct.Struct("<32sIII")  # scene hash, chunk index, chunk count, blob bytes (all chunks)


@dataclass
class SceneData:
    """Chunk `chunk` of `n_chunks` of the scene blob of `total` bytes; n_chunks = 0 (and no data): the
    scene the client named in SceneRequest.cached is the one served."""

    TYPE = MessageType.SCENE_DATA
    scene_hash: bytes
    chunk: int
    n_chunks: int
    total: int
    data: bytes = b""

    def serialize(self) -> bytes:
        return _SCENE_DATA.pack(self.scene_hash, self.chunk, self.n_chunks, self.total) + bytes(self.data)

    @classmethod
    def parse(cls, payload: bytes, limits: Limits = DEFAULT_LIMITS) -> "SceneData":
        r = Reader(payload, "SceneData")
        scene_hash, chunk, n_chunks, total = r.unpack(_SCENE_DATA)
        if total > limits.scene_bytes:
            raise LimitError(f"SceneData: scene of {total} bytes over the limit of {limits.scene_bytes}")
        most = -(-limits.scene_bytes // limits.scene_chunk_bytes)
        if n_chunks > most or (n_chunks and chunk >= n_chunks) or (not n_chunks and (chunk or total)):
            raise PayloadError(f"SceneData: chunk {chunk} of {n_chunks} ({total} bytes) is out of range")
        data = r.rest()
        if len(data) > limits.scene_chunk_bytes:
            raise LimitError(f"SceneData: chunk of {len(data)} bytes over the limit of {limits.scene_chunk_bytes}")
        return cls(scene_hash, chunk, n_chunks, total, bytes(data))


_STATUS = struct.Struct("<BfH")  # phase, progress, text length


@dataclass
class Status:
    """A server's state: `phase` (StatusPhase), `progress` (0..1, finite) of that phase's work and a line of
    `text` for people (UTF-8, at most Limits.error_text_bytes; serialize cuts a longer one at a character)."""

    TYPE = MessageType.STATUS
    phase: StatusPhase
    progress: float
    text: str = ""

    def serialize(self) -> bytes:
        if self.phase not in StatusPhase._value2member_map_:
            raise PayloadError(f"Status: unknown phase {self.phase}")
        if not (math.isfinite(self.progress) and 0.0 <= self.progress <= 1.0):
            raise PayloadError(f"Status: progress {self.progress} is not within 0..1")
        raw = self.text.encode("utf-8")[: DEFAULT_LIMITS.error_text_bytes]
        raw = raw.decode("utf-8", errors="ignore").encode("utf-8")  # never cut a character in half
        return _STATUS.pack(int(self.phase), self.progress, len(raw)) + raw

    @classmethod
    def parse(cls, payload: bytes, limits: Limits = DEFAULT_LIMITS) -> "Status":
        r = Reader(payload, "Status")
        phase, progress, n = r.unpack(_STATUS)
        if phase not in StatusPhase._value2member_map_:
            raise PayloadError(f"Status: unknown phase {phase}")
        if not (math.isfinite(progress) and 0.0 <= progress <= 1.0):
            raise PayloadError(f"Status: progress {progress} is not within 0..1")
        return cls(StatusPhase(phase), float(progress), _bounded_text(r, n, limits.error_text_bytes, "Status: text"))


MESSAGE_CLASSES = {cls.TYPE: cls for cls in (Hello, Welcome, Snapshot, Update, Camera, SceneEdit, Error, Bye,
                                              SceneRequest, SceneData, Status)}
Message = Hello | Welcome | Snapshot | Update | Camera | SceneEdit | Error | Bye | SceneRequest | SceneData | Status


def encode(msg: Message) -> bytes:
    """A message with an uncompressed payload (codec NONE): header + serialize()."""
    return frame(msg.TYPE, Codec.NONE, msg.serialize())


def parse_payload(mtype: MessageType, payload: bytes, limits: Limits = DEFAULT_LIMITS) -> Message:
    return MESSAGE_CLASSES[mtype].parse(payload, limits)
