"""Sans-I/O protocol state machines for both ends (in the style of websockets' protocol.py).

A session turns one received websocket message (bytes) into one event, and messages to send into
bytes; it owns the connection's codec state (its own zstd stream) and checks that messages come in an
order the protocol allows. A `SharedStream` encodes an Update once for many server sessions: a session
takes its bytes (`ServerSession.shared`) and from then on is on that stream until it sends a message of
its own again, which starts its own stream anew (psao.protocol.codecs: a message that begins a frame).
`SharedParts` compresses parts of Updates once, each a zstd frame, so that connections whose Updates
differ share most of their bytes (`ServerSession.update_of_parts`: a ZSTD message of several frames).
It does no I/O, so it is tested without sockets; the asyncio server and client are thin loops around it.

Server:  AWAIT_HELLO --Hello ok--> OPEN --Bye / error--> CLOSED
         (in AWAIT_HELLO one SceneRequest is answered with SceneData; the state stays AWAIT_HELLO)
Client:  [AWAIT_SCENE --last SceneData-->] AWAIT_WELCOME --Welcome--> SNAPSHOT --last chunk--> STREAMING
         --Bye / Error--> CLOSED   (a client without the scene asks for it first: scene_request())

A starting server (`psao serve` answers while it loads and bakes) sends Status messages in any state, before
Welcome and after it; a client session returns them as StatusReceived and stays in its state. A server
session may be made before the scene is known (ServerConfig.scene_hash None): it checks the token of what
arrives at once and a Hello's scene hash when `rebind` gives it the scene's config.

A server that replaces its grid (`psao serve --progressive`: the coarse first grid by the full one) ends
every connection with the websocket close code GRID_REPLACED_CLOSE and no Error message: the client
reconnects at once (`reconnect_at_once`) and gets the new grid's Welcome and Snapshot on a new session.

Any malformed or unexpected input raises a ProtocolError subclass; `error_reply(exc)` gives the Error
message and websocket close code to answer it with.
"""
from __future__ import annotations

import hmac
from dataclasses import dataclass, field
from enum import Enum, auto

import numpy as np

from psao.protocol import messages as m
from psao.protocol.codecs import (
    PAPER_ZSTD,
    OWN_STREAM_ZSTD,
    STREAM_ZSTD,
    Codec,
    FrameCodec,
    StreamCompressor,
    StreamDecompressor,
    ZstdSettings,
    codec_mask,
    codecs_from_mask,
    decompress_frame,
    starts_frame,
)
from psao.protocol.errors import (CodecError, EditError, HeaderError, LimitError, PayloadError, ProtocolError, RefusedError,
                     RemoteError, UnexpectedMessage)
from psao.protocol.limits import DEFAULT_LIMITS, HEADER_SIZE, Limits
from psao.protocol.scenefile import SceneFile
from psao.protocol.updates import GridDelta, Layout, encode_cell_runs, encode_delta


def error_code_for(exc: ProtocolError) -> m.ErrorCode:
    if isinstance(exc, RefusedError):
        return exc.code
    for cls, code in (
        (EditError, m.ErrorCode.BAD_EDIT),
        (LimitError, m.ErrorCode.TOO_LARGE),
        (HeaderError, m.ErrorCode.BAD_HEADER),
        (CodecError, m.ErrorCode.BAD_CODEC),
        (UnexpectedMessage, m.ErrorCode.UNEXPECTED_MESSAGE),
        (PayloadError, m.ErrorCode.BAD_PAYLOAD),
    ):
        if isinstance(exc, cls):
            return code
    return m.ErrorCode.INTERNAL


def error_reply(exc: ProtocolError) -> tuple[bytes, int]:
    """Error message bytes and websocket close code that answer a protocol error."""
    return m.encode(m.Error(error_code_for(exc), str(exc))), exc.close_code


# Websocket close code (RFC 6455 private range 4000-4999) and reason of a connection the server ends
# because it replaced its grid: the client reconnects at once, whatever its policy for lost connections.
GRID_REPLACED_CLOSE = 4000
GRID_REPLACED_REASON = "grid replaced: reconnect"


