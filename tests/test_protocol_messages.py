"""Wire format of every message, checked against hand-written bytes in both directions."""
from __future__ import annotations

import struct

import numpy as np
import pytest

from psao.protocol import messages as m
from psao.protocol.codecs import Codec
from psao.protocol.errors import HeaderError, LimitError, PayloadError
from psao.protocol.gridformat import EMPTY, INSTANCE_DTYPE
from psao.protocol.limits import Limits
from psao.protocol.updates import GridDelta, Layout, Reader, decode_delta, encode_delta, gaps_decode, gaps_encode
from psao.protocol.updates import varint_decode, varint_encode

HASH = bytes(range(32))
H = bytes.fromhex
ONE = H("0000803f")  # 1.0f little-endian
ZERO = H("00000000")
EYE = b"".join(ONE if i == j else ZERO for i in range(4) for j in range(4))


def header(mtype: int, length: int, codec: int = 0) -> bytes:
    return b"PSAO" + H("0100") + bytes([mtype, codec]) + length.to_bytes(4, "little")


def roundtrip(msg):
    data = m.encode(msg)
    hdr = m.Header.parse(data, 1 << 30)
    return data, m.parse_payload(hdr.type, data[12:])


def test_hello_bytes_both_ways():
    expected = header(1, 42) + H("0100") + H("0b000000") + HASH + H("0200") + b"tk"
    msg = m.Hello(HASH, 0b1011, "tk")
    data, back = roundtrip(msg)
    assert data == expected
    assert back == msg
    hand = m.Hello.parse(H("0100") + H("01000000") + HASH + H("0000"))
    assert (hand.version, hand.codec_mask, hand.token, hand.scene_hash) == (1, 1, "", HASH)


def test_error_bye_scene_edit_bytes():
    assert m.encode(m.Error(7, "bad")) == header(7, 7) + H("0700") + H("0300") + b"bad"
    assert m.Error.parse(H("0900") + H("0200") + "é".encode()) == m.Error(9, "é")
    assert m.encode(m.Bye()) == header(8, 0)
    edit = m.encode(m.SceneEdit(3, np.eye(4)))
    assert edit == header(6, 68) + H("03000000") + EYE
    back = m.SceneEdit.parse(H("05000000") + EYE)
    assert back.instance == 5 and np.array_equal(back.transform, np.eye(4))


def test_camera_bytes_and_nan_rejected():
    view = np.arange(16, dtype=np.float32).reshape(4, 4)
    data = m.encode(m.Camera(view, np.eye(4)))
    assert data == header(5, 128) + view.astype("<f4").tobytes() + EYE
    cam = m.Camera.parse(data[12:])
    assert np.array_equal(cam.view, view) and cam.view.dtype == np.float32
    bad = view.copy()
    bad[2, 1] = np.nan
    with pytest.raises(PayloadError, match="NaN"):
        m.Camera.parse(bad.tobytes() + EYE)
    with pytest.raises(PayloadError, match="NaN"):
        m.Camera.parse(EYE + struct.pack("<f", np.inf) + EYE[4:])
    with pytest.raises(PayloadError, match="truncated"):
        m.Camera.parse(EYE)
    with pytest.raises(PayloadError, match="unexpected bytes"):
        m.Camera.parse(EYE + EYE + b"x")


def test_welcome_bytes_both_ways():
    inst = np.zeros(1, INSTANCE_DTYPE)
    inst["origin"] = (1.0, 0.0, 0.0)
    inst["cell_size"] = 0.5
    inst["dims"] = (2, 3, 4)
    inst["bucket_count"] = 16
    msg = m.Welcome(HASH, 9, Codec.ZSTD_STREAM, Layout.PACKED, 60.0, 16, 100, inst)
    fields = HASH + H("09000000") + H("03") + H("01") + H("0000") + struct.pack("<f", 60.0)
    fields += H("01000000") + H("10000000") + H("64000000")
    record = ONE + ZERO + ZERO + H("0000003f") + H("02000000 03000000 04000000") + ZERO + H("10000000")
    record += ZERO + ZERO + ZERO
    data, back = roundtrip(msg)
    assert data == header(2, len(fields) + 48) + fields + record
    assert back.instances.tobytes() == inst.tobytes()
    assert (back.connection_id, back.codec, back.layout, back.n_buckets, back.cell_capacity) == (
        9, Codec.ZSTD_STREAM, Layout.PACKED, 16, 100)
    with pytest.raises(LimitError, match="buckets"):
        m.Welcome.parse(fields[:48] + H("ffffffff") + fields[52:] + record)


