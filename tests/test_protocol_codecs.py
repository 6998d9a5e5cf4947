"""Codecs: exact round trips, and decompression bombs refused before or while decoding."""
from __future__ import annotations

import lz4.frame
import numpy as np
import pytest
import zstandard

from psao.protocol.codecs import (
    Codec,
    FrameCodec,
    StreamCompressor,
    StreamDecompressor,
    codec_mask,
    codecs_from_mask,
    decompress_frame,
)
from psao.protocol.errors import CodecError, LimitError

CAP = 1 << 20


def _payloads():
    rng = np.random.default_rng(0)
    yield b""
    yield b"x"
    yield rng.integers(0, 4, 200_000, dtype=np.uint8).tobytes()
    yield rng.integers(0, 256, 5000, dtype=np.uint8).tobytes()


@pytest.mark.parametrize("codec", [Codec.NONE, Codec.ZSTD, Codec.LZ4])
def test_frame_codecs_roundtrip(codec):
    fc = FrameCodec(codec)
    for p in _payloads():
        assert decompress_frame(codec, fc.compress(p), CAP) == p


def test_stream_roundtrip_every_message_decodes_on_arrival():
    comp, dec = StreamCompressor(), StreamDecompressor()
    rng = np.random.default_rng(1)
    base = rng.integers(0, 256, 20_000, dtype=np.uint8)
    sizes = []
    for i in range(30):
        msg = base.copy()
        msg[rng.integers(0, len(msg), 50)] = i  # mostly a repeat of earlier messages
        data = comp.compress(msg.tobytes())
        sizes.append(len(data))
        assert dec.decompress(data, CAP) == msg.tobytes()
    assert max(sizes[5:]) < sizes[0] / 4  # later messages refer back to earlier ones


def test_codec_mask():
    assert codec_mask([Codec.NONE, Codec.ZSTD_STREAM]) == 0b1001
    assert codecs_from_mask(0b0110) == {Codec.ZSTD, Codec.LZ4}


def test_zstd_bomb_with_declared_size_refused_without_decoding():
    bomb = zstandard.ZstdCompressor(level=1).compress(bytes(64 << 20))
    assert len(bomb) < 10_000
    with pytest.raises(LimitError, match="declares 67108864"):
        decompress_frame(Codec.ZSTD, bomb, CAP)


def test_zstd_forged_huge_declared_size_refused():
    # A frame header claiming 2^60 bytes followed by almost nothing.
    frame = zstandard.ZstdCompressor(level=1).compress(b"abc")
    params = zstandard.get_frame_parameters(frame)
    assert params.content_size == 3
    forged = bytes.fromhex("28b52ffd") + bytes([0xE0]) + (1 << 60).to_bytes(8, "little") + b"\0" * 8
    with pytest.raises((LimitError, CodecError)):
        decompress_frame(Codec.ZSTD, forged, CAP)


def test_zstd_bomb_without_size_is_capped_while_decoding():
    cctx = zstandard.ZstdCompressor(level=1, write_content_size=False)
    bomb = cctx.compress(bytes(256 << 20))
    assert zstandard.frame_content_size(bomb) == -1
    with pytest.raises(LimitError, match="exceeds the limit"):
        decompress_frame(Codec.ZSTD, bomb, CAP)


def test_stream_bomb_is_capped():
    comp, dec = StreamCompressor(), StreamDecompressor()
    assert dec.decompress(comp.compress(b"hello"), CAP) == b"hello"
    with pytest.raises(LimitError):
        dec.decompress(comp.compress(bytes(64 << 20)), CAP)


def test_lz4_bomb_refused():
    bomb = lz4.frame.compress(bytes(32 << 20), store_size=True)
    with pytest.raises(LimitError, match="declares"):
        decompress_frame(Codec.LZ4, bomb, CAP)
    bomb = lz4.frame.compress(bytes(32 << 20), store_size=False)
    with pytest.raises(LimitError, match="exceeds"):
        decompress_frame(Codec.LZ4, bomb, CAP)


@pytest.mark.parametrize("codec", [Codec.ZSTD, Codec.LZ4])
def test_trailing_garbage_truncation_and_junk_refused(codec):
    data = FrameCodec(codec).compress(b"payload" * 100)
    with pytest.raises(CodecError, match="after the frame"):
        decompress_frame(codec, data + b"junk", CAP)
    with pytest.raises(CodecError):
        decompress_frame(codec, data[:-3], CAP)
    with pytest.raises(CodecError):
        decompress_frame(codec, b"definitely not compressed", CAP)