def reconnect_at_once(close_code: int | None) -> bool:
    """True when a connection closed with `close_code` is to be reopened at once (the server replaced its grid)."""
    return close_code == GRID_REPLACED_CLOSE


def scene_hash_bytes(content_hash_hex: str) -> bytes:
    """Scene.content_hash() (sha256 hex) -> the 32 bytes carried by Hello and Welcome."""
    raw = bytes.fromhex(content_hash_hex)
    if len(raw) != m.SCENE_HASH_BYTES:
        raise PayloadError(f"scene hash must be {m.SCENE_HASH_BYTES} bytes, got {len(raw)}")
    return raw


def check_edit_transform(transform: np.ndarray, limits: Limits) -> None:
    """A SceneEdit transform must be affine, scale each axis within [1/max, max] (no flattening, no
    mirror-free blow-up to 3e38) and keep its origin within the allowed distance; else EditError."""
    t = np.asarray(transform, dtype=np.float64)
    if not np.array_equal(t[3], [0.0, 0.0, 0.0, 1.0]):
        raise EditError(f"SceneEdit: last row must be 0 0 0 1 (an affine transform), got {t[3].tolist()}")
    sv = np.linalg.svd(t[:3, :3], compute_uv=False)
    lo, hi = 1.0 / limits.edit_max_scale, limits.edit_max_scale
    if not (sv.min() >= lo and sv.max() <= hi):
        raise EditError(f"SceneEdit: axis scales {sv.min():.3g}..{sv.max():.3g} outside {lo:g}..{hi:g}")
    move = float(np.linalg.norm(t[:3, 3]))
    if move > limits.edit_max_translation:
        raise EditError(f"SceneEdit: translation {move:.3g} over the limit of {limits.edit_max_translation:g}")


@dataclass
class Traffic:
    messages_in: int = 0
    bytes_in: int = 0
    messages_out: int = 0
    bytes_out: int = 0

    def sent(self, data: bytes) -> bytes:
        self.messages_out += 1
        self.bytes_out += len(data)
        return data


def _split(data: bytes, max_payload: int) -> tuple[m.Header, memoryview]:
    header = m.Header.parse(data, max_payload)
    return header, memoryview(data)[HEADER_SIZE:]


# -------------------------------------------------------------------------------------------------- server


class ServerState(Enum):
    AWAIT_HELLO = auto()
    OPEN = auto()
    CLOSED = auto()


@dataclass(frozen=True)
class ServerConfig:
    scene_hash: bytes | None  # 32 bytes; None: the scene is not loaded yet (ServerSession.rebind)
    token: str = ""  # "" accepts anyone
    edit_token: str = ""  # "" refuses every SceneEdit; else a Hello with this token may edit (and view)
    codec: Codec = Codec.ZSTD_STREAM  # preferred payload codec for Snapshot and Update
    layout: Layout = Layout.PACKED
    zstd: ZstdSettings = PAPER_ZSTD  # per-message zstd
    limits: Limits = DEFAULT_LIMITS
    stream_zstd: ZstdSettings = STREAM_ZSTD  # the shared zstd stream (compressed once for many)
    own_stream_zstd: ZstdSettings = OWN_STREAM_ZSTD  # a connection's own zstd stream (compressed per client)

    def codec_preference(self) -> list[Codec]:
        prefs = [self.codec]
        if self.codec == Codec.ZSTD_STREAM:
            prefs.append(Codec.ZSTD)
        return prefs + [Codec.NONE]


@dataclass
class HelloAccepted:
    hello: m.Hello
    codec: Codec
    may_edit: bool = False


@dataclass
class SceneRequested:
    request: m.SceneRequest


@dataclass
class CameraReceived:
    camera: m.Camera


@dataclass
class SceneEditReceived:
    edit: m.SceneEdit


@dataclass
class ByeReceived:
    pass