def _small_delta() -> GridDelta:
    bucket = np.full((1, 8, 2), EMPTY, np.uint32)
    bucket[0, 0] = (6, 3)
    cells = np.array([[0x801234FF, 0, 0, 0, 0, 0, 0, 5], [0] * 7 + [0xFFFFFFFF]], np.uint32)
    return GridDelta(4, [1], np.eye(4)[None], [2], bucket, [0, 3], cells)


def test_update_plain_layout_bytes():
    d = _small_delta()
    counts = H("00") + H("04000000 01000000 01000000 02000000")
    body = H("01000000") + EYE + H("02000000") + H("06000000 03000000") + H("ffffffff") * 14
    body += H("00000000 03000000") + H("ff341280 00000000") + ZERO * 5 + H("05000000") + ZERO * 7 + H("ffffffff")
    payload = H("0700000000000000") + struct.pack("<d", 0.5) + counts + body
    assert m.Update(7, 0.5, d, Layout.PLAIN).serialize() == payload
    back = m.Update.parse(payload)
    assert back.tick == 7 and back.server_time == 0.5 and back.layout == Layout.PLAIN
    assert back.delta.equals(d)


def test_update_packed_layout_bytes():
    d = _small_delta()
    counts = H("01") + H("04000000 01000000 01000000 02000000") + H("01000000 01000000 02000000")
    plane2 = bytes(0x80 if i in (0, 5, 10, 15) else 0 for i in range(16))
    plane3 = bytes(0x3F if i in (0, 5, 10, 15) else 0 for i in range(16))
    transforms = H("01") + bytes(32) + plane2 + plane3  # id 1 as a varint, then 4 byte planes
    buckets = H("02") + H("01") + H("06 00 00 00") + H("03 00 00 00")  # id, 1 used entry, key and slot planes
    cells = H("00 02") + H("01 00")  # slots 0 and 3 as gaps, point counts
    cells += H("05ff 00ff 00ff 00ff")  # key planes of both cells
    cells += H("12 00") + H("34") + H("ff")  # position planes, normal, AO of the one point
    payload = H("0700000000000000") + struct.pack("<d", 0.5) + counts + transforms + buckets + cells
    assert m.Update(7, 0.5, d, Layout.PACKED).serialize() == payload
    assert m.Update.parse(payload).delta.equals(d)


def test_snapshot_chunk_bytes_and_range():
    d = GridDelta(0)
    payload = H("02000000 05000000") + H("00") + bytes(16)
    assert m.Snapshot(2, 5, d, Layout.PLAIN).serialize() == payload
    s = m.Snapshot.parse(payload)
    assert (s.chunk, s.n_chunks) == (2, 5)
    with pytest.raises(PayloadError, match="out of range"):
        m.Snapshot.parse(H("05000000 05000000") + payload[8:])


@pytest.mark.parametrize(
    "data, exc, text",
    [
        (b"PSA", HeaderError, "truncated header"),
        (b"XXXX" + bytes(8), HeaderError, "bad magic"),
        (b"PSAO" + H("0200") + H("0100") + bytes(4), HeaderError, "version"),
        (header(99, 0), HeaderError, "unknown message type"),
        (header(1, 0, codec=9), HeaderError, "unknown codec"),
        (header(5, 1 << 30), LimitError, "over the limit"),
        (header(5, 10) + b"short", HeaderError, "carries 5"),
    ],
)
def test_bad_headers(data, exc, text):
    with pytest.raises(exc, match=text):
        m.Header.parse(data, 1 << 20)


def test_varints_and_gaps():
    values = np.array([0, 1, 127, 128, 300, 16383, 16384, 2**21, 2**28, 2**32 - 1], np.uint32)
    enc = varint_encode(values)
    assert enc[:7] == H("00 01 7f 8001 ac02")
    assert np.array_equal(varint_decode(enc, len(values), "v"), values)
    with pytest.raises(PayloadError):
        varint_decode(enc, len(values) + 1, "v")
    with pytest.raises(PayloadError):
        varint_decode(H("ffffffff7f"), 1, "v")  # 35 bits
    with pytest.raises(PayloadError):
        varint_decode(H("808080808001"), 1, "v")  # 6 bytes
    with pytest.raises(PayloadError):
        varint_decode(H("0102"), 1, "v")  # one-byte values, one too many
    rng = np.random.default_rng(0)
    for top in (1 << 7, 1 << 14, 1 << 32):  # one-byte values only, and mixed lengths
        values = rng.integers(0, top, 500, dtype=np.uint64).astype(np.uint32)
        assert np.array_equal(varint_decode(varint_encode(values), len(values), "v"), values)
    ids = np.array([0, 1, 5, 1000, 2**32 - 1], np.uint32)
    assert gaps_encode(ids)[:3] == H("00 00 03")
    assert np.array_equal(gaps_decode(gaps_encode(ids), len(ids), "g"), ids)