def test_none_codec_limit():
    with pytest.raises(LimitError):
        decompress_frame(Codec.NONE, bytes(CAP + 1), CAP)


def test_stream_codec_is_not_a_frame_codec():
    with pytest.raises(CodecError):
        FrameCodec(Codec.ZSTD_STREAM)
    with pytest.raises(CodecError):
        decompress_frame(Codec.ZSTD_STREAM, b"", CAP)


# b"ab" and b"cd", each a whole zstd frame (magic, header with the content size, one raw block)
FRAME_AB = bytes.fromhex("28b52ffd20021100006162")
FRAME_CD = bytes.fromhex("28b52ffd20021100006364")


def test_zstd_payload_of_several_frames_is_their_contents_concatenated():
    assert decompress_frame(Codec.ZSTD, FRAME_AB + FRAME_CD, CAP) == b"abcd"
    ab, cd = (zstandard.ZstdCompressor(level=3).compress(p) for p in (b"ab", b"cd"))
    assert (ab, cd) == (FRAME_AB, FRAME_CD)
    assert decompress_frame(Codec.ZSTD, ab + cd, CAP) == b"abcd"
    assert decompress_frame(Codec.ZSTD, ab + cd + ab, CAP) == b"abcdab"
    with pytest.raises(CodecError, match="after the frame"):
        decompress_frame(Codec.ZSTD, ab + cd + b"junk", CAP)
    with pytest.raises(CodecError, match="truncated"):
        decompress_frame(Codec.ZSTD, ab + cd[:-2], CAP)


def test_zstd_cap_holds_for_all_frames_together():
    part = FrameCodec(Codec.ZSTD).compress(bytes(CAP // 2 + 1))
    assert len(decompress_frame(Codec.ZSTD, part, CAP)) == CAP // 2 + 1
    with pytest.raises(LimitError):
        decompress_frame(Codec.ZSTD, part + part, CAP)


def test_bomb_of_rle_blocks_stops_within_a_few_blocks_of_the_cap_in_pieces_sized_to_the_room():
    """The worst case: a frame of 4-byte RLE blocks, 128 KiB each. Input goes in pieces sized so that
    their output cannot pass the cap (large far from it, limits.decompress_piece_bytes near it), so the
    output seen before the cap check stops it passes the cap by at most (piece / 4 + 1) blocks."""
    from psao.protocol.codecs import ZSTD_BLOCK_MAX, _zstd_bounded
    from psao.protocol.limits import DEFAULT_LIMITS as L

    block = ((ZSTD_BLOCK_MAX << 3) | (1 << 1)).to_bytes(3, "little") + b"\x07"  # RLE block of 128 KiB of 7s
    frame = bytes.fromhex("28b52ffd") + bytes([0x00, 0x38]) + block * 400  # no content size, 128 KiB window
    cap = 16 << 20

    class Spy:
        def __init__(self):
            self.inner = zstandard.ZstdDecompressor().decompressobj()
            self.out = 0
            self.calls = 0

        def decompress(self, data):
            self.calls += 1
            chunk = self.inner.decompress(data)
            self.out += len(chunk)
            return chunk

        def __getattr__(self, name):
            return getattr(self.inner, name)

    spy = Spy()
    with pytest.raises(LimitError, match="exceeds the limit"):
        _zstd_bounded(spy, frame, cap, L, "bomb")
    assert cap < spy.out <= cap + (L.decompress_piece_bytes // 4 + 1) * ZSTD_BLOCK_MAX
    assert spy.calls < len(frame) // L.decompress_piece_bytes / 4  # far from the cap, pieces are larger
    whole = Spy()  # and a frame that fits decodes whole, exactly
    fits = bytes.fromhex("28b52ffd") + bytes([0x00, 0x38]) + block * 20 + ((ZSTD_BLOCK_MAX << 3) | 3).to_bytes(3, "little") + b"\x07"
    assert _zstd_bounded(whole, fits, cap, L, "fits").data == b"\x07" * (21 * ZSTD_BLOCK_MAX)
