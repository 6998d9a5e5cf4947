"""Payload codecs: none, zstd (one frame per message), lz4 (one frame per message), and a zstd stream.

The codec byte in every message header says how that payload is compressed. ZSTD_STREAM is a zstd
frame that lives across messages, flushed at a block boundary after every message (the paper compresses
each message alone; a stream lets a message refer to earlier ones, which is where most of the redundancy
of an update stream is: the same cells change again and again). A ZSTD_STREAM message that begins with
the zstd frame magic starts the stream anew: the decoder drops the frame it was in and decodes a new
one. That is how a sender switches a connection from one encoder to another (its own, or one shared by
many connections, whose bytes every one of them receives): the first message from the new encoder
starts a frame. A continuation can never begin with the magic: read as a block header, those bytes
declare a raw block of 390,821 bytes, over zstd's 128 KiB block maximum.

Decompression never trusts a declared size: a zstd frame whose header declares more than the cap is
refused before anything is decoded; otherwise the input is fed in pieces no larger than what cannot
decode past the cap (small ones near it) and decoding stops as soon as the output passes the cap (a
decompression bomb costs at most the cap plus a few MiB). A ZSTD
payload may hold several whole frames back to back (a sender that compressed parts of a message apart
sends them so, and each part's bytes can be shared by many messages); the cap holds for all of them
together, and bytes after the last frame that are not a whole frame are refused. An LZ4 payload is
one frame: bytes after it are refused.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import lz4.frame
import zstandard

from psao.protocol.errors import CodecError, LimitError
from psao.protocol.limits import DEFAULT_LIMITS, Limits


class Codec(IntEnum):
    NONE = 0
    ZSTD = 1  # one or more zstd frames per message (contents concatenated), content sizes in the frame headers
    LZ4 = 2  # one lz4 frame per message, content size in the frame header
    ZSTD_STREAM = 3  # one zstd frame per connection, a flushed block per message


CODEC_NAMES = {"none": Codec.NONE, "zstd": Codec.ZSTD, "lz4": Codec.LZ4, "zstd-stream": Codec.ZSTD_STREAM}


def codec_name(codec: Codec) -> str:
    return next(name for name, c in CODEC_NAMES.items() if c == codec)


def codec_mask(codecs) -> int:
    """Set of codecs -> bit mask (bit c set when codec c is accepted), as carried by Hello."""
    mask = 0
    for c in codecs:
        mask |= 1 << int(c)
    return mask


def codecs_from_mask(mask: int) -> frozenset[Codec]:
    return frozenset(c for c in Codec if mask & (1 << int(c)))


ZSTD_FRAME_MAGIC = b"\x28\xb5\x2f\xfd"  # the first four bytes of every zstd frame


def starts_frame(data) -> bool:
    """Whether a ZSTD_STREAM payload starts a new frame (the stream starts anew)."""
    return bytes(data[:4]) == ZSTD_FRAME_MAGIC


@dataclass(frozen=True)
class ZstdSettings:
    level: int = 15  # the paper's level
    strategy: int = zstandard.STRATEGY_LAZY  # the paper's "strategy 4"
    window_log: int = 0  # log2 of the match window (bytes); 0: zstd's choice for the level
    hash_log: int = 0  # log2 of the hash table's entries; 0: zstd's choice
    chain_log: int = 0  # log2 of the match chain's entries; 0: zstd's choice

    def parameters(self) -> zstandard.ZstdCompressionParameters:
        # Level and strategy only (unless sizes are given), the rest left to zstd, as ZSTD_CCtx_setParameter
        # + ZSTD_compress2 do in the paper's C++: for a message of known size zstd then fits window and
        # tables to it, which is both smaller and faster than from_level()'s parameters for an unknown size
        # (so the baseline is the strong one). A stream has no known size and gets from_level()'s
        # parameters: about 45 MB of context at level 15, hence the sized settings for per-connection streams.
        sizes = {k: v for k, v in (("window_log", self.window_log), ("hash_log", self.hash_log),
                                   ("chain_log", self.chain_log)) if v}
        return zstandard.ZstdCompressionParameters(compression_level=self.level, strategy=self.strategy, **sizes)

    def compressor(self) -> zstandard.ZstdCompressor:
        return zstandard.ZstdCompressor(compression_params=self.parameters())


PAPER_ZSTD = ZstdSettings()
# The shared zstd stream (one for many connections): the paper's level and strategy in a
# 128 KiB window (a few updates back, where the repeats are) with 64 Ki-entry tables: about 1.2 MB of
# context instead of from_level()'s 45 MB, for 3% more bytes on the animated courtyard's updates.
STREAM_ZSTD = ZstdSettings(window_log=17, hash_log=16, chain_log=16)
# A connection's own zstd stream (its snapshot, and Updates while it is off the shared stream: culled, joining,
# behind): compressed once per client, so a fast level. Level 3 (the paper's lazy strategy) in the same
# 128 KiB window takes half the compression time of STREAM_ZSTD for about 1% more bytes (the courtyard
# at N=64: its snapshot 1.4% more, culled per-client Updates 1.0% more).
OWN_STREAM_ZSTD = ZstdSettings(level=3, window_log=17)


class FrameCodec:
    """Stateless per-message compression (NONE, ZSTD, LZ4). Keeps its zstd context for speed."""

    def __init__(self, codec: Codec, zstd_settings: ZstdSettings = PAPER_ZSTD):
        if codec == Codec.ZSTD_STREAM:
            raise CodecError("zstd-stream is not a per-message codec")
        self.codec = Codec(codec)
        self._zstd = zstd_settings.compressor() if codec == Codec.ZSTD else None

    def compress(self, payload: bytes) -> bytes:
        if self.codec == Codec.NONE:
            return bytes(payload)
        if self.codec == Codec.ZSTD:
            return self._zstd.compress(payload)
        return lz4.frame.compress(payload, store_size=True, compression_level=0)


class StreamCompressor:
    """A zstd frame across messages; every message ends at a flushed block so it decodes on arrival.
    The first message, and the first after restart(), starts a new frame."""

    codec = Codec.ZSTD_STREAM

    def __init__(self, zstd_settings: ZstdSettings = PAPER_ZSTD):
        self._zstd = zstd_settings.compressor()
        self._obj = self._zstd.compressobj()

    def restart(self) -> None:
        """The next message starts a new frame, with no reference to what came before."""
        self._obj = self._zstd.compressobj()

    def compress(self, payload: bytes) -> bytes:
        return self._obj.compress(payload) + self._obj.flush(zstandard.COMPRESSOBJ_FLUSH_BLOCK)


ZSTD_BLOCK_MAX = 128 * 1024  # the most one zstd block decodes to
ZSTD_BLOCK_MIN = 4  # the fewest bytes a block takes (3 of header, 1 of an RLE block's byte)


def _piece(room: int, smallest: int) -> int:
    """Input bytes to feed next so that their output cannot pass `room` more bytes: each block they
    complete (one begun earlier, and one per ZSTD_BLOCK_MIN bytes fed) decodes to at most ZSTD_BLOCK_MAX;
    at least `smallest` (limits.decompress_piece_bytes, which then bounds the overshoot)."""
    return max(smallest, ZSTD_BLOCK_MIN * (room // ZSTD_BLOCK_MAX - 1))


def _zstd_bounded(dobj, data: bytes, cap: int, limits: Limits, what: str) -> _Frame:
    """Feed `data` to a zstd decompressobj in pieces, each no larger than what cannot decode past `cap`
    (near the cap, limits.decompress_piece_bytes); stop as soon as the output passes `cap`, or where the
    frame ends (the bytes after it are counted, not fed)."""
    out: list[bytes] = []
    total = 0
    view = memoryview(data)
    i = 0
    try:
        while i < len(data):
            piece = _piece(cap - total, limits.decompress_piece_bytes)
            chunk = dobj.decompress(view[i : i + piece])
            i += piece
            if chunk:
                total += len(chunk)
                if total > cap:
                    raise LimitError(f"{what}: decompressed payload exceeds the limit of {cap} bytes")
                out.append(chunk)
            if dobj.eof:
                return _Frame(b"".join(out), len(dobj.unused_data) + max(0, len(data) - i))
    except zstandard.ZstdError as exc:
        raise CodecError(f"{what}: corrupt zstd data ({exc})") from None
    return _Frame(b"".join(out), 0)


@dataclass
class _Frame:
    data: bytes
    unused: int  # bytes after the frame


def _decompress_zstd_frames(data: bytes, cap: int, limits: Limits) -> bytes:
    """A ZSTD payload: one or more whole zstd frames, back to back; their contents concatenated (as
    RFC 8878 decoders read consecutive frames). The cap holds for the total."""
    out: list[bytes] = []
    total = 0
    view = memoryview(data)
    dctx = zstandard.ZstdDecompressor(max_window_size=limits.zstd_max_window_bytes)
    while True:
        part = _decompress_zstd_frame(dctx, view, cap - total, limits)
        out.append(part.data)
        total += len(part.data)
        if not part.unused:
            return b"".join(out)
        view = view[len(view) - part.unused:]
        if not starts_frame(view):
            raise CodecError(f"zstd payload: {len(view)} bytes after the frame that are not a zstd frame")


def _decompress_zstd_frame(dctx, data, cap: int, limits: Limits) -> _Frame:
    try:
        declared = zstandard.frame_content_size(data)
    except zstandard.ZstdError as exc:
        raise CodecError(f"zstd payload: not a zstd frame ({exc})") from None
    if declared > cap:  # -1 means not declared: the bounded feed below still caps it
        raise LimitError(f"zstd payload declares {declared} bytes, over the limit of {cap}")
    dobj = dctx.decompressobj()
    frame = _zstd_bounded(dobj, data, cap, limits, "zstd payload")
    if not dobj.eof:
        raise CodecError("zstd payload: truncated frame")
    if declared >= 0 and declared != len(frame.data):
        raise CodecError(f"zstd payload: frame declares {declared} bytes but holds {len(frame.data)}")
    return frame


def _decompress_lz4_frame(data: bytes, cap: int) -> bytes:
    try:
        info = lz4.frame.get_frame_info(data)
        declared = int(info.get("content_size") or 0)
        if declared > cap:
            raise LimitError(f"lz4 payload declares {declared} bytes, over the limit of {cap}")
        dobj = lz4.frame.LZ4FrameDecompressor()
        out = dobj.decompress(data, max_length=cap + 1)
    except RuntimeError as exc:  # lz4 reports malformed frames as RuntimeError
        raise CodecError(f"lz4 payload: corrupt frame ({exc})") from None
    if len(out) > cap:
        raise LimitError(f"lz4 payload: decompressed payload exceeds the limit of {cap} bytes")
    if not dobj.eof:
        raise CodecError("lz4 payload: truncated frame")
    if dobj.unused_data:
        raise CodecError(f"lz4 payload: {len(dobj.unused_data)} bytes after the frame")
    return out


def decompress_frame(codec: Codec, data: bytes, cap: int, limits: Limits = DEFAULT_LIMITS) -> bytes:
    """Decode a per-message payload (NONE, ZSTD, LZ4), refusing more than `cap` bytes of output."""
    if codec == Codec.NONE:
        if len(data) > cap:
            raise LimitError(f"payload of {len(data)} bytes exceeds the limit of {cap}")
        return bytes(data)
    if codec == Codec.ZSTD:
        return _decompress_zstd_frames(data, cap, limits)
    if codec == Codec.LZ4:
        return _decompress_lz4_frame(data, cap)
    raise CodecError(f"codec {codec!r} needs a stream decoder")


class StreamDecompressor:
    """Client end of a ZSTD_STREAM: one decompression context, started anew by a message that begins a
    frame (the sender switched encoders)."""

    def __init__(self, limits: Limits = DEFAULT_LIMITS):
        self.limits = limits
        self._dctx = zstandard.ZstdDecompressor(max_window_size=limits.zstd_max_window_bytes)
        self._obj = self._dctx.decompressobj()
        self.messages = 0
        self.restarts = 0  # frames started after the first message

    def decompress(self, data: bytes, cap: int) -> bytes:
        if starts_frame(data) and self.messages:
            self._obj = self._dctx.decompressobj()
            self.restarts += 1
        self.messages += 1
        out = _zstd_bounded(self._obj, data, cap, self.limits, "zstd stream").data
        if self._obj.eof:  # the server never ends the frame: a finished frame is malformed input
            raise CodecError("zstd stream: frame ended; the stream must stay open for the connection")
        return out