def _leb128(value: int) -> bytes:
    out = bytearray()
    while True:
        byte, value = value & 0x7F, value >> 7
        out.append(byte | (0x80 if value else 0))
        if not value:
            return bytes(out)


def test_varints_equal_plain_leb128():
    rng = np.random.default_rng(7)
    edges = [2**k + d for k in (7, 14, 21, 28) for d in (-1, 0, 1)] + [0, 2**32 - 1]
    values = np.concatenate([np.array(edges, np.uint32), rng.integers(0, 2**32, 500, dtype=np.uint32),
                             (rng.integers(0, 2**32, 500, dtype=np.uint32) >> rng.integers(0, 32, 500)).astype(np.uint32)])
    assert varint_encode(values) == b"".join(_leb128(int(x)) for x in values)
    assert varint_encode(values[:1]) == _leb128(int(values[0])) and varint_encode(values[:0]) == b""


def _random_delta(rng, nb=60, nc=90, cap=2000) -> GridDelta:
    b_ids = np.sort(rng.choice(1 << 14, nb, replace=False))
    buckets = np.full((nb, 8, 2), EMPTY, np.uint32)
    used = rng.integers(0, 9, nb)
    for i, n in enumerate(used):
        buckets[i, :n, 0] = rng.integers(0, 1 << 30, n)
        buckets[i, :n, 1] = rng.integers(0, cap, n)
    slots = np.sort(rng.choice(cap, nc, replace=False))
    cells = np.zeros((nc, 8), np.uint32)
    cells[:, 7] = rng.integers(0, 1 << 30, nc)
    for i, n in enumerate(rng.integers(0, 8, nc)):
        cells[i, :n] = 0x80000000 | rng.integers(0, 1 << 31, n)
    cells[rng.random(nc) < 0.1, 7] = EMPTY
    # Non-canonical records (holes, stray bits) must survive too: PACKED sends them whole.
    buckets[0, 0] = (EMPTY, 5)
    buckets[1] = rng.integers(0, 1 << 32, (8, 2), dtype=np.uint64)
    cells[0, 3] = 7
    cells[1, :7] = rng.integers(0, 1 << 32, 7, dtype=np.uint64)
    k = 3
    return GridDelta(cap, [0, 4, 9], rng.normal(size=(k, 4, 4)), b_ids, buckets, slots, cells)


@pytest.mark.parametrize("layout", list(Layout))
def test_random_deltas_roundtrip_exactly(layout):
    rng = np.random.default_rng(5)
    for _ in range(20):
        d = _random_delta(rng)
        back, got_layout = decode_delta(Reader(encode_delta(d, layout), "t"))
        assert got_layout == layout and back.equals(d)
    empty = GridDelta(0)
    assert decode_delta(Reader(encode_delta(empty, layout), "t"))[0].equals(empty)


@pytest.mark.parametrize("layout", list(Layout))
def test_canonical_and_cell_only_deltas_roundtrip_exactly(layout):
    """The usual Update: cells only (no bucket changed), every record canonical (no raw section)."""
    rng = np.random.default_rng(9)
    for nb in (0, 3):
        d = _random_delta(rng, nb=nb + 2, nc=120)  # its first 2 buckets and cells are the raw ones
        d = GridDelta(d.cell_capacity, d.transform_ids, d.transforms, d.bucket_ids[2:], d.buckets[2:],
                      d.cell_slots[2:], d.cells[2:])
        back, _ = decode_delta(Reader(encode_delta(d, layout), "t"))
        assert back.equals(d)


