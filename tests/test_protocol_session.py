"""Sans-I/O sessions of both ends talking to each other in memory, and the mirror they feed."""
from __future__ import annotations

import numpy as np
import pytest
import zstandard

from psao.protocol import messages as m
from psao.protocol.codecs import Codec, codec_mask
from psao.protocol.errors import CodecError, EditError, HeaderError, PayloadError
from psao.protocol.gridformat import EMPTY, FREE_CELL, INSTANCE_DTYPE
from psao.protocol.session import (
    ByeReceived,
    CameraReceived,
    ClientConfig,
    ClientSession,
    HelloAccepted,
    RefusedError,
    RemoteError,
    SceneEditReceived,
    ServerConfig,
    ServerSession,
    SharedStream,
    SnapshotReceived,
    StatusReceived,
    UnexpectedMessage,
    UpdateReceived,
    Welcomed,
    error_reply,
)
from psao.protocol.updates import GridDelta, Layout
from psao.client.errors import MirrorError
from psao.client.mirror import Mirror

HASH = bytes(range(32))
OTHER = bytes(32)


class SyntheticGrid:
    """Arrays in the Grid's layout, edited at random: stands in for the server state in pure tests."""

    def __init__(self, rng, n_buckets=256, capacity=300, n_inst=3):
        self.rng = rng
        self.instances = np.zeros(n_inst, INSTANCE_DTYPE)
        self.instances["bucket_count"] = n_buckets // n_inst
        self.instances["bucket_offset"] = np.arange(n_inst) * (n_buckets // n_inst)
        self.buckets = np.full((n_buckets, 8, 2), EMPTY, np.uint32)
        self.cells = np.tile(FREE_CELL, (capacity, 1))
        self.transforms = rng.normal(size=(n_inst, 4, 4)).astype(np.float32)
        self.edit(200)

    def edit(self, n):
        """Rewrite n random buckets and cells (canonical and not), sometimes grow the pool."""
        rng = self.rng
        if rng.random() < 0.2:
            self.cells = np.concatenate([self.cells, np.tile(FREE_CELL, (len(self.cells), 1))])
        b = rng.integers(0, len(self.buckets), n)
        c = rng.integers(0, len(self.cells), n)
        used = rng.integers(0, 9, n)
        self.buckets[b] = EMPTY
        for i, k in zip(b, used):
            self.buckets[i, :k, 0] = rng.integers(0, 1 << 20, k)
            self.buckets[i, :k, 1] = rng.integers(0, len(self.cells), k)
        pts = rng.integers(0, 8, n)
        self.cells[c] = FREE_CELL
        for i, k in zip(c, pts):
            self.cells[i, :k] = 0x80000000 | rng.integers(0, 1 << 31, k)
            self.cells[i, 7] = rng.integers(0, 1 << 20) if k else EMPTY
        self.cells[c[0], 2] ^= 0x10  # a stray bit: non-canonical cells must still arrive exactly
        self.transforms[rng.integers(0, len(self.transforms))] += 1.0
        return np.unique(b).astype(np.uint32), np.unique(c).astype(np.uint32)

    def delta(self, b, c, tids):
        tids = np.asarray(tids, np.uint32)
        return GridDelta(len(self.cells), tids, self.transforms[tids], b, self.buckets[b], c, self.cells[c])


def handshake(codecs=frozenset(Codec), server_codec=Codec.ZSTD_STREAM, layout=Layout.PACKED, token="", client_token="",
              edit_token=""):
    server = ServerSession(ServerConfig(HASH, token=token, edit_token=edit_token, codec=server_codec, layout=layout))
    client = ClientSession(ClientConfig(HASH, token=client_token, codecs=frozenset(codecs)))
    event = server.receive(client.hello())
    assert isinstance(event, HelloAccepted)
    return server, client, event


def assert_mirror_equals(mirror: Mirror, g: SyntheticGrid):
    assert mirror.buckets.tobytes() == g.buckets.tobytes()
    assert mirror.cells.tobytes() == g.cells.tobytes()
    assert mirror.transforms.tobytes() == g.transforms.tobytes()
    assert mirror.instances.tobytes() == g.instances.tobytes()


@pytest.mark.parametrize("codec", list(Codec))
@pytest.mark.parametrize("layout", list(Layout))
def test_stream_keeps_mirror_exact(codec, layout):
    rng = np.random.default_rng(int(codec) * 10 + int(layout))
    g = SyntheticGrid(rng)
    server, client, event = handshake(codecs={codec}, server_codec=codec, layout=layout)
    assert event.codec == codec
    welcomed = client.receive(server.welcome(7, 60.0, len(g.buckets), len(g.cells), g.instances))
    assert isinstance(welcomed, Welcomed) and welcomed.welcome.connection_id == 7
    mirror = Mirror.from_welcome(welcomed.welcome)
    # Snapshot in 3 chunks, the first with every transform.
    b_all = np.flatnonzero(np.any(g.buckets != EMPTY, axis=(1, 2))).astype(np.uint32)
    c_all = np.flatnonzero(np.any(g.cells != FREE_CELL, axis=1)).astype(np.uint32)
    for i, (b, c) in enumerate(zip(np.array_split(b_all, 3), np.array_split(c_all, 3))):
        ev = client.receive(server.snapshot(i, 3, g.delta(b, c, np.arange(3) if i == 0 else [])))
        assert isinstance(ev, SnapshotReceived) and ev.complete == (i == 2)
        mirror.apply(ev.snapshot.delta)
    assert_mirror_equals(mirror, g)
    for tick in range(40):
        b, c = g.edit(int(rng.integers(1, 40)))
        changed = np.flatnonzero(np.any(mirror.transforms != g.transforms, axis=(1, 2)))
        ev = client.receive(server.update(tick, tick / 60, g.delta(b, c, changed)))
        assert isinstance(ev, UpdateReceived) and ev.update.tick == tick
        mirror.apply(ev.update.delta)
        assert_mirror_equals(mirror, g)
    assert isinstance(server.receive(client.bye()), ByeReceived)


def test_camera_and_scene_edit_reach_the_server():
    server, client, _ = handshake()
    view = np.arange(16, dtype=np.float32).reshape(4, 4)
    ev = server.receive(client.camera(view, np.eye(4)))
    assert isinstance(ev, CameraReceived) and np.array_equal(ev.camera.view, view)
    with pytest.raises(RefusedError, match="does not accept scene edits") as exc:
        server.receive(client.scene_edit(2, np.eye(4)))
    assert exc.value.code == m.ErrorCode.EDITS_NOT_ALLOWED
    server, client, event = handshake(edit_token="e", client_token="e")
    assert event.may_edit
    edit = np.diag([2.0, 2.0, 2.0, 1.0])
    ev = server.receive(client.scene_edit(2, edit))
    assert isinstance(ev, SceneEditReceived) and ev.edit.instance == 2
    with pytest.raises(EditError, match="axis scales"):
        server.receive(client.scene_edit(2, np.diag([3e38, 1.0, 1.0, 1.0])))


def test_edit_token_is_its_own():
    """The viewing token does not allow edits; the edit token also lets a client view."""
    server, client, event = handshake(token="view", client_token="view", edit_token="edit")
    assert not event.may_edit
    with pytest.raises(RefusedError, match="need the edit token"):
        server.receive(client.scene_edit(0, np.eye(4)))
    _, _, event = handshake(token="view", client_token="edit", edit_token="edit")
    assert event.may_edit


def test_an_update_encoded_after_bye_still_encodes():
    """The sender may be encoding on another thread when the reader hears Bye."""
    g = SyntheticGrid(np.random.default_rng(5))
    server, client, _ = handshake()
    assert isinstance(server.receive(client.bye()), ByeReceived)
    data = server.update(1, 0.0, g.delta(np.zeros(0, np.uint32), np.zeros(0, np.uint32), []))
    assert m.Header.parse(data, 1 << 20).type == m.MessageType.UPDATE


def test_an_update_of_parts_queued_before_bye_still_encodes():
    """Parts queued for a client before its Bye go out as an Update would (the peer ignores them); refusing
    them closed the connection with a protocol error instead of the Bye's clean close."""
    server, client, _ = handshake()
    assert server.takes_parts()
    assert isinstance(server.receive(client.bye()), ByeReceived)
    assert not server.takes_parts()  # no new parts are planned for it
    data = server.update_of_parts([zstandard.ZstdCompressor().compress(b"head")])
    assert m.Header.parse(data, 1 << 20).type == m.MessageType.UPDATE


def test_token_checked():
    with pytest.raises(RefusedError, match="missing token") as exc:
        handshake(token="secret")
    assert exc.value.code == m.ErrorCode.UNAUTHORIZED and exc.value.close_code == 1008
    with pytest.raises(RefusedError, match="wrong token"):
        handshake(token="secret", client_token="guess")
    handshake(token="secret", client_token="secret")


def test_scene_hash_checked_by_both_ends():
    server = ServerSession(ServerConfig(HASH))
    client = ClientSession(ClientConfig(OTHER))
    with pytest.raises(RefusedError, match="scene hash mismatch") as exc:
        server.receive(client.hello())
    assert exc.value.code == m.ErrorCode.SCENE_MISMATCH
    # A server that answers with another scene's Welcome is refused by the client too.
    client = ClientSession(ClientConfig(OTHER))
    welcome = m.encode(m.Welcome(HASH, 1, Codec.NONE, Layout.PACKED, 60.0, 0, 0, np.zeros(0, INSTANCE_DTYPE)))
    with pytest.raises(RefusedError, match="scene hash mismatch"):
        client.receive(welcome)


def test_codec_negotiation():
    assert handshake(codecs={Codec.ZSTD, Codec.NONE})[2].codec == Codec.ZSTD  # stream preferred, frames next
    assert handshake(codecs={Codec.NONE}, server_codec=Codec.LZ4)[2].codec == Codec.NONE
    with pytest.raises(CodecError, match="no common codec"):
        handshake(codecs={Codec.LZ4})


def test_messages_out_of_order_are_refused():
    server = ServerSession(ServerConfig(HASH))
    client = ClientSession(ClientConfig(HASH))
    with pytest.raises(UnexpectedMessage, match="expected Hello"):
        server.receive(client.camera(np.eye(4), np.eye(4)))
    server, client, _ = handshake()
    with pytest.raises(UnexpectedMessage):
        server.receive(client.hello())
    with pytest.raises(UnexpectedMessage):
        server.receive(m.encode(m.Update(1, 0.0, GridDelta(0))))
    client.receive(server.welcome(1, 60.0, 0, 0, np.zeros(0, INSTANCE_DTYPE)))
    with pytest.raises(UnexpectedMessage, match="UPDATE"):
        client.receive(server.update(1, 0.0, GridDelta(0)))


def test_snapshot_chunks_must_come_in_order():
    server, client, _ = handshake(codecs={Codec.NONE})
    client.receive(server.welcome(1, 60.0, 0, 0, np.zeros(0, INSTANCE_DTYPE)))
    client.receive(server.snapshot(0, 3, GridDelta(0)))
    with pytest.raises(UnexpectedMessage, match="chunk 2 of 3, expected 1"):
        client.receive(server.snapshot(2, 3, GridDelta(0)))


def test_stream_payload_without_negotiation_refused():
    server, client, _ = handshake(codecs={Codec.ZSTD_STREAM})
    welcome = server.welcome(1, 60.0, 0, 0, np.zeros(0, INSTANCE_DTYPE))
    with pytest.raises(CodecError, match="did not offer"):
        ClientSession(ClientConfig(HASH, codecs=frozenset({Codec.NONE}))).receive(welcome)
    plain_server, plain_client, _ = handshake(codecs={Codec.NONE})
    plain_client.receive(plain_server.welcome(1, 60.0, 0, 0, np.zeros(0, INSTANCE_DTYPE)))
    with pytest.raises(CodecError, match="did not negotiate"):
        plain_client.receive(server.snapshot(0, 1, GridDelta(0)))
    hello = m.frame(m.MessageType.HELLO, Codec.ZSTD_STREAM, b"")
    with pytest.raises(CodecError, match="clients may not send"):
        ServerSession(ServerConfig(HASH)).receive(hello)


def test_error_reply_and_remote_error():
    data, code = error_reply(HeaderError("bad magic"))
    assert code == 1002
    client = ClientSession(ClientConfig(HASH))
    with pytest.raises(RemoteError, match="BAD_HEADER: bad magic") as exc:
        client.receive(data)
    assert exc.value.code == m.ErrorCode.BAD_HEADER
    data, code = error_reply(PayloadError("Camera view has NaN"))
    assert m.Error.parse(data[12:]).code == m.ErrorCode.BAD_PAYLOAD and code == 1002


def test_hello_mask_and_unknown_version():
    hello = m.Hello(HASH, codec_mask([Codec.NONE]), version=2)
    with pytest.raises(HeaderError, match="version 2"):
        ServerSession(ServerConfig(HASH)).receive(m.encode(hello))


def test_mirror_grows_shrinks_and_checks_indices():
    inst = np.zeros(2, INSTANCE_DTYPE)
    inst["bucket_count"] = 4
    inst["bucket_offset"] = (0, 4)
    mirror = Mirror(inst, 8, 4)
    cells = np.tile(FREE_CELL, (1, 1))
    cells[0, :2] = (0x80000001, 0x80000002)
    cells[0, 7] = 9
    mirror.apply(GridDelta(16, cell_slots=[12], cells=cells))
    assert mirror.cells.shape == (16, 8) and mirror.cells[12].tolist() == cells[0].tolist()
    assert (mirror.cells[4:12] == FREE_CELL).all()
    mirror.apply(GridDelta(13))
    assert mirror.cells.shape == (13, 8) and mirror.allocated_cells() == 1
    with pytest.raises(MirrorError, match="bucket 8"):
        mirror.apply(GridDelta(13, bucket_ids=[8], buckets=np.full((1, 8, 2), EMPTY)))
    with pytest.raises(MirrorError, match="instance 2"):
        mirror.apply(GridDelta(13, transform_ids=[2], transforms=np.eye(4)[None]))
    with pytest.raises(MirrorError, match="refers to bucket"):
        Mirror(inst, 7, 4)


@pytest.mark.parametrize("codec", [Codec.ZSTD, Codec.LZ4, Codec.ZSTD_STREAM])
def test_corrupted_compressed_messages_raise_protocol_errors_only(codec):
    from psao.protocol.errors import ProtocolError
    from test_protocol_messages import _mutate

    rng = np.random.default_rng(int(codec))
    g = SyntheticGrid(rng, n_buckets=64, capacity=64)
    b, c = g.edit(20)
    server, _, _ = handshake(codecs={codec}, server_codec=codec)
    welcome = server.welcome(1, 60.0, len(g.buckets), len(g.cells), g.instances)
    valid = server.snapshot(0, 1, g.delta(b, c, [0]))
    outcomes = set()
    for _ in range(150):
        client = ClientSession(ClientConfig(HASH, codecs=frozenset({codec})))
        client.receive(welcome)
        data = _mutate(rng, valid)
        try:
            client.receive(data)
            outcomes.add("parsed")
        except ProtocolError as exc:
            outcomes.add(type(exc).__name__)
    assert "CodecError" in outcomes or "HeaderError" in outcomes


def test_fresh_mirror_reports_everything_dirty_once():
    inst = np.zeros(1, INSTANCE_DTYPE)
    inst["bucket_count"] = 4
    mirror = Mirror(inst, 4, 6)
    b, c = mirror.take_dirty()
    assert b.tolist() == [0, 1, 2, 3] and c.tolist() == list(range(6))
    cells = np.tile(FREE_CELL, (1, 1))
    mirror.apply(GridDelta(6, cell_slots=[2], cells=cells))
    b, c = mirror.take_dirty()
    assert b.tolist() == [] and c.tolist() == [2]


def test_claims_of_a_tiny_message_allocate_nothing_big():
    """A 68-byte Welcome claiming 2^24 buckets, and a Snapshot claiming 2^24 cells, meet a mirror that grows
    with the data received: it refuses before allocating, and a real grid still fits."""
    from psao.protocol.limits import DEFAULT_LIMITS as limits

    def rss_bytes():
        import os
        return int(open("/proc/self/statm").read().split()[1]) * os.sysconf("SC_PAGE_SIZE")

    big = np.zeros(1, INSTANCE_DTYPE)
    big["bucket_count"] = limits.max_buckets
    client = ClientSession(ClientConfig(HASH))
    server, _, _ = handshake()
    wire = server.welcome(1, 60.0, limits.max_buckets, limits.max_cell_capacity, big)
    welcome = client.receive(wire).welcome
    rss = rss_bytes()
    mirror = Mirror.from_welcome(welcome, limits)
    mirror.received(len(wire))
    assert mirror.buckets.nbytes == 0 and mirror.cells.nbytes == 0  # nothing yet
    one = np.tile(FREE_CELL, (1, 1))
    with pytest.raises(MirrorError, match="out of proportion"):  # a cell at the far end of the claim
        mirror.apply(GridDelta(limits.max_cell_capacity, cell_slots=[limits.max_cell_capacity - 1], cells=one))
    with pytest.raises(MirrorError, match="out of proportion"):  # the snapshot "complete" after 49 bytes
        mirror.complete()
    assert rss_bytes() - rss < 256 * 2**20
    # A real grid: its snapshot pays for its mirror.
    g = SyntheticGrid(np.random.default_rng(9), n_buckets=4096, capacity=8192)
    g.edit(3000)
    b = np.flatnonzero(np.any(g.buckets != EMPTY, axis=(1, 2))).astype(np.uint32)
    c = np.flatnonzero(np.any(g.cells != FREE_CELL, axis=1)).astype(np.uint32)
    server, client, _ = handshake()
    mirror = Mirror.from_welcome(client.receive(server.welcome(1, 60.0, 4096, 8192, g.instances)).welcome, limits)
    data = server.snapshot(0, 1, g.delta(b, c, np.arange(len(g.transforms))))
    mirror.received(len(data))
    mirror.apply(client.receive(data).snapshot.delta)
    mirror.complete()
    assert_mirror_equals(mirror, g)


def _joined(g: SyntheticGrid, k: int):
    """A zstd-stream connection with its snapshot (one chunk, its own stream): (server, client, mirror)."""
    server, client, _ = handshake(codecs={Codec.ZSTD_STREAM})
    mirror = Mirror.from_welcome(client.receive(server.welcome(k, 60.0, len(g.buckets), len(g.cells),
                                                               g.instances)).welcome)
    b_all = np.flatnonzero(np.any(g.buckets != EMPTY, axis=(1, 2))).astype(np.uint32)
    c_all = np.flatnonzero(np.any(g.cells != FREE_CELL, axis=1)).astype(np.uint32)
    mirror.apply(client.receive(server.snapshot(0, 1, g.delta(b_all, c_all, np.arange(3)))).snapshot.delta)
    return server, client, mirror


def test_shared_stream_serves_connections_joining_leaving_and_rejoining():
    """One SharedStream encodes each Update once; connections join it where it starts a frame, leave it for
    their own stream and come back, and every mirror stays exact through every switch."""
    rng = np.random.default_rng(5)
    g = SyntheticGrid(rng)
    shared = SharedStream(ServerConfig(HASH))
    ends = [_joined(g, k) for k in range(3)]
    on_shared = [False, False, False]
    schedule = {0: {0: True}, 6: {1: True}, 12: {2: True, 0: False}, 20: {1: False}, 27: {0: True, 1: True}}
    decoders_restarted = 0
    for tick in range(34):
        b, c = g.edit(int(rng.integers(1, 30)))
        joining = {k for k, on in schedule.get(tick, {}).items() if on and not on_shared[k]}
        for k, on in schedule.get(tick, {}).items():
            on_shared[k] = on
        if joining:
            shared.restart()
        data = shared.update(tick, tick / 60, g.delta(b, c, np.arange(3))) if any(on_shared) else None
        for k, (server, client, mirror) in enumerate(ends):
            if on_shared[k]:
                msg = server.shared(data)
                assert msg is data  # the same bytes for every member: encoded once
            else:
                msg = server.update(tick, tick / 60, g.delta(b, c, np.arange(3)))
            mirror.apply(client.receive(msg).update.delta)
            assert_mirror_equals(mirror, g)
    decoders_restarted = sum(client.decoder_restarts for _, client, _ in ends)
    assert decoders_restarted >= 6  # every switch between streams started a frame
    assert shared.messages == 34


def test_a_connection_joins_a_shared_stream_only_where_a_frame_starts():
    rng = np.random.default_rng(6)
    g = SyntheticGrid(rng)
    shared = SharedStream(ServerConfig(HASH))
    server, client, mirror = _joined(g, 1)
    b, c = g.edit(10)
    shared.update(0, 0.0, g.delta(b, c, np.arange(3)))  # the stream is under way
    b, c = g.edit(10)
    with pytest.raises(UnexpectedMessage, match="starts a frame"):
        server.shared(shared.update(1, 0.1, g.delta(b, c, np.arange(3))))
    frame_server, *_ = handshake(codecs={Codec.ZSTD}, server_codec=Codec.ZSTD)
    shared.restart()
    with pytest.raises(UnexpectedMessage, match="zstd-stream"):
        frame_server.shared(shared.update(2, 0.2, g.delta(b, c, np.arange(3))))


def test_own_streams_use_the_fast_level_and_the_shared_stream_the_papers():
    """A connection's own zstd stream is compressed per client (OWN_STREAM_ZSTD, a fast level); the shared
    one once for many (STREAM_ZSTD, the paper's level 15). Both decode on the same client stream."""
    from psao.protocol.codecs import OWN_STREAM_ZSTD, STREAM_ZSTD

    cfg = ServerConfig(HASH)
    assert cfg.own_stream_zstd == OWN_STREAM_ZSTD and cfg.stream_zstd == STREAM_ZSTD
    assert OWN_STREAM_ZSTD.level < STREAM_ZSTD.level == 15
    assert OWN_STREAM_ZSTD.window_log == STREAM_ZSTD.window_log  # same history a decoder keeps


def test_status_reaches_a_client_in_every_state_and_leaves_it_there():
    """A starting server's Status comes before Welcome, between snapshot chunks and among Updates; it is
    uncompressed, so a zstd-stream connection's stream goes on undisturbed."""
    st = m.Status(m.StatusPhase.BAKING, 0.4, "baking 40%")
    asking = ClientSession(ClientConfig(None))
    server = ServerSession(ServerConfig(HASH))
    server.receive(asking.scene_request())
    assert isinstance(asking.receive(server.status(st)), StatusReceived) and asking.state.name == "AWAIT_SCENE"
    server, client, _ = handshake(codecs={Codec.ZSTD_STREAM})
    event = client.receive(server.status(st))
    assert isinstance(event, StatusReceived) and event.status == m.Status(m.StatusPhase.BAKING, np.float32(0.4), "baking 40%")
    assert client.state.name == "AWAIT_WELCOME"
    client.receive(server.welcome(1, 60.0, 0, 0, np.zeros(0, INSTANCE_DTYPE)))
    client.receive(server.snapshot(0, 2, GridDelta(0)))
    assert isinstance(client.receive(server.status(m.Status(m.StatusPhase.COARSE, 0.1))), StatusReceived)
    assert isinstance(client.receive(server.snapshot(1, 2, GridDelta(0))), SnapshotReceived)
    for k in range(3):
        assert isinstance(client.receive(server.update(k, 0.0, GridDelta(0))), UpdateReceived)
        assert isinstance(client.receive(server.status(m.Status(m.StatusPhase.COARSE, 0.5 + k / 10))), StatusReceived)
    assert client.state.name == "STREAMING"
    client.receive(server.bye())
    with pytest.raises(UnexpectedMessage, match="STATUS in state CLOSED"):
        client.receive(server.status(st))


def test_a_compressed_status_is_refused():
    client = ClientSession(ClientConfig(HASH))
    body = m.Status(m.StatusPhase.READY, 1.0).serialize()
    with pytest.raises(CodecError, match="Status with codec ZSTD"):
        client.receive(m.frame(m.MessageType.STATUS, Codec.ZSTD, zstandard.ZstdCompressor().compress(body)))


def test_a_session_made_before_the_scene_is_known_checks_the_hello_on_rebind():
    """The token at once, the scene hash once the scene is loaded; nothing grid-related goes out before."""
    early = ServerConfig(None, token="tk")
    with pytest.raises(RefusedError, match="missing token"):
        ServerSession(early).receive(ClientSession(ClientConfig(HASH)).hello())
    server = ServerSession(early)
    client = ClientSession(ClientConfig(HASH, token="tk"))
    assert isinstance(server.receive(client.hello()), HelloAccepted) and server.scene_pending()
    server.status(m.Status(m.StatusPhase.LOADING, 0.0))  # Status may go out meanwhile, a Welcome may not
    with pytest.raises(UnexpectedMessage, match="scene was checked"):
        server.welcome(1, 60.0, 0, 0, np.zeros(0, INSTANCE_DTYPE))
    server.rebind(ServerConfig(HASH, token="tk"))
    assert not server.scene_pending()
    assert isinstance(client.receive(server.welcome(1, 60.0, 0, 0, np.zeros(0, INSTANCE_DTYPE))), Welcomed)
    other = ServerSession(ServerConfig(None))
    other.receive(ClientSession(ClientConfig(OTHER)).hello())
    with pytest.raises(RefusedError, match="scene hash mismatch") as exc:
        other.rebind(ServerConfig(HASH))
    assert exc.value.code == m.ErrorCode.SCENE_MISMATCH
    asking = ServerSession(ServerConfig(None))
    event = asking.receive(ClientSession(ClientConfig(None)).scene_request())
    with pytest.raises(UnexpectedMessage, match="before the scene is known"):
        asking.scene_data(event.request, b"blob")
    asking.rebind(ServerConfig(HASH))
    assert len(asking.scene_data(event.request, b"blob")) == 1
