"""Size limits of the wire protocol, checked before anything is allocated or decompressed.

Both ends use the same numbers: the server bounds what a client may send (tiny: handshake, camera,
scene edits) and what it puts in one message (it splits big updates and keeps the rest pending); the
client bounds what it accepts from a server. Every count read from a payload is checked against these
before an array of that size is created.
"""
from __future__ import annotations

from dataclasses import dataclass

HEADER_SIZE = 12  # bytes, see psao.protocol.messages.HEADER


@dataclass(frozen=True)
class Limits:
    # Client -> server (Hello, Camera, SceneEdit, Bye): small by nature.
    client_message_bytes: int = 64 * 1024  # whole websocket message, header included
    client_payload_bytes: int = 64 * 1024  # payload after decompression
    token_bytes: int = 256
    # Server -> client.
    server_message_bytes: int = 48 * 1024 * 1024  # whole websocket message, compressed
    server_payload_bytes: int = 64 * 1024 * 1024  # payload after decompression
    error_text_bytes: int = 1024
    # Grid sizes a client accepts (memory it will allocate for the mirror).
    max_instances: int = 1 << 16
    max_buckets: int = 1 << 24  # 64 B each (8 entries x 2 uint32): 1 GiB of buckets at most
    max_cell_capacity: int = 1 << 24  # 32 B each (CELL_WORDS uint32): 512 MiB of cells at most
    # SceneEdit transforms a server accepts: affine, each axis scaled within [1/max, max], the origin
    # moved at most this far (world units) from the world origin.
    edit_max_scale: float = 1e3
    edit_max_translation: float = 1e6
    # A client's mirror grows as data arrives: at most base + per_byte x bytes received so far, whatever a
    # Welcome or Snapshot claims (a legitimate snapshot carries roughly 1 byte per 8-30 bytes of table).
    mirror_base_bytes: int = 64 * 1024 * 1024
    mirror_bytes_per_received_byte: int = 256
    # What the server puts into one Update or Snapshot chunk; the rest stays pending for the next one.
    max_cells_per_message: int = 1 << 16
    max_buckets_per_message: int = 1 << 16
    max_snapshot_chunks: int = 1 << 16
    # The scene (SceneData): one zstd frame of psao.protocol.scenefile bytes, sent in chunks.
    scene_bytes: int = 256 * 1024 * 1024  # compressed, all chunks together
    scene_payload_bytes: int = 1024 * 1024 * 1024  # the decompressed scene file
    scene_chunk_bytes: int = 1024 * 1024  # what the server puts into one SceneData message
    max_scene_meshes: int = 1 << 16  # meshes, and camera paths
    max_scene_vertices: int = 1 << 26  # per mesh
    max_scene_faces: int = 1 << 26  # per mesh
    max_skin_samples: int = 1 << 14  # sampled poses per skin
    max_scene_camera_keys: int = 1 << 16
    # Decompression: input is fed in pieces whose output cannot pass the cap, and near it in pieces this
    # small, so the output overshoots a cap by at most (piece / 4 + 1) * 128 KiB (a zstd RLE block is 4
    # bytes for 128 KiB) before the cap check stops it.
    decompress_piece_bytes: int = 128
    zstd_max_window_bytes: int = 1 << 24


DEFAULT_LIMITS = Limits()
