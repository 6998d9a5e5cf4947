"""`builtin:tangle`: a skinned character built to be hard for the point grid, on a floor beside a thin wall.

The character is the robots' skeleton and walk cycle (walking in place) dressed in thin boxes and spheres
that pass through each other, as downloaded characters are: 2 cm armour plates through the torso and the
limbs, spheres through the plates at the joints, a thin hat brim through the head, a flat belt through the
pelvis. Many surfaces cross in one grid cell, surfaces lie millimetres from others they do not belong to,
and thin parts have two faces close together. Beside it stands a 2 cm wall (one side in a corner, the other
open) and a sphere pushed halfway through a slab: the two places where a surface could take AO from a
neighbour it does not belong to. Metres; Y up.
"""
from __future__ import annotations

import numpy as np

from psao.scene import builtin_shapes as shapes
from psao.scene.builtin_robots import JOINT, SKELETON, WalkCycle, two_joint
from psao.scene.meshfile import clean_geometry
from psao.scene.model import Mesh, Scene
from psao.scene.scene_builder import SceneBuilder
from psao.scene.skin import Skin
from psao.scene.transforms import trs

PLATE = 0.02  # thickness of the armour plates and the wall, metres


def tangle_parts() -> list[tuple[shapes.Geometry, np.ndarray, np.ndarray]]:
    """(geometry, joints, weights) of each part of the character in its rest pose."""
    parts = []

    def add(geom, upper, lower=None, y_from=0.0, y_to=1.0):
        jw = two_joint(geom[0], upper, upper if lower is None else lower, y_from, y_to)
        parts.append((geom, *jw))

    chest, pelvis, head = JOINT["chest"], JOINT["pelvis"], JOINT["head"]
    # torso: a box with a front and a back plate through it, and a crossing side plate
    add(shapes.transformed(shapes.box((0.34, 0.5, 0.2)), (0, 1.15, 0)), chest, pelvis, 0.95, 1.2)
    for z in (-0.09, 0.09):
        add(shapes.transformed(shapes.box((0.42, 0.4, PLATE)), (0, 1.2, z)), chest)
    add(shapes.transformed(shapes.box((PLATE, 0.36, 0.3)), (0, 1.18, 0)), chest)
    add(shapes.transformed(shapes.box((0.46, 0.05, 0.3)), (0, 0.93, 0)), pelvis)  # belt through the pelvis
    # head: a sphere with a thin brim through it and a sphere through the brim
    add(shapes.transformed(shapes.sphere(0.13, 2), (0, 1.6, 0)), head)
    add(shapes.transformed(shapes.box((0.4, PLATE, 0.4)), (0, 1.66, 0)), head)
    add(shapes.transformed(shapes.sphere(0.05, 1), (0, 1.66, 0.16)), head)
    for side, hip, knee in ((1, "hip_l", "knee_l"), (-1, "hip_r", "knee_r")):
        x = 0.10 * side
        add(shapes.transformed(shapes.box((0.1, 0.82, 0.1)), (x, 0.49, 0)), JOINT[hip], JOINT[knee], 0.42, 0.54)
        add(shapes.transformed(shapes.box((0.16, 0.3, PLATE)), (x, 0.7, 0.05)), JOINT[hip])  # thigh plate
        add(shapes.transformed(shapes.box((PLATE, 0.3, 0.16)), (x, 0.25, 0)), JOINT[knee])  # shin fin
        add(shapes.transformed(shapes.sphere(0.08, 2), (x, 0.48, 0.02)), JOINT[knee])  # knee ball through both
        add(shapes.transformed(shapes.box((0.12, 0.04, 0.26)), (x, 0.02, 0.05)), JOINT[knee])
    for side, shoulder, elbow in ((1, "shoulder_l", "elbow_l"), (-1, "shoulder_r", "elbow_r")):
        x = 0.27 * side
        add(shapes.transformed(shapes.box((0.07, 0.55, 0.07)), (x, 1.125, 0)), JOINT[shoulder], JOINT[elbow], 1.04, 1.16)
        add(shapes.transformed(shapes.sphere(0.09, 2), (x, 1.38, 0)), JOINT[shoulder])  # shoulder ball in the torso plates
        add(shapes.transformed(shapes.box((0.14, PLATE, 0.14)), (x, 1.3, 0)), JOINT[shoulder])  # pauldron
        add(shapes.transformed(shapes.sphere(0.055, 1), (x, 1.1, 0)), JOINT[elbow])
    return parts


def tangle_mesh(walk: WalkCycle) -> Mesh:
    parts = tangle_parts()
    v, f = shapes.combine([p[0] for p in parts])
    joints = np.concatenate([p[1] for p in parts])
    weights = np.concatenate([p[2] for p in parts])
    r = clean_geometry(v, f, "builtin:tangle: mesh 'character'", merge=False)  # parts cross, never merge
    inverse_bind = np.tile(np.eye(4), (len(SKELETON), 1, 1))
    inverse_bind[:, :3, 3] = -walk.rest  # bind pose = rest pose: joints are pure translations
    skin = Skin(inverse_bind=inverse_bind, joints=joints[r.source_vertex], weights=weights[r.source_vertex],
                animator=walk, joint_names=[n for n, _, _ in SKELETON])
    return Mesh(name="character", vertices=r.vertices, faces=r.faces, color=(0.7, 0.6, 0.5), skin=skin)


def tangle() -> Scene:
    b = SceneBuilder("tangle")
    b.place("floor", shapes.box((6.0, 0.1, 6.0)), trs((0, -0.05, 0)), color=(0.5, 0.5, 0.52))
    b.place("corner_wall", shapes.box((2.0, 1.6, 0.3)), trs((1.6, 0.8, -1.6)), color=(0.75, 0.75, 0.72))
    b.place("thin_wall", shapes.box((PLATE, 1.4, 1.6)), trs((0.9, 0.7, -0.9)), color=(0.75, 0.75, 0.72))
    b.place("slab", shapes.box((1.0, PLATE * 2, 1.0)), trs((-1.4, 0.5, -1.0)), color=(0.6, 0.55, 0.5))
    b.place("ball_through_slab", shapes.sphere(0.3, 3), trs((-1.4, 0.5, -1.0)), color=(0.8, 0.3, 0.2))
    mesh = len(b.meshes)
    b.meshes.append(tangle_mesh(WalkCycle(frequency=0.6)))
    b.instance("character", mesh, trs((0.0, 0.0, 0.3)))
    b.camera("around", [(0.0, (2.6, 1.6, 2.6), (-0.2, 0.8, -0.4)), (6.0, (-2.6, 1.8, 2.4), (-0.2, 0.8, -0.4)),
                        (12.0, (0.3, 2.2, 3.2), (-0.2, 0.7, -0.4)), (18.0, (2.6, 1.6, 2.6), (-0.2, 0.8, -0.4))],
             fov_y=55.0)
    return b.build(ao_distance=0.5)
