"""Mesh generators shared by the built-in scenes and TOML `generator = "..."` meshes.

Every generator returns (vertices (V, 3) float64, faces (F, 3) int64), Y up, closed and outward-facing
unless it says otherwise (`plane` is a single open quad grid facing +Y). Shapes are centred on the
origin except where noted (`column`, `arch` and `railing` stand on y = 0, like building parts).
Parameters are keyword arguments in scene units; GENERATORS maps the TOML name to the function.
"""
from __future__ import annotations

import numpy as np
import trimesh

Geometry = tuple[np.ndarray, np.ndarray]


def _rot_x(deg: float) -> np.ndarray:
    return trimesh.transformations.rotation_matrix(np.radians(deg), [1, 0, 0])


def _geom(m: trimesh.Trimesh, transform: np.ndarray | None = None) -> Geometry:
    v = np.asarray(m.vertices, dtype=np.float64)
    if transform is not None:
        v = v @ transform[:3, :3].T + transform[:3, 3]
    return v, np.asarray(m.faces, dtype=np.int64)


def transformed(geom: Geometry, translate=(0, 0, 0), scale=(1, 1, 1)) -> Geometry:
    v, f = geom
    return v * np.asarray(scale, dtype=np.float64) + np.asarray(translate, dtype=np.float64), f


def combine(parts: list[Geometry]) -> Geometry:
    verts, faces, offset = [], [], 0
    for v, f in parts:
        verts.append(v)
        faces.append(f + offset)
        offset += len(v)
    return np.concatenate(verts), np.concatenate(faces)


def box(size=(1.0, 1.0, 1.0)) -> Geometry:
    return _geom(trimesh.creation.box(extents=np.asarray(size, dtype=np.float64)))


def plane(size=(1.0, 1.0), subdivisions: int = 1) -> Geometry:
    """Open quad grid in XZ facing +Y, `subdivisions` quads per side."""
    n = int(subdivisions)
    xs = np.linspace(-size[0] / 2, size[0] / 2, n + 1)
    zs = np.linspace(-size[1] / 2, size[1] / 2, n + 1)
    gx, gz = np.meshgrid(xs, zs, indexing="ij")
    v = np.stack([gx.ravel(), np.zeros(gx.size), gz.ravel()], axis=1)
    i, k = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a = (i * (n + 1) + k).ravel()
    b, c, d = a + (n + 1), a + (n + 1) + 1, a + 1
    # (a, d, c) and (a, c, b): counter-clockwise seen from +Y
    f = np.concatenate([np.stack([a, d, c], 1), np.stack([a, c, b], 1)])
    return v, f.astype(np.int64)


def sphere(radius: float = 1.0, subdivisions: int = 2) -> Geometry:
    return _geom(trimesh.creation.icosphere(subdivisions=int(subdivisions), radius=radius))


def cylinder(radius: float = 0.5, height: float = 1.0, sections: int = 24) -> Geometry:
    """Axis along Y, centred."""
    return _geom(trimesh.creation.cylinder(radius=radius, height=height, sections=int(sections)), _rot_x(-90))


def cone(radius: float = 0.5, height: float = 1.0, sections: int = 24) -> Geometry:
    """Base at y = 0, apex at y = height."""
    return _geom(trimesh.creation.cone(radius=radius, height=height, sections=int(sections)), _rot_x(-90))


def capsule(radius: float = 0.5, height: float = 1.0, count: int = 12) -> Geometry:
    """Axis along Y, centred; `height` is the distance between the two hemisphere centres."""
    return _geom(trimesh.creation.capsule(height=height, radius=radius, count=[int(count), int(count)]),
                 _rot_x(-90))


