"""`builtin:space`: a large, mostly static scene: a ring station in an asteroid field, with a few
far-away asteroids tumbling and drifting (keyframed rigid animations). Metres; about 300 m across.

The scene is big but its surface area is moderate (a few thousand square metres), so that a bake at
N = 256 points per square metre stays around a million points; moving geometry is far from everything
else, so the server's selection (points within the AO distance of a moving instance) stays small.
"""
from __future__ import annotations

import numpy as np

from psao.scene import builtin_shapes as shapes
from psao.scene.model import Scene
from psao.scene.rigid import KeyframeAnimation, RigidKey
from psao.scene.scene_builder import SceneBuilder
from psao.scene.transforms import axis_angle_matrix, matrix_to_quat, trs

RING_RADIUS, RING_TUBE = 12.0, 1.2
HUB_RADIUS, HUB_LENGTH = 2.5, 10.0
FIELD = (25.0, 70.0)  # static asteroids: distance band from the station's centre
STATIC_ASTEROIDS = 48
MOVING = (  # (distance, radius, tumble period s, drift m, seed)
    (110.0, 3.0, 24.0, 12.0, 900), (130.0, 4.5, 36.0, 15.0, 901),
    (150.0, 2.5, 18.0, 10.0, 902), (125.0, 3.5, 30.0, 18.0, 903),
)


def space() -> Scene:
    b = SceneBuilder("space")
    hull, dark, panel = (0.75, 0.76, 0.78), (0.45, 0.46, 0.5), (0.15, 0.2, 0.45)
    b.place("hub", shapes.cylinder(HUB_RADIUS, HUB_LENGTH, sections=32), color=hull)
    b.place("ring", shapes.torus(RING_RADIUS, RING_TUBE, sections=64), color=hull)
    spoke = b.mesh("spoke", shapes.cylinder(0.5, RING_RADIUS - HUB_RADIUS, sections=12), color=dark)
    for k in range(4):  # spokes in the ring's plane (XZ), from the hub to the ring
        yaw = 45.0 + 90.0 * k
        r = (HUB_RADIUS + RING_RADIUS) / 2
        pos = (r * np.sin(np.radians(yaw)), 0.0, r * np.cos(np.radians(yaw)))
        b.instance(f"spoke{k}", spoke, trs(pos, axis_angle_matrix([0, 1, 0], np.radians(yaw)) @ _rx(90)))
    truss = b.mesh("truss", shapes.box((0.6, 14.0, 0.6)), color=dark)
    wing = b.mesh("solar_panel", shapes.box((16.0, 0.1, 4.0)), color=panel)
    for side in (-1, 1):  # a truss above and below the hub carrying two solar panels each
        y = side * (HUB_LENGTH / 2 + 7.0)
        b.instance(f"truss{side:+d}", truss, trs((0, y, 0)))
        for k, dy in enumerate((-3.5, 3.5)):
            b.instance(f"solar_panel{side:+d}_{k}", wing, trs((0, y + dy, 0)))
    module = b.mesh("module", shapes.capsule(1.0, 4.0, count=12), color=hull)
    for k, angle in enumerate((0.0, 120.0, 240.0)):  # docking modules around the hub
        a = np.radians(angle)
        b.instance(f"module{k}", module, trs((3.6 * np.cos(a), 3.6, 3.6 * np.sin(a))))
    _asteroid_field(b)
    _moving_asteroids(b)
    keys = []
    for k, a in enumerate(np.linspace(0, 2 * np.pi, 9)):  # a slow fly-around, rising and sinking
        eye = (21 * np.cos(a), 4 * np.sin(2 * a) + 6, 21 * np.sin(a))
        keys.append((k * 5.0, eye, (0.0, 0.0, 0.0)))
    b.camera("flyby", keys, fov_y=55.0)
    return b.build(ao_distance=2.0)


def _rx(deg: float) -> np.ndarray:
    return axis_angle_matrix([1, 0, 0], np.radians(deg))


def _random_direction(rng: np.random.Generator) -> np.ndarray:
    d = rng.normal(size=3)
    return d / np.linalg.norm(d)


def _asteroid_field(b: SceneBuilder) -> None:
    rng = np.random.default_rng(4242)
    placed: list[tuple[np.ndarray, float]] = []
    k = 0
    while len(placed) < STATIC_ASTEROIDS:
        radius = float(np.exp(rng.uniform(np.log(0.6), np.log(3.5))))
        d = _random_direction(rng)
        d[1] *= 0.35  # a flattened field around the ring's plane
        pos = d / np.linalg.norm(d) * rng.uniform(*FIELD)
        k += 1
        if any(np.linalg.norm(pos - p) < 1.3 * (radius + r) + 1.0 for p, r in placed):
            continue  # keep rocks apart: no interpenetration
        placed.append((pos, radius))
        n = len(placed) - 1
        geom = shapes.boulder(radius, roughness=0.25, seed=1000 + k, subdivisions=2)
        rot = axis_angle_matrix(_random_direction(rng), rng.uniform(0, 2 * np.pi))
        b.place(f"asteroid{n:02d}", geom, trs(pos, rot), color=(0.42, 0.4, 0.37))


def _moving_asteroids(b: SceneBuilder) -> None:
    """Far away, each tumbling about a random axis (three slerp keys per turn) while drifting back
    and forth along a random direction; looping keyframes."""
    for k, (dist, radius, period, drift, seed) in enumerate(MOVING):
        rng = np.random.default_rng(seed)
        d = _random_direction(rng)
        d[1] *= 0.3
        pos = d / np.linalg.norm(d) * dist
        axis, heading = _random_direction(rng), _random_direction(rng)
        keys = []
        for j in range(7):  # every 60 degrees: steps well under 180, so slerp always turns the same way
            u = j / 6
            rot = matrix_to_quat(axis_angle_matrix(axis, 2 * np.pi * u))
            offset = heading * drift * np.sin(2 * np.pi * u)
            keys.append(RigidKey(period * u, offset, rot, np.ones(3)))
        anim = KeyframeAnimation(base=trs(pos), keys=keys, loop=True)
        mesh = b.mesh(f"moving_asteroid{k}", shapes.boulder(radius, roughness=0.3, seed=seed, subdivisions=3),
                      color=(0.5, 0.45, 0.4))
        b.instance(f"moving_asteroid{k}", mesh, anim.matrix(0.0), animation=anim)