class ServerSession:
    """Server end of one connection."""

    def __init__(self, config: ServerConfig):
        self.config = config
        self.state = ServerState.AWAIT_HELLO
        self.codec: Codec | None = None
        self.traffic = Traffic()
        self.may_edit = False
        self._compress = None  # FrameCodec, or StreamCompressor (None while on a shared stream)
        self.on_shared = False  # the last grid message came from a SharedStream
        self.accepted: frozenset = frozenset()  # the codecs the client's Hello offered
        self.scene_requests = 0
        self._hello_hash: bytes | None = None  # a Hello's scene hash, until the scene is known to check it

    # ------------------------------------------------------------------ inbound
    def receive(self, data: bytes):
        """One client message -> HelloAccepted | CameraReceived | SceneEditReceived | ByeReceived."""
        limits = self.config.limits
        self.traffic.messages_in += 1
        self.traffic.bytes_in += len(data)
        if self.state == ServerState.CLOSED:
            raise UnexpectedMessage("message after the connection was closed")
        if len(data) > limits.client_message_bytes:
            raise LimitError(f"message of {len(data)} bytes over the limit of {limits.client_message_bytes}")
        header, body = _split(data, limits.client_message_bytes)
        if header.codec == Codec.ZSTD_STREAM:
            raise CodecError("clients may not send zstd-stream payloads")
        payload = decompress_frame(header.codec, body, limits.client_payload_bytes, limits)
        if self.state == ServerState.AWAIT_HELLO:
            if header.type == m.MessageType.SCENE_REQUEST and not self.scene_requests:
                request = m.SceneRequest.parse(payload, limits)
                self._check_token(request.token)
                self.scene_requests += 1
                return SceneRequested(request)
            if header.type == m.MessageType.BYE and self.scene_requests:  # took the scene, leaves
                m.Bye.parse(payload, limits)
                self.state = ServerState.CLOSED
                return ByeReceived()
            if header.type != m.MessageType.HELLO:
                raise UnexpectedMessage(f"expected Hello, got {header.type.name}")
            return self._accept(m.Hello.parse(payload, limits))
        if header.type == m.MessageType.CAMERA:
            return CameraReceived(m.Camera.parse(payload, limits))
        if header.type == m.MessageType.SCENE_EDIT:
            edit = m.SceneEdit.parse(payload, limits)
            if not self.may_edit:
                why = ("this server does not accept scene edits" if not self.config.edit_token
                       else "scene edits need the edit token")
                raise RefusedError(why, m.ErrorCode.EDITS_NOT_ALLOWED)
            check_edit_transform(edit.transform, limits)
            return SceneEditReceived(edit)
        if header.type == m.MessageType.BYE:
            m.Bye.parse(payload, limits)
            self.state = ServerState.CLOSED
            return ByeReceived()
        raise UnexpectedMessage(f"a client may not send {header.type.name} here")

    def _check_token(self, token: str) -> bool:
        """Refuse a token that is neither the viewing token (when one is set) nor the edit token; True when
        it is the edit token (this connection may edit)."""
        cfg = self.config
        given = token.encode()
        may_edit = bool(cfg.edit_token) and hmac.compare_digest(given, cfg.edit_token.encode())
        if cfg.token and not may_edit and not hmac.compare_digest(given, cfg.token.encode()):
            reason = "missing token" if not token else "wrong token"
            raise RefusedError(reason, m.ErrorCode.UNAUTHORIZED)
        return may_edit

    def _accept(self, hello: m.Hello) -> HelloAccepted:
        cfg = self.config
        if hello.version != m.PROTOCOL_VERSION:
            raise HeaderError(f"Hello: unsupported protocol version {hello.version}")
        may_edit = self._check_token(hello.token)
        if cfg.scene_hash is None:
            self._hello_hash = hello.scene_hash  # checked by rebind, once the scene is loaded
        else:
            _check_scene(hello.scene_hash, cfg.scene_hash)
        accepted = codecs_from_mask(hello.codec_mask)
        codec = next((c for c in cfg.codec_preference() if c in accepted), None)
        if codec is None:
            raise CodecError(f"no common codec: client accepts {sorted(c.name for c in accepted)}")
        self.codec = codec
        self.accepted = accepted
        self._compress = (StreamCompressor(cfg.own_stream_zstd) if codec == Codec.ZSTD_STREAM
                          else FrameCodec(codec, cfg.zstd))
        self.state = ServerState.OPEN
        self.may_edit = may_edit
        return HelloAccepted(hello, codec, may_edit)

    def rebind(self, config: ServerConfig) -> None:
        """The server's scene is known now (`config` names its hash; else as the config the session was
        made with): a Hello accepted meanwhile is checked against it (RefusedError SCENE_MISMATCH)."""
        if config.scene_hash is None:
            raise ValueError("rebind needs the config of a loaded scene")
        self.config = config
        if self._hello_hash is not None:
            hello_hash, self._hello_hash = self._hello_hash, None
            _check_scene(hello_hash, config.scene_hash)

    def scene_pending(self) -> bool:
        """Whether a Hello was accepted before the scene was known and waits for rebind's check."""
        return self._hello_hash is not None

    # ----------------------------------------------------------------- outbound
    def status(self, status: m.Status) -> bytes:
        """A Status message (codec NONE: it leaves the connection's zstd stream as it was), in any state."""
        return self.traffic.sent(m.encode(status))

    def _grid_message(self, msg: m.Snapshot | m.Update) -> bytes:
        if self._hello_hash is not None:
            raise UnexpectedMessage(f"cannot send {msg.TYPE.name} before the Hello's scene is checked (rebind)")
        # Only the handshake gates sending: a Bye received meanwhile (on another thread) closes the inbound
        # side, and an Update already being encoded may still go out; the peer ignores it.
        if self.codec is None:
            raise UnexpectedMessage(f"cannot send {msg.TYPE.name} before the handshake")
        if self._compress is None:  # back from a shared stream: a fresh stream of our own starts a frame
            self._compress = StreamCompressor(self.config.own_stream_zstd)
        self.on_shared = False
        return self.traffic.sent(m.frame(msg.TYPE, self.codec, self._compress.compress(msg.serialize())))

    def shared(self, data: bytes) -> bytes:
        """An Update that a SharedStream encoded for many connections, sent on this one. A connection joins
        a shared stream only at a message that starts a frame; its own stream is dropped meanwhile."""
        if self.codec != Codec.ZSTD_STREAM:
            raise UnexpectedMessage("only a zstd-stream connection takes a shared stream")
        if not self.on_shared and not starts_frame(memoryview(data)[HEADER_SIZE:]):
            raise UnexpectedMessage("a connection joins a shared stream only where the stream starts a frame")
        self.on_shared = True
        self._compress = None
        return self.traffic.sent(data)

    def takes_parts(self) -> bool:
        """Whether this connection may be sent Updates made of shared parts (its client decodes ZSTD)."""
        return self.state == ServerState.OPEN and Codec.ZSTD in self.accepted

    def update_of_parts(self, frames: list[bytes]) -> bytes:
        """An Update made of parts compressed apart (SharedParts): a head frame, then any part frames, as
        one ZSTD message. It leaves the connection's own stream as it was (the client decodes a ZSTD
        message without touching its stream decoder)."""
        # Gated like update(): by the handshake, not by a Bye heard meanwhile (parts already queued may go out)
        if self.codec is None or Codec.ZSTD not in self.accepted:
            raise UnexpectedMessage("an Update of parts needs a handshake whose client decodes zstd")
        return self.traffic.sent(m.frame(m.MessageType.UPDATE, Codec.ZSTD, b"".join(frames)))

    def welcome(self, connection_id: int, tick_hz: float, n_buckets: int, cell_capacity: int,
                instances: np.ndarray) -> bytes:
        if self.codec is None or self._hello_hash is not None:
            raise UnexpectedMessage("Welcome needs an accepted Hello whose scene was checked")
        msg = m.Welcome(self.config.scene_hash, connection_id, self.codec, self.config.layout, tick_hz,
                        n_buckets, cell_capacity, instances)
        return self.traffic.sent(m.encode(msg))

    def snapshot(self, chunk: int, n_chunks: int, delta: GridDelta) -> bytes:
        return self._grid_message(m.Snapshot(chunk, n_chunks, delta, self.config.layout))

    def update(self, tick: int, server_time: float, delta: GridDelta) -> bytes:
        return self._grid_message(m.Update(tick, server_time, delta, self.config.layout))

    def scene_data(self, request: m.SceneRequest, blob: bytes) -> list[bytes]:
        """SceneData messages answering `request`: the scene blob in chunks, or one empty message when
        the client's cached scene is the one served."""
        h = self.config.scene_hash
        if h is None:
            raise UnexpectedMessage("SceneData before the scene is known (rebind)")
        if request.cached == h:
            return [self.traffic.sent(m.encode(m.SceneData(h, 0, 0, 0)))]
        size = self.config.limits.scene_chunk_bytes
        n = max(1, -(-len(blob) // size))
        return [self.traffic.sent(m.encode(m.SceneData(h, i, n, len(blob), blob[i * size:(i + 1) * size])))
                for i in range(n)]

    def bye(self) -> bytes:
        self.state = ServerState.CLOSED
        return self.traffic.sent(m.encode(m.Bye()))

    def fail(self, exc: ProtocolError) -> tuple[bytes, int]:
        """Error message and close code for `exc`; the session is closed afterwards."""
        self.state = ServerState.CLOSED
        data, code = error_reply(exc)
        return self.traffic.sent(data), code


def _check_scene(hello_hash: bytes, served: bytes) -> None:
    if hello_hash != served:
        raise RefusedError(f"scene hash mismatch: client has {hello_hash.hex()[:12]}, server serves {served.hex()[:12]}",
                           m.ErrorCode.SCENE_MISMATCH)


class SharedStream:
    """Updates encoded once for every connection on this stream (ZSTD_STREAM with the config's stream
    settings). A connection takes each message through ServerSession.shared, from a message that starts
    a frame (the first one, or the first after restart()) on, in order, without a gap."""

    def __init__(self, config: ServerConfig):
        self.config = config
        self._compress = StreamCompressor(config.stream_zstd)
        self.messages = 0
        self.frame_start = True  # the next message starts a frame

    def restart(self) -> None:
        """The next message starts a frame, so connections may join at it."""
        self._compress.restart()
        self.frame_start = True

    def update(self, tick: int, server_time: float, delta: GridDelta) -> bytes:
        msg = m.Update(tick, server_time, delta, self.config.layout)
        self.messages += 1
        self.frame_start = False
        return m.frame(msg.TYPE, Codec.ZSTD_STREAM, self._compress.compress(msg.serialize()))


class SharedParts:
    """Parts of Updates, each compressed once as a zstd frame of its own (per-message settings), that
    many connections' Updates share: a connection's Update is a head (tick, server time and a first
    delta) and any number of part frames, for disjoint indices (ServerSession.update_of_parts)."""

    def __init__(self, config: ServerConfig):
        self.config = config
        self._frames = FrameCodec(Codec.ZSTD, config.zstd)

    def head(self, tick: int, server_time: float, delta: GridDelta) -> bytes:
        return self._frames.compress(m.Update(tick, server_time, delta, self.config.layout).serialize())

    def part(self, delta: GridDelta) -> bytes:
        return self._frames.compress(encode_delta(delta, self.config.layout))

    def cell_runs(self, capacity: int, slots: np.ndarray, cells: np.ndarray, runs: list[tuple[int, int]]) -> list[bytes]:
        """part() of the cells-only delta of each run (a, b) of these rows, encoded together (encode_cell_runs)."""
        return [self._frames.compress(b) for b in encode_cell_runs(capacity, slots, cells, runs, self.config.layout)]


# -------------------------------------------------------------------------------------------------- client


class ClientState(Enum):
    AWAIT_SCENE = auto()
    AWAIT_WELCOME = auto()
    SNAPSHOT = auto()
    STREAMING = auto()
    CLOSED = auto()


@dataclass(frozen=True)
class ClientConfig:
    scene_hash: bytes | None  # None: take the server's scene (scene_request() before hello())
    token: str = ""
    codecs: frozenset = frozenset(Codec)
    limits: Limits = DEFAULT_LIMITS


@dataclass
class Welcomed:
    welcome: m.Welcome


@dataclass
class SnapshotReceived:
    snapshot: m.Snapshot
    complete: bool  # the last chunk: the mirror now equals the server


@dataclass
class UpdateReceived:
    update: m.Update


@dataclass
class StatusReceived:
    status: m.Status


@dataclass
class SceneReceived:
    scene_hash: bytes
    scene: SceneFile | None  # None: the cached scene named in the request is current
    blob_bytes: int  # compressed bytes received


@dataclass
class ClientSession:
    """Client end of one connection (a reconnect starts a new session)."""

    config: ClientConfig
    state: ClientState = ClientState.AWAIT_WELCOME
    welcome: m.Welcome | None = None
    traffic: Traffic = field(default_factory=Traffic)
    payload_bytes: int = 0  # decompressed Snapshot and Update payloads
    _stream: StreamDecompressor | None = None
    _next_chunk: int = 0
    _n_chunks: int = 0
    scene_hash: bytes | None = None  # the scene Hello names: the configured one, or the server's
    _cached: bytes = m.NO_SCENE
    _scene_parts: list = field(default_factory=list)

    @property
    def decoder_restarts(self) -> int:
        """Frames the zstd stream decoder started anew (a switch between streams starts one); 0 without it."""
        return self._stream.restarts if self._stream is not None else 0

    def __post_init__(self):
        self.scene_hash = self.config.scene_hash

    def scene_request(self, cached: bytes = m.NO_SCENE) -> bytes:
        """Ask for the server's scene (before hello()); `cached`: the hash of a scene already held."""
        if self.state != ClientState.AWAIT_WELCOME or self.traffic.messages_out:
            raise UnexpectedMessage("SceneRequest must be the first message of a connection")
        self.state = ClientState.AWAIT_SCENE
        self._cached = cached
        return self.traffic.sent(m.encode(m.SceneRequest(cached, self.config.token)))

    def hello(self) -> bytes:
        if self.scene_hash is None:
            raise UnexpectedMessage("Hello needs a scene hash: configure one or receive the server's scene first")
        msg = m.Hello(self.scene_hash, codec_mask(self.config.codecs), self.config.token)
        return self.traffic.sent(m.encode(msg))

    def camera(self, view: np.ndarray, projection: np.ndarray) -> bytes:
        return self.traffic.sent(m.encode(m.Camera(view, projection)))

    def scene_edit(self, instance: int, transform: np.ndarray) -> bytes:
        return self.traffic.sent(m.encode(m.SceneEdit(instance, transform)))

    def bye(self) -> bytes:
        self.state = ClientState.CLOSED
        return self.traffic.sent(m.encode(m.Bye()))

    def _payload(self, header: m.Header, body: memoryview) -> bytes:
        limits = self.config.limits
        if header.codec == Codec.ZSTD_STREAM:
            if self._stream is None:
                raise CodecError("zstd-stream payload on a connection that did not negotiate it")
            return self._stream.decompress(body, limits.server_payload_bytes)
        return decompress_frame(header.codec, body, limits.server_payload_bytes, limits)

    def receive(self, data: bytes):
        """One server message -> SceneReceived | None (a SceneData chunk before the last) | Welcomed |
        SnapshotReceived | UpdateReceived | StatusReceived (in any state but CLOSED; the state stays) |
        ByeReceived. An Error message raises RemoteError."""
        limits = self.config.limits
        self.traffic.messages_in += 1
        self.traffic.bytes_in += len(data)
        if len(data) > limits.server_message_bytes:
            raise LimitError(f"message of {len(data)} bytes over the limit of {limits.server_message_bytes}")
        header, body = _split(data, limits.server_message_bytes)
        t = header.type
        if t == m.MessageType.STATUS and header.codec != Codec.NONE:
            raise CodecError(f"Status with codec {header.codec.name}: it is sent uncompressed")
        payload = self._payload(header, body)
        if t == m.MessageType.ERROR:
            err = m.Error.parse(payload, limits)
            self.state = ClientState.CLOSED
            raise RemoteError(err.code, err.text)
        if t == m.MessageType.BYE:
            m.Bye.parse(payload, limits)
            self.state = ClientState.CLOSED
            return ByeReceived()
        if t == m.MessageType.STATUS and self.state != ClientState.CLOSED:
            return StatusReceived(m.Status.parse(payload, limits))
        if self.state == ClientState.AWAIT_SCENE and t == m.MessageType.SCENE_DATA:
            return self._scene_chunk(m.SceneData.parse(payload, limits))
        if self.state == ClientState.AWAIT_WELCOME and t == m.MessageType.WELCOME:
            return self._welcomed(m.Welcome.parse(payload, limits))
        if self.state == ClientState.SNAPSHOT and t == m.MessageType.SNAPSHOT:
            self.payload_bytes += len(payload)
            return self._chunk(m.Snapshot.parse(payload, limits))
        if self.state == ClientState.STREAMING and t == m.MessageType.UPDATE:
            self.payload_bytes += len(payload)
            return UpdateReceived(m.Update.parse(payload, limits))
        raise UnexpectedMessage(f"unexpected {t.name} in state {self.state.name}")

    def _scene_chunk(self, d: m.SceneData) -> SceneReceived | None:
        """Collect SceneData chunks; the last one gives the parsed scene (None until then)."""
        limits = self.config.limits
        if self.config.scene_hash is not None and d.scene_hash != self.config.scene_hash:
            raise RefusedError(f"scene hash mismatch: server serves {d.scene_hash.hex()[:12]}, client has "
                               f"{self.config.scene_hash.hex()[:12]}", m.ErrorCode.SCENE_MISMATCH)
        if d.n_chunks == 0:
            if d.scene_hash != self._cached:
                raise PayloadError("SceneData: 'cached scene is current' for a scene this client does not hold")
            return self._scene_done(SceneReceived(d.scene_hash, None, 0))
        first = self._scene_parts[0] if self._scene_parts else d
        if d.chunk != len(self._scene_parts) or (d.n_chunks, d.total, d.scene_hash) != (first.n_chunks, first.total,
                                                                                       first.scene_hash):
            raise UnexpectedMessage(f"SceneData chunk {d.chunk} of {d.n_chunks}, expected {len(self._scene_parts)} "
                                    f"of {first.n_chunks}")
        self._scene_parts.append(d)
        received = sum(len(p.data) for p in self._scene_parts)
        if received > d.total or (d.chunk == d.n_chunks - 1) != (received == d.total):
            raise PayloadError(f"SceneData: {received} bytes in chunks 0..{d.chunk} of a {d.total}-byte scene")
        if d.chunk < d.n_chunks - 1:
            return None
        blob = b"".join(p.data for p in self._scene_parts)
        raw = decompress_frame(Codec.ZSTD, blob, limits.scene_payload_bytes, limits)
        return self._scene_done(SceneReceived(d.scene_hash, SceneFile.parse(raw, limits), len(blob)))

    def _scene_done(self, event: SceneReceived) -> SceneReceived:
        self.scene_hash = event.scene_hash
        self._scene_parts = []
        self.state = ClientState.AWAIT_WELCOME
        return event

    def _welcomed(self, w: m.Welcome) -> Welcomed:
        if w.scene_hash != self.scene_hash:
            raise RefusedError(
                f"scene hash mismatch: server serves {w.scene_hash.hex()[:12]}, client has "
                f"{self.scene_hash.hex()[:12]}",
                m.ErrorCode.SCENE_MISMATCH,
            )
        if w.codec not in self.config.codecs:
            raise CodecError(f"server chose codec {w.codec.name}, which this client did not offer")
        if w.codec == Codec.ZSTD_STREAM:
            self._stream = StreamDecompressor(self.config.limits)
        self.welcome = w
        self.state = ClientState.SNAPSHOT
        return Welcomed(w)

    def _chunk(self, s: m.Snapshot) -> SnapshotReceived:
        if s.chunk != self._next_chunk or (self._n_chunks and s.n_chunks != self._n_chunks):
            raise UnexpectedMessage(
                f"snapshot chunk {s.chunk} of {s.n_chunks}, expected {self._next_chunk} of {self._n_chunks or '?'}"
            )
        self._n_chunks = s.n_chunks
        self._next_chunk += 1
        complete = self._next_chunk == s.n_chunks
        if complete:
            self.state = ClientState.STREAMING
        return SnapshotReceived(s, complete)
