"""Built-in scenes generated in code (`builtin:NAME`): no files, no downloads, deterministic.

Conventions: Y up, units are metres, open geometry faces the camera side. BUILTINS maps a name to a
function returning a Scene; the loader adds source = "builtin:NAME".
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from psao.scene import builtin_shapes as shapes
from psao.scene.builtin_robots import robots
from psao.scene.builtin_space import space
from psao.scene.builtin_tangle import tangle
from psao.scene.model import Scene
from psao.scene.rigid import Polyline, RollAnimation
from psao.scene.scene_builder import SceneBuilder, quad
from psao.scene.transforms import trs


# ------------------------------------------------------------------------------------------- cornell

def cornell() -> Scene:
    """The Cornell box, 1 unit: floor, ceiling, back, left (red) and right (green) walls as single-sided
    quads facing inwards; the front (z = +0.5) is open and the camera looks in through it. Two closed
    blocks stand on the floor. 34 triangles; AO distance 0.5."""
    b = SceneBuilder("cornell")
    lo, hi = -0.5, 0.5
    white, red, green = (0.73, 0.73, 0.73), (0.63, 0.065, 0.05), (0.14, 0.45, 0.09)
    b.place("floor", quad((lo, 0, lo), (lo, 0, hi), (hi, 0, hi), (hi, 0, lo)), color=white)
    b.place("ceiling", quad((lo, 1, lo), (hi, 1, lo), (hi, 1, hi), (lo, 1, hi)), color=white)
    b.place("back_wall", quad((lo, 0, lo), (hi, 0, lo), (hi, 1, lo), (lo, 1, lo)), color=white)
    b.place("left_wall", quad((lo, 0, lo), (lo, 1, lo), (lo, 1, hi), (lo, 0, hi)), color=red)
    b.place("right_wall", quad((hi, 0, lo), (hi, 0, hi), (hi, 1, hi), (hi, 1, lo)), color=green)
    b.place("tall_block", shapes.box((0.3, 0.6, 0.3)), trs((-0.17, 0.3, -0.12), (0, 17, 0)), color=white)
    b.place("short_block", shapes.box((0.3, 0.3, 0.3)), trs((0.18, 0.15, 0.12), (0, -18, 0)), color=white)
    b.camera("front", [(0.0, (0.0, 0.5, 1.9), (0.0, 0.45, 0.0)),
                       (4.0, (0.18, 0.55, 1.7), (0.0, 0.4, 0.0)),
                       (8.0, (-0.18, 0.45, 1.7), (0.0, 0.45, 0.0)),
                       (12.0, (0.0, 0.5, 1.9), (0.0, 0.45, 0.0))], fov_y=40.0)
    return b.build(ao_distance=0.5)


# ----------------------------------------------------------------------------------------- courtyard

# Courtyard layout, metres. The open court spans x in [-15, 15], z in [-7.5, 7.5] inside the outer walls;
# along both long walls runs a two-storey arcade (columns with arches) at |z| = ARCADE_Z, with a gallery
# behind it; the upper gallery has a railing between its columns. The top is open to the sky.
COURT_X, COURT_Z, WALL_H, WALL_T = 15.0, 7.5, 12.0, 0.5
ARCADE_Z = 4.5
BAY = 3.0  # column spacing
COLUMN_XS = np.arange(-12.0, 12.0 + 1e-9, BAY)
STOREYS = (  # (name, floor y, column height, arch height)
    ("ground", 0.0, 4.5, 1.8),
    ("upper", 6.3, 3.5, 1.2),
)
ARCH_DEPTH = 0.6
SLAB_T = 0.3


def courtyard() -> Scene:
    """A Sponza-like atrium about 30 x 12 x 15 m: floor, outer walls, two storeys of arcades along the long
    sides, a railing of thin bars on the upper gallery, banners (double-sided cloth) and boulders on the
    floor. Columns, arches and railing bays share one mesh per kind, placed by many instances."""
    b = SceneBuilder("courtyard")
    stone, wall, floor_c = (0.76, 0.72, 0.64), (0.70, 0.66, 0.58), (0.55, 0.52, 0.48)
    b.place("floor", shapes.box((2 * COURT_X + 2 * WALL_T, 0.3, 2 * COURT_Z + 2 * WALL_T)),
            trs((0, -0.15, 0)), color=floor_c)
    long_wall = b.mesh("long_wall", shapes.box((2 * COURT_X + 2 * WALL_T, WALL_H, WALL_T)), color=wall)
    short_wall = b.mesh("short_wall", shapes.box((WALL_T, WALL_H, 2 * COURT_Z)), color=wall)
    for side in (-1, 1):
        b.instance(f"wall_z{side:+d}", long_wall, trs((0, WALL_H / 2, side * (COURT_Z + WALL_T / 2))))
        b.instance(f"wall_x{side:+d}", short_wall, trs((side * (COURT_X + WALL_T / 2), WALL_H / 2, 0)))
    _arcades(b, stone)
    _boulders(b)
    _rolling_boulders(b)
    cloth = b.mesh("banner", shapes.cloth((1.2, 3.0), subdivisions=8, sag=0.12), color=(0.55, 0.12, 0.1),
                   double_sided=True)
    arch_front = ARCADE_Z - ARCH_DEPTH / 2 - 0.02
    for k, x in enumerate((-7.5, 7.5)):
        for side in (-1, 1):  # hung from the ground-storey arches, facing the court
            b.instance(f"banner{k}_z{side:+d}", cloth, trs((x, 6.2, side * arch_front), (0, 90 + side * 90, 0)))
    keys = []
    for k, a in enumerate(np.linspace(0, 2 * np.pi, 9)):  # an elliptic walk, looking across the court
        eye = (9.0 * np.cos(a), 1.7, 3.2 * np.sin(a))
        ahead = a + 0.9
        target = (6.0 * np.cos(ahead), 2.6, 2.0 * np.sin(ahead))
        keys.append((k * 1.25, eye, target))
    b.camera("walk", keys, fov_y=65.0)
    return b.build(ao_distance=1.5)


def _arcades(b: SceneBuilder, color) -> None:
    inner_slab_z = ARCADE_Z + ARCH_DEPTH / 2  # galleries: from behind the arches to the wall
    slab_depth = COURT_Z - inner_slab_z
    slab = b.mesh("gallery_slab", shapes.box((2 * COURT_X, SLAB_T, slab_depth)), color=color)
    rail = b.mesh("railing", shapes.railing(BAY - 0.8, 1.0, bar_spacing=0.12, bar_size=0.03), color=color)
    bay_xs = (COLUMN_XS[:-1] + COLUMN_XS[1:]) / 2
    for name, y0, col_h, arch_h in STOREYS:
        col = b.mesh(f"column_{name}", shapes.column(0.3, col_h), color=color)
        arc = b.mesh(f"arch_{name}", shapes.arch(BAY, arch_h, ARCH_DEPTH, span=BAY - 0.8, segments=16),
                     color=color)
        top = y0 + col_h + arch_h
        for side in (-1, 1):
            z = side * ARCADE_Z
            for i, x in enumerate(COLUMN_XS):
                b.instance(f"column_{name}_z{side:+d}_{i:02d}", col, trs((x, y0, z)))
            for i, x in enumerate(bay_xs):
                b.instance(f"arch_{name}_z{side:+d}_{i:02d}", arc, trs((x, y0 + col_h, z)))
                if name == "upper":
                    b.instance(f"railing_z{side:+d}_{i:02d}", rail, trs((x, y0, z)))
            # the gallery above this storey: floor of the next one, or the roof
            b.instance(f"slab_{name}_z{side:+d}", slab,
                       trs((0, top - SLAB_T / 2, side * (inner_slab_z + slab_depth / 2))))


BOULDERS = (  # (x, z, radius, yaw degrees)
    (-9.5, -1.5, 1.1, 20), (-4.0, 2.0, 0.6, 75), (-1.0, -2.5, 0.8, 140),
    (3.5, 1.0, 1.2, 200), (7.0, -2.0, 0.5, 260), (10.5, 2.2, 0.9, 310),
)


def boulder_on_floor(seed: int, radius: float) -> shapes.Geometry:
    """A boulder mesh shifted so that it rests on y = 0 (sunk 2% of its radius so it touches the floor)."""
    v, f = shapes.boulder(radius, roughness=0.18, seed=seed, subdivisions=3)
    v = v.copy()
    v[:, 1] -= v[:, 1].min() + 0.02 * radius
    return v, f


def _boulders(b: SceneBuilder) -> None:
    for k, (x, z, radius, yaw) in enumerate(BOULDERS):
        b.place(f"boulder{k}", boulder_on_floor(100 + k, radius), trs((x, 0, z), (0, yaw, 0)),
                color=(0.45, 0.42, 0.38))


ROLLING = (  # (radius, seed, centre path on the floor [(x, z), ...], closed loop (else there and back), speed m/s)
    # lanes kept clear of the static boulders and the columns (|z| + radius < 4.1)
    (0.55, 200, [(-14.0, -3.0), (-11.8, -3.0), (-11.8, 3.0), (-14.0, 3.0)], True, 0.9),
    (0.7, 201, [(-8.0, 3.35), (8.0, 3.35)], False, 1.2),
    (0.5, 202, [(12.0, -3.0), (14.0, -3.0), (14.0, 3.0), (12.0, 3.0)], True, 0.7),
)


def _rolling_boulders(b: SceneBuilder) -> None:
    """Round boulders rolling without slipping on the floor (RigidAnimation kind "roll")."""
    for k, (radius, seed, path, closed, speed) in enumerate(ROLLING):
        mesh = b.mesh(f"rolling_boulder{k}", shapes.boulder(radius, roughness=0.05, seed=seed, subdivisions=3,
                                                           squash=False), color=(0.5, 0.44, 0.36))
        centre = np.array([[x, radius, z] for x, z in path])
        base = trs(centre[0])
        anim = RollAnimation(base=base, path=Polyline(centre, closed=closed), speed=speed, radius=radius)
        b.instance(f"rolling_boulder{k}", mesh, anim.matrix(0.0), animation=anim)


BUILTINS: dict[str, Callable[[], Scene]] = {
    "cornell": cornell,
    "courtyard": courtyard,
    "space": space,
    "robots": robots,
    "tangle": tangle,
}