@pytest.mark.parametrize("layout", list(Layout))
def test_delta_truncation_and_garbage_rejected(layout):
    data = encode_delta(_random_delta(np.random.default_rng(2)), layout)
    for cut in (1, 7, len(data) // 2, len(data) - 1):
        with pytest.raises(PayloadError):
            decode_delta(Reader(data[:cut], "t"))
    with pytest.raises(PayloadError, match="unexpected bytes"):
        decode_delta(Reader(data + b"\0", "t"))


def test_delta_counts_checked_before_allocation():
    huge = H("00") + H("00000001 00000000 00000000 ffffff7f")  # 2^31 cells claimed in a tiny payload
    with pytest.raises(LimitError, match="cell count"):
        decode_delta(Reader(huge, "t"))
    small = Limits(max_cell_capacity=10)
    with pytest.raises(LimitError, match="capacity"):
        decode_delta(Reader(H("00") + H("0b000000") + bytes(12), "t"), small)


def test_delta_structure_checked():
    d = _small_delta()
    d.cell_slots = np.array([3, 0], np.uint32)
    with pytest.raises(PayloadError, match="sorted"):
        decode_delta(Reader(encode_delta(d, Layout.PLAIN), "t"))
    d = _small_delta()
    d.cell_capacity = 3  # slot 3 outside
    with pytest.raises(PayloadError, match="capacity"):
        decode_delta(Reader(encode_delta(d, Layout.PACKED), "t"))
    d = _small_delta()
    d.transforms[0, 1, 1] = np.nan
    with pytest.raises(PayloadError, match="NaN"):
        decode_delta(Reader(encode_delta(d, Layout.PLAIN), "t"))


def _mutate(rng, data: bytes) -> bytes:
    p = bytearray(data)
    for _ in range(int(rng.integers(1, 4))):
        op = int(rng.integers(0, 3))
        if op == 0 and p:
            p[int(rng.integers(len(p)))] = int(rng.integers(0, 256))
        elif op == 1 and p:
            del p[int(rng.integers(len(p))):]
        else:
            p.insert(int(rng.integers(len(p) + 1)), int(rng.integers(0, 256)))
    return bytes(p)


def test_fuzzed_payloads_raise_protocol_errors_only():
    """Flipped, cut and inserted bytes: every message either parses or raises a ProtocolError."""
    from psao.protocol.errors import ProtocolError

    rng = np.random.default_rng(11)
    originals = [m.Update(1, 0.0, _random_delta(rng, 12, 12), lay) for lay in Layout]
    originals += [m.Snapshot(0, 2, _random_delta(rng, 5, 5), Layout.PACKED), m.Hello(HASH, 3, "tok"),
                  m.Camera(np.eye(4), np.eye(4)), m.Error(3, "x"), m.SceneEdit(1, np.eye(4))]
    for i in range(1500):
        msg = originals[i % len(originals)]
        try:
            msg.parse(_mutate(rng, msg.serialize()))
        except ProtocolError:
            pass


def _parts_payload():
    """An Update of two parts, PLAIN: part 1 moves instance 1, part 2 writes cell slot 5."""
    t = np.eye(4, dtype=np.float32)
    part1 = GridDelta(8, np.array([1], np.uint32), t[None])
    cell = np.arange(1, 9, dtype=np.uint32)[None]
    part2 = GridDelta(8, cell_slots=np.array([5], np.uint32), cells=cell)
    return m.Update(3, 0.5, part1, Layout.PLAIN).serialize() + encode_delta(part2, Layout.PLAIN), part1, part2


def test_update_of_parts_bytes_and_union():
    payload, part1, part2 = _parts_payload()
    identity = "0000803f" + "00000000" * 4 + "0000803f" + "00000000" * 4 + "0000803f" + "00000000" * 4 + "0000803f"
    assert payload.hex() == (
        "0300000000000000" + "000000000000e03f"  # tick 3, server time 0.5
        + "00" + "08000000" + "01000000" + "00000000" + "00000000"  # part 1: PLAIN, capacity 8, 1 transform
        + "01000000" + identity
        + "00" + "08000000" + "00000000" + "00000000" + "01000000"  # part 2: 1 cell
        + "05000000" + "".join(f"{v:02x}000000" for v in range(1, 9)))
    u = m.Update.parse(payload)
    assert (u.tick, u.server_time) == (3, 0.5)
    assert u.delta.transform_ids.tolist() == [1] and u.delta.cell_slots.tolist() == [5]
    assert u.delta.cells.tolist() == part2.cells.tolist() and np.array_equal(u.delta.transforms, part1.transforms)


def test_update_parts_are_sorted_into_one_delta():
    cells = np.arange(24, dtype=np.uint32).reshape(3, 8)
    a = GridDelta(16, cell_slots=np.array([2, 9], np.uint32), cells=cells[:2])
    b = GridDelta(16, cell_slots=np.array([4], np.uint32), cells=cells[2:])
    u = m.Update.parse(m.Update(1, 0.0, a).serialize() + encode_delta(b))
    assert u.delta.cell_slots.tolist() == [2, 4, 9]
    assert u.delta.cells.tolist() == [cells[0].tolist(), cells[2].tolist(), cells[1].tolist()]


def test_update_parts_that_overlap_or_disagree_are_refused():
    payload, part1, part2 = _parts_payload()
    with pytest.raises(PayloadError, match="overlap"):
        m.Update.parse(payload + encode_delta(part2, Layout.PLAIN))
    other = GridDelta(9, cell_slots=np.array([6], np.uint32), cells=part2.cells)
    with pytest.raises(PayloadError, match="capacities"):
        m.Update.parse(payload + encode_delta(other, Layout.PLAIN))
    with pytest.raises(PayloadError, match="layouts"):
        m.Update.parse(payload + encode_delta(GridDelta(8), Layout.PACKED))
    with pytest.raises(PayloadError):
        m.Update.parse(payload + b"\x00")  # a part cut short


def test_gaps_of_several_sections_decode_as_each_alone():
    from psao.protocol.updates import gaps_decode_parts

    rng = np.random.default_rng(7)
    runs = [np.sort(rng.choice(1 << 31, n, replace=False)) for n in (5, 0, 1, 300, 0, 17)]
    datas = [gaps_encode(r) for r in runs]
    got = gaps_decode_parts(datas, [len(r) for r in runs], "ids")
    assert got.tolist() == np.concatenate(runs).tolist()
    with pytest.raises(PayloadError):
        gaps_decode_parts(datas, [4, 1, 1, 300, 0, 17], "ids")  # a value counted in the wrong section
    with pytest.raises(PayloadError):
        gaps_decode_parts([datas[0][:-1], datas[0][-1:] + datas[2]], [5, 1], "ids")  # a varint split between


def test_varint_sections_decode_alike_by_loop_and_vectorised():
    """Small sections are decoded by a loop over their bytes, large ones vectorised: on random valid and
    random malformed sections (among them runs of close ids, one byte each, longer than the loop takes) the
    loop, the vectorised decode and gaps_decode_parts give the same ids or all refuse."""
    from psao.protocol.updates import LOOP_VARINT_BYTES, _gaps_loop, _gaps_numpy, gaps_decode_parts

    rng = np.random.default_rng(13)
    for trial in range(400):
        top = int(rng.choice([200, 1 << 14, 1 << 32]))
        most = 30 if trial % 4 else 600  # (600 close ids: one-byte gaps past LOOP_VARINT_BYTES)
        runs = [np.sort(rng.choice(top, int(rng.integers(0, min(most, top))), replace=False))
                for _ in range(int(rng.integers(1, 6)))]
        datas = [gaps_encode(r) for r in runs]
        counts = [len(r) for r in runs]
        want = np.concatenate(runs).astype(np.uint32)
        for decode in (_gaps_loop, _gaps_numpy, gaps_decode_parts):
            got = decode(datas, counts, "ids")
            assert got.dtype == np.uint32 and got.tolist() == want.tolist()
        # malformed: random bytes, a count off by one, a byte cut or added, a 6-byte varint, a value past 32 bits
        bad = [bytes(rng.integers(0, 256, int(rng.integers(0, 12)), dtype=np.uint8)) for _ in datas]
        k = int(rng.integers(len(datas)))
        cases = [(bad, counts), (datas, [c + (i == k) for i, c in enumerate(counts)]),
                 ([d[:-1] if i == k else d for i, d in enumerate(datas)], counts),
                 ([d + b"\x80" if i == k else d for i, d in enumerate(datas)], counts),
                 ([H("808080808001")], [1]), ([H("ffffffff7f")], [1]), ([H("ffffffff0f") + H("00")], [2])]
        for ds, cs in cases:
            answers = []
            for decode in (_gaps_loop, _gaps_numpy, gaps_decode_parts):
                try:
                    answers.append(decode(ds, cs, "ids").tolist())
                except PayloadError:
                    answers.append("refused")
            assert answers[0] == answers[1] == answers[2], (ds, cs, answers)
    assert _gaps_loop([H("ffffffff0f")], [1], "ids").tolist() == [0xFFFFFFFF]
    big = np.arange(0, 40 * LOOP_VARINT_BYTES, 40)  # gaps of 39: one byte each, more bytes than the loop takes
    assert gaps_decode_parts([gaps_encode(big)], [len(big)], "ids").tolist() == big.tolist()


def test_small_id_sections_encode_to_the_bytes_of_the_vectorised_encode():
    """A few hundred ids are encoded by a loop: the same bytes as the vectorised varints of their gaps."""
    from psao.protocol.updates import LOOP_GAPS_IDS, _gaps_encode_loop

    rng = np.random.default_rng(17)
    for trial in range(300):
        top = int(rng.choice([300, 1 << 14, 1 << 32]))
        ids = np.sort(rng.choice(top, int(rng.integers(0, 60)), replace=False))
        gaps = np.diff(ids, prepend=-1) - 1
        assert _gaps_encode_loop(ids.tolist()) == varint_encode(gaps) == gaps_encode(ids)
    assert gaps_encode(np.array([0, 1, 2, 200, 0xFFFFFFFF])) == H("000000c501b6feffff0f")
    assert _gaps_encode_loop([3, 3]) is None and _gaps_encode_loop([5, 2]) is None  # not strictly increasing
    many = np.arange(0, 3 * LOOP_GAPS_IDS, 3)  # more ids than the loop takes: vectorised, same decode
    assert gaps_decode(gaps_encode(many), len(many), "ids").tolist() == many.tolist()


@pytest.mark.parametrize("layout", list(Layout))
def test_runs_of_cells_encoded_together_give_the_bytes_of_each_run_encoded_alone(layout):
    """The tiles of an Update of parts are encoded in one pass over their rows (encode_cell_runs): each
    tile's bytes equal encode_delta of its cells alone, raw (non-canonical) cells, empty tiles and
    every run length included."""
    from psao.protocol.updates import encode_cell_runs

    rng = np.random.default_rng(23)
    for trial in range(60):
        d = _random_delta(rng, nb=2, nc=int(rng.integers(2, 90)))
        cut = 2 * (trial % 2)  # odd trials without the 2 raw cells: all canonical, no raw section in any tile
        d = GridDelta(d.cell_capacity, cell_slots=d.cell_slots[cut:], cells=d.cells[cut:])
        n = len(d.cell_slots)
        cuts = np.sort(rng.integers(0, n + 1, int(rng.integers(0, 6)))).tolist()  # repeats: empty runs
        bounds = [0, *cuts, n]
        runs = [(a, b) for a, b in zip(bounds[:-1], bounds[1:])]
        rng.shuffle(runs)  # tiles are encoded in any order, and some runs not at all
        runs = runs[: int(rng.integers(0, len(runs) + 1))]
        alone = [encode_delta(GridDelta(d.cell_capacity, cell_slots=d.cell_slots[a:b], cells=d.cells[a:b]), layout)
                 for a, b in runs]
        assert encode_cell_runs(d.cell_capacity, d.cell_slots, d.cells, runs, layout) == alone


def test_update_of_many_packed_parts_equals_the_union_of_the_parts_decoded_alone():
    from psao.protocol.updates import union_of_parts

    rng = np.random.default_rng(11)
    slots = rng.permutation(5000)[:400].astype(np.uint32)
    parts = []
    for k, chunk in enumerate(np.array_split(slots, 9)):
        cells = np.zeros((len(chunk), 8), np.uint32)
        used = rng.integers(0, 8, len(chunk))
        for i, u in enumerate(used):
            cells[i, :u] = (1 << 31) | rng.integers(0, 1 << 23, u)
        cells[:, 7] = rng.integers(0, 1 << 30, len(chunk))
        if k == 3:
            cells[0, 5] = 7  # a cell outside the packed form (sent raw)
        order = np.argsort(chunk)
        parts.append(GridDelta(5000, cell_slots=chunk[order], cells=cells[order]))
    payload = m.Update(2, 1.0, parts[0]).serialize() + b"".join(encode_delta(p) for p in parts[1:])
    got = m.Update.parse(payload).delta
    assert got.equals(union_of_parts(parts))
    assert got.cell_slots.tolist() == sorted(slots.tolist())


@pytest.mark.parametrize("bad_part", [0, 2])
def test_a_cell_count_over_the_points_per_cell_in_any_part_is_refused(bad_part):
    """A cell's count byte is its number of points (at most POINTS_PER_CELL) or RAW, in every part of an
    Update."""
    from psao.protocol.gridformat import POINTS_PER_CELL
    from psao.protocol.updates import gaps_encode

    parts = []
    for k in range(3):
        slots = np.arange(10, dtype=np.uint32) * 3 + k
        cells = np.zeros((10, 8), np.uint32)
        cells[:, :2] = (1 << 31) | 5
        parts.append(encode_delta(GridDelta(100, cell_slots=slots, cells=cells)))
    lc = len(gaps_encode(np.arange(10) * 3 + bad_part))
    counts_at = struct.calcsize("<BIIII") + struct.calcsize("<III") + lc
    part = bytearray(parts[bad_part])
    assert part[counts_at] == 2
    part[counts_at] = POINTS_PER_CELL + 1
    parts[bad_part] = bytes(part)
    head = m.Update(1, 0.0, GridDelta(100)).serialize()
    m.Update.parse(head + b"".join(p for k, p in enumerate(parts) if k != bad_part))  # the others decode
    with pytest.raises(PayloadError, match=f"entry count above {POINTS_PER_CELL}"):
        m.Update.parse(head + b"".join(parts))


def _payload_of_parts(rng, layouts=(Layout.PACKED,)) -> bytes:
    """An Update's delta bytes as the fanout writes them: a head (transforms, buckets, maybe cells), then
    tiles of cells only (disjoint slots, some empty, some with raw cells), each part in a layout of `layouts`."""
    cap = int(rng.integers(50, 5000))
    n_tiles = int(rng.integers(0, 12))
    sizes = rng.integers(0, 30, n_tiles + 1)
    slots = rng.permutation(rng.choice(cap, min(cap, int(sizes.sum())), replace=False))
    runs = np.split(slots, np.cumsum(sizes)[:-1].clip(max=len(slots)))
    deltas = []
    for i, run in enumerate(runs):
        d = _random_delta(rng, nb=6, nc=2, cap=cap)
        nb = int(rng.integers(0, 7)) if i == 0 else 0
        cells = np.zeros((len(run), 8), np.uint32)
        cells[:, 7] = rng.integers(0, 1 << 32, len(run), dtype=np.uint64)
        for j, n in enumerate(rng.integers(0, 8, len(run))):
            cells[j, :n] = 0x80000000 | rng.integers(0, 1 << 31, n)
        raw = rng.random(len(run)) < 0.05
        cells[raw, :7] = rng.integers(0, 1 << 32, (int(raw.sum()), 7), dtype=np.uint64)
        keep_head = i == 0 and rng.random() < 0.7
        deltas.append(GridDelta(cap, d.transform_ids if keep_head else [], d.transforms if keep_head else np.zeros((0, 4, 4)),
                                d.bucket_ids[:nb], d.buckets[:nb],
                                np.sort(run), cells[np.argsort(run)]))
    return b"".join(encode_delta(d, layouts[int(rng.integers(len(layouts)))]) for d in deltas)


def _decoded_both_ways(payload: bytes, limits: Limits):
    """decode_delta_parts and the reader of any part (_read_part) on every part: each delta, or the refusal's
    type and text."""
    from psao.protocol import updates

    out = []
    for read in (lambda r: updates.decode_delta_parts(r, limits), lambda r: updates._read_parts(r, limits, updates._read_part)):
        try:
            delta, layout = read(Reader(payload, "update"))
            out.append((delta, layout))
        except (PayloadError, LimitError) as e:
            out.append((type(e), str(e)))
    return out


def _same(a, b) -> bool:
    if isinstance(a[0], GridDelta) and isinstance(b[0], GridDelta):
        return a[1] == b[1] and a[0].equals(b[0]) and all(
            getattr(a[0], f).dtype == getattr(b[0], f).dtype and getattr(a[0], f).shape == getattr(b[0], f).shape
            for f in ("transform_ids", "transforms", "bucket_ids", "buckets", "cell_slots", "cells"))
    return a == b


def test_parts_decoder_gives_the_delta_the_reader_of_any_part_gives():
    rng = np.random.default_rng(13)
    for _ in range(200):
        payload = _payload_of_parts(rng)
        fast, general = _decoded_both_ways(payload, Limits())
        assert isinstance(fast[0], GridDelta) and _same(fast, general)


@pytest.mark.parametrize("seed", range(4))
def test_parts_decoder_refuses_what_the_reader_of_any_part_refuses(seed):
    """Truncated, extended, mutated, overlapping, mixed-layout and over-limit payloads: the same delta or
    the same refusal (type and text) both ways."""
    rng = np.random.default_rng(100 + seed)
    tight = Limits(max_cell_capacity=3000, max_cells_per_message=20, max_buckets_per_message=4)
    refused = 0
    for _ in range(60):
        payload = _payload_of_parts(rng, layouts=(Layout.PACKED, Layout.PACKED, Layout.PLAIN))
        bad = [payload[: int(rng.integers(0, len(payload)))], payload + rng.bytes(int(rng.integers(1, 40))),
               payload + payload[-int(rng.integers(1, len(payload))):]]  # (a repeated tail: overlapping parts)
        for _ in range(8):
            b = np.frombuffer(payload, np.uint8).copy()
            at = rng.integers(0, len(b), int(rng.integers(1, 4)))
            b[at] = rng.integers(0, 256, len(at))
            bad.append(b.tobytes())
        for data in [payload, *bad]:
            for limits in (Limits(), tight):
                fast, general = _decoded_both_ways(data, limits)
                assert _same(fast, general), (fast, general)
                refused += not isinstance(fast[0], GridDelta)
    assert refused > 100


def test_parts_decoder_refuses_every_truncation_as_the_reader_of_any_part():
    rng = np.random.default_rng(7)
    payloads = [p for p in (_payload_of_parts(rng) for _ in range(40)) if 200 < len(p) < 1500][:3]
    assert payloads
    for payload in payloads:
        for n in range(len(payload)):
            fast, general = _decoded_both_ways(payload[:n], Limits())
            assert _same(fast, general), (n, fast, general)


def test_status_bytes_both_ways():
    """Status: phase u8 | progress f32 | text length u16 | text, codec NONE, type 11."""
    assert m.MessageType.STATUS == 11
    assert [int(p) for p in m.StatusPhase] == [1, 2, 3, 4]
    data = m.encode(m.Status(m.StatusPhase.BAKING, 0.5, "baking 50%"))
    assert data == header(11, 17) + H("02") + H("0000003f") + H("0a00") + b"baking 50%"
    back = m.Status.parse(H("03") + H("0000803f") + H("0300") + "né".encode())
    assert back == m.Status(m.StatusPhase.COARSE, 1.0, "né") and isinstance(back.phase, m.StatusPhase)
    assert m.Status.parse(H("04") + ZERO + H("0000")) == m.Status(m.StatusPhase.READY, 0.0, "")
    assert m.encode(m.Status(m.StatusPhase.LOADING, 0.0)) == header(11, 7) + H("01") + ZERO + H("0000")
    _, parsed = roundtrip(m.Status(m.StatusPhase.COARSE, 0.25, "full grid: trace"))
    assert parsed == m.Status(m.StatusPhase.COARSE, 0.25, "full grid: trace")


@pytest.mark.parametrize("payload, exc, text", [
    (H("00") + ZERO + H("0000"), PayloadError, "unknown phase 0"),
    (H("05") + ZERO + H("0000"), PayloadError, "unknown phase 5"),
    (H("02") + H("0000c07f") + H("0000"), PayloadError, "not within 0..1"),  # NaN
    (H("02") + H("0000807f") + H("0000"), PayloadError, "not within 0..1"),  # +inf
    (H("02") + H("000080bf") + H("0000"), PayloadError, "not within 0..1"),  # -1
    (H("02") + H("cdcc8c3f") + H("0000"), PayloadError, "not within 0..1"),  # 1.1
    (H("02") + ZERO + H("0200") + b"\xff\xfe", PayloadError, "not valid UTF-8"),
    (H("02") + ZERO + H("0500") + b"ab", PayloadError, "truncated"),
    (H("02") + ZERO + H("0100") + b"ab", PayloadError, "unexpected bytes after the end"),
    (H("02") + ZERO, PayloadError, "truncated"),
    (H("02") + ZERO + H("0104") + b"a" * 1025, LimitError, "over the limit of 1024"),
])
def test_bad_status_payloads_refused(payload, exc, text):
    with pytest.raises(exc, match=text):
        m.Status.parse(payload)


def test_status_serialize_checks_and_cuts_its_text():
    for phase, progress in ((0, 0.5), (m.StatusPhase.BAKING, float("nan")), (m.StatusPhase.BAKING, 1.5)):
        with pytest.raises(PayloadError):
            m.Status(phase, progress).serialize()
    long = m.Status(m.StatusPhase.BAKING, 0.1, "é" * 600).serialize()  # 1200 bytes of text: cut at a character
    assert struct.unpack_from("<H", long, 5)[0] == 1024 and m.Status.parse(long).text == "é" * 512
    assert m.Status.parse(m.Status(m.StatusPhase.BAKING, 0.1, "x" * 2000).serialize(), Limits()).text == "x" * 1024
