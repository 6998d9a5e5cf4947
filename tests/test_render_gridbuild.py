"""Test support for the renderer tests: synthetic scenes and a small grid builder of our own.

The builder follows src/psao/protocol/gridformat.py (keys, wrapping hash, buckets with used entries first,
cells with allocated words first, overflow dropped) without importing the server, so renderer tests
run before and independently of the lead's bake. Its own tests check it against gridformat's helpers.
"""
from __future__ import annotations

import numpy as np

from psao.protocol import gridformat as gf
from psao.protocol import pointword as pw
from psao.scene.model import Instance, Mesh, Scene


def box_mesh(name, lo, hi, color=(0.8, 0.8, 0.8), inward=False):
    """Axis-aligned box, 12 outward-facing triangles (inward=True flips them: a room)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    v = np.array([[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1]) for x in (lo[0], hi[0])])
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    faces = []
    for a, b, c, d in quads:
        faces += [(a, b, c), (a, c, d)]
    f = np.array(faces, dtype=np.int64)
    if inward:
        f = f[:, ::-1]
    return Mesh(name=name, vertices=v, faces=f, color=color)


def plane_mesh(name, size=4.0, color=(0.7, 0.7, 0.7)):
    """Square in y = 0, normal +y."""
    s = size / 2
    v = np.array([[-s, 0, -s], [s, 0, -s], [s, 0, s], [-s, 0, s]], dtype=float)
    return Mesh(name=name, vertices=v, faces=np.array([[0, 2, 1], [0, 3, 2]], dtype=np.int64), color=color)


def translate(x, y, z):
    m = np.eye(4)
    m[:3, 3] = (x, y, z)
    return m


def floor_and_box_scene(ao_distance=0.6):
    """A 4x4 floor with a unit box on it (instance 1 moved by a transform): contact occlusion."""
    meshes = [plane_mesh("floor"), box_mesh("box", (-0.5, 0, -0.5), (0.5, 1, 0.5), color=(0.8, 0.5, 0.3))]
    instances = [Instance("floor", 0, np.eye(4)), Instance("box", 1, translate(0.3, 0.0, -0.2))]
    return Scene("floor_box", meshes, instances, ao_distance=ao_distance)


def sample_surface(mesh, spacing, rng):
    """Points on every triangle of the mesh (about one per spacing^2), with face normals."""
    a, b, c = (mesh.vertices[mesh.faces[:, i]] for i in range(3))
    n = np.cross(b - a, c - a)
    area = 0.5 * np.linalg.norm(n, axis=1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    counts = np.maximum(1, np.round(area / spacing**2)).astype(int)
    tri = np.repeat(np.arange(len(a)), counts)
    u, v = rng.random(len(tri)), rng.random(len(tri))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    pts = a[tri] + u[:, None] * (b[tri] - a[tri]) + v[:, None] * (c[tri] - a[tri])
    return pts, n[tri]


def build_grid(pointsets, cell_size, radius, bucket_factor=4.0):
    """pointsets: per instance (local_pos (P,3), normals (P,3), ao_code (P,)). -> instances, buckets, cells."""
    records = np.zeros(len(pointsets), dtype=gf.INSTANCE_DTYPE)
    all_buckets, all_cells = [], []
    bucket_offset = 0
    for i, (pos, nrm, ao) in enumerate(pointsets):
        pos = np.asarray(pos, float)
        lo, hi = pos.min(axis=0) - cell_size, pos.max(axis=0) + cell_size
        dims = np.maximum(np.ceil((hi - lo) / cell_size).astype(int), 1)
        n_cells_est = len(np.unique(np.floor((pos - lo) / cell_size).astype(int), axis=0))
        count = gf.next_pow2(max(1, int(bucket_factor * n_cells_est / gf.BUCKET_ENTRIES)))
        records[i] = (lo.astype(np.float32), cell_size, dims, bucket_offset, count, radius, 0, 0)
        origin = records[i]["origin"]
        g = gf.grid_coords(pos, origin, cell_size)
        cell = np.clip(np.floor(g).astype(np.int64), 0, dims - 1)
        frac = g - cell
        words = pw.pack_point(pw.quantise_cell_fraction(frac), pw.oct_encode(nrm), ao)
        buckets = np.tile(gf.EMPTY_BUCKET, (count, 1, 1))
        slot_of_key: dict[int, int] = {}
        keys = gf.cell_key(cell[:, 0], cell[:, 1], cell[:, 2], dims)
        bidx = gf.bucket_index(cell[:, 0], cell[:, 1], cell[:, 2], dims, 0, count)
        for key, b, w in zip(keys.tolist(), bidx.tolist(), words.tolist()):
            if key not in slot_of_key:
                used = int(np.sum(buckets[b, :, 0] != gf.EMPTY))
                if used == gf.BUCKET_ENTRIES:
                    continue  # bucket overflow: dropped, as the paper does
                slot = len(all_cells)
                buckets[b, used] = (key, slot)
                cell_row = gf.FREE_CELL.copy()
                cell_row[gf.KEY_WORD] = key
                all_cells.append(cell_row)
                slot_of_key[key] = slot
            row = all_cells[slot_of_key[key]]
            free = np.nonzero(row[: gf.POINTS_PER_CELL] == 0)[0]
            if free.size:
                row[free[0]] = w  # cell overflow beyond 7 points: dropped
        all_buckets.append(buckets)
        bucket_offset += count
    cells = np.array(all_cells, dtype=np.uint32).reshape(-1, gf.CELL_WORDS)
    return records, np.concatenate(all_buckets).astype(np.uint32), cells


def synthetic_ao(local_pos, box_center_local, box_half):
    """A smooth, position-dependent AO code field (darker near the box) for tests."""
    d = np.linalg.norm(np.maximum(np.abs(local_pos - box_center_local) - box_half, 0.0), axis=1)
    return pw.quantise_ao(0.25 + 0.75 * np.clip(d / 0.6, 0, 1))


def floor_box_grid(scene, spacing=0.05, seed=0):
    """Grid for floor_and_box_scene: points on both meshes, AO darker near the box (in floor space)."""
    rng = np.random.default_rng(seed)
    box_t = scene.instances[1].transform
    sets = []
    for inst in scene.instances:
        mesh = scene.meshes[inst.mesh]
        pts, nrm = sample_surface(mesh, spacing, rng)
        world = pts @ inst.transform[:3, :3].T + inst.transform[:3, 3]
        ao = synthetic_ao(world, box_t[:3, 3] + [0, 0.5, 0], np.array([0.5, 0.5, 0.5]))
        sets.append((pts, nrm, ao))
    radius = 2.0 * spacing
    return build_grid(sets, cell_size=2.0 * radius, radius=radius)


def test_builder_cells_are_findable_and_points_decode_near_their_source():
    scene = floor_and_box_scene()
    inst, buckets, cells = floor_box_grid(scene)
    for rec in inst:
        lo = rec["bucket_offset"]
        for b in range(lo, lo + rec["bucket_count"]):
            entries = buckets[b]
            used = entries[:, 0] != gf.EMPTY
            assert not np.any(used[1:] & ~used[:-1])  # used entries first
            for key, slot in entries[used]:
                xyz = gf.key_to_cell(key, rec["dims"])
                assert gf.bucket_index(*xyz, rec["dims"], lo, rec["bucket_count"]) == b
                assert cells[slot, gf.KEY_WORD] == key
    alloc = (cells[:, :7] & pw.ALLOCATED_BIT) != 0
    assert not np.any(alloc[:, 1:] & ~alloc[:, :-1])  # allocated words first
    assert alloc.sum() > 1000


def server_grid(scene, density, seed=0, rays=16):
    """Grid of a real scene through the server's own pipeline (tests may import the server): the lead's
    bake (points, grid, traced AO) when it is there, else the server's point generation and Grid with a
    smooth synthetic AO field, enough to test that shader and oracle agree."""
    try:
        from psao.server.bake import bake_scene
        from psao.server.settings import BakeSettings
    except ImportError:
        return _synthetic_server_grid(scene, density, seed)
    result = bake_scene(scene, BakeSettings(density=density, rays=rays, seed=seed), show_progress=False)
    result.tracer.close()
    result.grid.take_dirty()
    return result.grid


def _synthetic_server_grid(scene, density, seed):
    from psao.server.grid import Grid
    from psao.server.points.generate import generate_points, instance_seed
    from psao.server.settings import PointSettings

    settings = PointSettings(density=density, seed=seed)
    sets = [generate_points(scene.meshes[i.mesh], i.transform, settings, seed=instance_seed(seed, k))
            for k, i in enumerate(scene.instances)]
    grid = Grid.build([(p.positions, p.normals, p.poisson_radius, 0) for p in sets])
    table = grid.point_table()
    field = 0.5 + 0.5 * np.sin(7.0 * table.local_pos[:, 0] + 3.0 * table.local_pos[:, 1]) * np.cos(5.0 * table.local_pos[:, 2])
    grid.set_ao(table.slot, table.index, pw.quantise_ao(field))
    grid.take_dirty()
    return grid