def torus(major_radius: float = 1.0, minor_radius: float = 0.25, sections: int = 32) -> Geometry:
    """In the XZ plane (axis Y)."""
    m = trimesh.creation.torus(major_radius=major_radius, minor_radius=minor_radius,
                               major_sections=int(sections), minor_sections=max(8, int(sections) // 2))
    return _geom(m, _rot_x(-90))


def boulder(radius: float = 1.0, roughness: float = 0.2, seed: int = 0, subdivisions: int = 3,
            squash: bool = True) -> Geometry:
    """Icosphere with a seeded smooth radial noise: a rock. The noise is a sum of random low-order
    cosine waves over the sphere, so it is smooth and the same for a given seed on every machine.
    squash=False keeps it round (a rock that rolls)."""
    v, f = sphere(1.0, subdivisions)
    rng = np.random.default_rng(int(seed))
    dirs = rng.normal(size=(12, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    freq = rng.uniform(1.0, 3.5, size=12)
    phase = rng.uniform(0, 2 * np.pi, size=12)
    amp = rng.uniform(0.5, 1.0, size=12) / freq
    noise = (amp * np.cos(v @ dirs.T * freq + phase)).sum(axis=1)
    noise /= np.abs(noise).max()
    flat = np.array([1.0, rng.uniform(0.6, 0.85), rng.uniform(0.8, 1.0)])  # rocks are flatter than balls
    return v * (radius * (1.0 + roughness * noise))[:, None] * (flat if squash else 1.0), f


def tube(radius: float = 0.1, length: float = 1.0, rings: int = 8, sections: int = 12) -> Geometry:
    """Closed cylinder along Y from y = 0 down to y = -length with `rings` intermediate vertex rings
    (so that it can bend when skinned), flat caps."""
    n, k = int(sections), int(rings) + 2
    ang = 2 * np.pi * np.arange(n) / n
    ys = np.linspace(0.0, -length, k)
    side = np.stack([np.tile(radius * np.cos(ang), k), np.repeat(ys, n), np.tile(-radius * np.sin(ang), k)], 1)
    v = np.vstack([side, [[0, 0, 0], [0, -length, 0]]])
    top, bottom = len(side), len(side) + 1
    faces = []
    for r in range(k - 1):
        a = r * n + np.arange(n)
        b = r * n + (np.arange(n) + 1) % n
        faces += [np.stack([a, a + n, b], 1), np.stack([b, a + n, b + n], 1)]
    ring0, ringk = np.arange(n), (k - 1) * n + np.arange(n)
    faces.append(np.stack([np.full(n, top), ring0, (ring0 + 1) % n], 1))
    faces.append(np.stack([np.full(n, bottom), (k - 1) * n + (np.arange(n) + 1) % n, ringk], 1))
    return v, np.concatenate(faces).astype(np.int64)


def column(radius: float = 0.3, height: float = 4.0, sections: int = 16) -> Geometry:
    """Square plinth, round shaft, square capital; stands on y = 0, top at y = height."""
    plinth_h, cap_h = 0.08 * height, 0.07 * height
    side = 2.6 * radius
    shaft_h = height - plinth_h - cap_h
    return combine([
        transformed(box((side, plinth_h, side)), (0, plinth_h / 2, 0)),
        transformed(cylinder(radius, shaft_h, sections), (0, plinth_h + shaft_h / 2, 0)),
        transformed(box((side, cap_h, side)), (0, height - cap_h / 2, 0)),
    ])


def arch(width: float = 3.0, height: float = 1.5, depth: float = 0.6, span: float = 2.4,
         spring: float = 0.0, segments: int = 16) -> Geometry:
    """A wall block width x height x depth (x, y, z), standing on y = 0, with a round-arched opening of
    width `span` cut from below: straight jambs up to y = `spring`, then a semicircle of radius span/2.
    Set on top of two columns (spring = 0) it makes an arcade bay. Closed solid."""
    r, hw = span / 2, width / 2
    if not (0 < r < hw and spring + r < height):
        raise ValueError("arch: need 0 < span < width and spring + span/2 < height")
    # The part above the spring line is a radial quad strip between the semicircle and the outer
    # rectangle, seen from the arc centre (0, spring); the corners of the rectangle are strip samples so
    # every outer edge is straight.
    corner = np.arctan2(height - spring, hw)
    angles = np.unique(np.concatenate([np.linspace(0, np.pi, segments + 1), [corner, np.pi - corner]]))
    d = np.stack([np.cos(angles), np.sin(angles)], 1)
    inner = d * r + [0, spring]
    t = np.minimum(np.where(np.abs(d[:, 0]) > 1e-12, hw / np.maximum(np.abs(d[:, 0]), 1e-12), np.inf),
                   np.where(d[:, 1] > 1e-12, (height - spring) / np.maximum(d[:, 1], 1e-12), np.inf))
    outer = d * t[:, None] + [0, spring]
    pts = [*inner, *outer]
    n = len(angles)
    tris = []
    for k in range(n - 1):
        tris += [(k, n + k, n + k + 1), (k, n + k + 1, k + 1)]
    if spring > 0:  # the jambs below the spring line: one quad each side
        base = len(pts)
        pts += [(r, 0), (hw, 0), (-hw, 0), (-r, 0)]
        tris += [(base, base + 1, n), (base, n, 0)]  # right: (r,0) (hw,0) (hw,s) (r,s)
        tris += [(base + 3, n - 1, 2 * n - 1), (base + 3, 2 * n - 1, base + 2)]  # left
    v2 = np.asarray(pts, dtype=np.float64)
    f2 = np.asarray(tris, dtype=np.int64)
    # the strip triangles above were written clockwise or counter-clockwise depending on k; orient all CCW
    a, b, c = v2[f2[:, 0]], v2[f2[:, 1]], v2[f2[:, 2]]
    cw = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]) < 0
    f2[cw] = f2[cw][:, ::-1]
    m = trimesh.creation.extrude_triangulation(v2, f2, depth)
    v, f = _geom(m)
    v[:, 2] -= depth / 2
    return v, f


def railing(length: float = 3.0, height: float = 1.0, bar_spacing: float = 0.15, bar_size: float = 0.03,
            rail_size: float = 0.06) -> Geometry:
    """Handrail and bottom rail along X on thin square bars; stands on y = 0, centred in x and z.
    Every part is a closed box (thin, but closed: no double-sided surfaces needed)."""
    bars = max(1, int(np.floor(length / bar_spacing)))
    xs = (np.arange(bars) + 0.5) * (length / bars) - length / 2
    bar_h = height - 2 * rail_size
    parts = [transformed(box((length, rail_size, rail_size * 1.5)), (0, height - rail_size / 2, 0)),
             transformed(box((length, rail_size, rail_size)), (0, rail_size / 2, 0))]
    parts += [transformed(box((bar_size, bar_h, bar_size)), (x, rail_size + bar_h / 2, 0)) for x in xs]
    return combine(parts)


def cloth(size=(1.0, 2.0), subdivisions: int = 8, sag: float = 0.1) -> Geometry:
    """A hanging banner in the XY plane facing +Z, top edge at y = 0, gently bulged: an open thin
    surface, to be used double-sided."""
    v, f = plane((size[0], size[1]), subdivisions)
    x, z = v[:, 0], v[:, 2]
    u = (z + size[1] / 2) / size[1]  # 0 at the top edge, 1 at the bottom
    bulge = sag * np.sin(np.pi * u) * np.cos(np.pi * x / size[0])
    # plane faces +Y with z running down the banner: map (x, 0, z) -> (x, -z', bulge) facing +Z
    return np.stack([x, -u * size[1], bulge], 1), f


GENERATORS = {
    "box": box, "plane": plane, "sphere": sphere, "cylinder": cylinder, "cone": cone, "capsule": capsule,
    "torus": torus, "boulder": boulder, "column": column, "arch": arch, "railing": railing, "cloth": cloth,
    "tube": tube,
}
