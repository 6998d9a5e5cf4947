"""TOML scene files (examples in src/psao/scene/scenes/, loadable as `builtin:NAME`).

Schema (every table is checked: an unknown key, a wrong type or a bad value is a SceneFormatError
naming the file and the element):

    [scene]
    name = "pavilion"            # default: the file's stem
    ao_distance = 1.0            # world units, > 0; default: 0.1 x the scene's bounding-box diagonal, and
                                 #   then each [[instance]] is sampled at its own size: at the default
                                 #   density of an AO distance of 0.4 x its own diagonal (at most the
                                 #   scene's AO distance; model.OBJECT_SAMPLING_FRACTION)
    root = "../assets"           # the folder mesh `path`s are relative to and must stay inside, itself
                                 #   relative to this TOML file; default: the TOML file's folder. A root
                                 #   that is not a folder is a SceneNotFound (files absent: one line)

    [[mesh]]                     # one per mesh; names unique
    name = "floor"
    generator = "box"            # one of builtin_shapes.GENERATORS: box, plane, sphere, cylinder, cone,
    size = [10.0, 0.2, 10.0]     #   capsule, torus, boulder, column, arch, railing, cloth; its keyword
                                 #   parameters are given as keys of this table (e.g. radius, height)
    # path = "meshes/statue.glb" # instead of generator: a mesh file, relative to the scene root (above),
                                 #   inside it; a file without skins has all its nodes baked into this
                                 #   one mesh. A skinned glTF (a character: any number of meshes,
                                 #   primitives and skins) keeps the file's meshes and instances as
                                 #   load_mesh_file gives them: each [[instance]] of it places every
                                 #   part, its transform (and rigid animation) applied to the whole
                                 #   character. Parts are named "MESH/PART" (meshes) and
                                 #   "INSTANCE/PART" (instances) when the file has more than one.
    # animation = "Walk"         #   The glTF animation to play (name or index, default 0: the first) and
    # animation_offset = 0.5     #   a time offset in seconds (characters out of step)
    double_sided = false         # true only for thin open surfaces (cloth, leaves)
    color = [0.8, 0.8, 0.8]      # linear RGB albedo, each in [0, 1]

    [[instance]]                 # one per placed mesh; names unique
    name = "floor"
    mesh = "floor"               # a [[mesh]] name
    translate = [0.0, -0.1, 0.0]
    rotate = [0.0, 45.0, 0.0]    # degrees about X, then Y, then Z (fixed axes), or
                                 #   rotate = { axis = [0, 1, 0], angle = 45.0 } (degrees)
    scale = 1.0                  # > 0, a number or [sx, sy, sz] (negative mirrors, zero is an error)
    [instance.animation]         # optional: a rigid motion (src/psao/scene/rigid.py); the instance's
    kind = "roll"                #   translate/rotate/scale above is its rest pose. kind is one of:
    path = [[0.0, 0.0], [4.0, 0.0], [4.0, 3.0]]  # roll/path: centre waypoints (x, z) on the floor
    radius = 0.5                 # roll: rolling radius (the ball's centre height is `translate` y)
    speed = 1.0                  # roll/path: m/s; loop = true closes the path, false goes there and back
    # kind = "path"              #   walk the polyline facing along it (model faces +Z)
    # kind = "swing"             #   pivot = [x, y, z], axis = [x, y, z], amplitude (deg), period (s), phase (deg)
    # kind = "platform"          #   offset = [dx, dy, dz], period (s), phase (deg): there and back, eased
    # kind = "keyframes"         #   loop = true, then [[instance.animation.key]] time, translate (offset),
                                 #   rotate (as above, about the object's origin), scale (> 0); times
                                 #   strictly increasing. Out-of-order keys, NaN, zero scale: errors at load.

    [[camera_path]]
    name = "walk"
    fov_y = 60.0                 # degrees, vertical
    loop = true                  # repeat with period last time - first time (repeat the first key last
                                 #   to close the loop smoothly)
    [[camera_path.key]]          # at least one; times strictly increasing
    time = 0.0                   # seconds
    eye = [0.0, 1.7, 8.0]
    target = [0.0, 1.0, 0.0]

The transform of an instance is T * R * S (scale first, then rotate, then translate).
"""
from __future__ import annotations

import inspect
import os
import tomllib
from pathlib import Path

import numpy as np

from psao.scene.errors import SceneError, SceneFormatError, SceneNotFound
from psao.scene import limits
from psao.scene.meshfile import clean_geometry, load_mesh_file, merged_mesh
from psao.scene.model import OBJECT_SAMPLING_FRACTION, CameraKey, CameraPath, Instance, Mesh, Scene
from psao.scene.rigid import PartAnimation
from psao.scene.skin import TimeShift
from psao.scene.toml_animation import parse_animation
from psao.scene.toml_fields import Table, rotation_of, scale_of
from psao.scene.transforms import trs


def load_toml_scene(path: Path) -> Scene:
    path = Path(path)
    if not path.is_file():
        raise SceneNotFound(f"{path}: scene file not found")
    size, most = path.stat().st_size, limits.current().max_scene_file_bytes
    if size > most:
        raise SceneFormatError(f"{path}: {size} bytes, over the scene file limit of {most} "
                               f"(psao --scene-limit max_scene_file_bytes=N raises it)")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as e:
        raise SceneFormatError(f"{path}: malformed TOML: {e}") from None
    except RecursionError:
        raise SceneFormatError(f"{path}: tables or arrays nested too deeply to read") from None
    except UnicodeDecodeError as e:
        raise SceneFormatError(f"{path}: not UTF-8 text: {e}") from None
    root = Table(data, str(path), {"scene", "mesh", "instance", "camera_path"})
    head = Table(data.get("scene", {}), f"{path}: [scene]", {"name", "ao_distance", "root"})
    name = head.text("name", path.stem)
    meshes, mesh_ids = _meshes(path, root.tables("mesh"), _scene_root(path, head))
    objects = _instances(path, root.tables("instance"), mesh_ids)
    instances = [inst for parts in objects for inst in parts]
    if not instances:
        raise SceneFormatError(f"{path}: no [[instance]]: the scene is empty")
    cameras = _camera_paths(path, root.tables("camera_path"))
    ao = head.number("ao_distance", positive=True) if head.has("ao_distance") else 0.0  # 0: loader picks
    scene = Scene(name=name, meshes=meshes, instances=instances, ao_distance=ao, camera_paths=cameras,
                  source=str(path))
    if not head.has("ao_distance"):
        _own_sampling_scales(scene, objects)
    return scene


def _own_sampling_scales(scene: Scene, objects: list[list[Instance]]) -> None:
    """OBJECT_SAMPLING_FRACTION x each object's own diagonal as the sampling scale of its parts (load_scene
    caps it at the scene's AO distance): a character in a cathedral is sampled at its own size."""
    for parts in objects:
        scale = OBJECT_SAMPLING_FRACTION * scene.diagonal(parts)
        for inst in parts:
            inst.sampling_scale = scale if np.isfinite(scale) and scale > 0 else 0.0


# A [[mesh]] of a TOML scene as the scene's meshes it became: (mesh index, part name or None when it is the
# only part, the part's transform inside the [[mesh]]).
Part = tuple[int, "str | None", np.ndarray]


def _scene_root(path: Path, head: Table) -> Path:
    """The folder mesh paths are resolved in: [scene] root relative to the TOML file, or the TOML's folder."""
    base = path.parent.resolve()
    if not head.has("root"):
        return base
    rel = head.text("root")
    folder = (base / rel).resolve()
    if not folder.is_dir():
        raise SceneNotFound(f"{head.where}: scene root '{rel}' ({folder}) is not a folder")
    return folder


def _generator(name, where: str):
    """The builtin_shapes generator `name` (imported here: its shapes come from trimesh, which a scene of
    mesh files need not load)."""
    from psao.scene import builtin_shapes

    gen = builtin_shapes.GENERATORS.get(name) if isinstance(name, str) else None
    if gen is None:
        raise SceneFormatError(f"{where}: unknown generator '{name}' (known: {', '.join(builtin_shapes.GENERATORS)})")
    return gen


def _meshes(path: Path, tables: list, root: Path) -> tuple[list[Mesh], dict[str, list[Part]]]:
    meshes: list[Mesh] = []
    ids: dict[str, list[Part]] = {}
    for k, raw in enumerate(tables):
        label = raw.get("name", f"#{k}") if isinstance(raw, dict) else f"#{k}"
        where = f"{path}: mesh '{label}'"
        gen_name = raw.get("generator") if isinstance(raw, dict) else None
        gen = _generator(gen_name, where) if gen_name is not None else None
        params = set(inspect.signature(gen).parameters) if gen else set()
        file_keys = {"animation", "animation_offset"} if gen_name is None else set()
        t = Table(raw, where, {"name", "generator", "path", "double_sided", "color"} | params | file_keys)
        name = t.text("name")
        if name in ids:
            raise t.fail("duplicate mesh name")
        fields = dict(double_sided=t.flag("double_sided", False),
                      color=tuple(t.vec("color", 3, [0.8, 0.8, 0.8]).tolist()))
        if not all(0 <= c <= 1 for c in fields["color"]):
            raise t.fail("'color' components must be in [0, 1]")
        if t.has("generator") == t.has("path"):
            raise t.fail("give exactly one of 'generator' or 'path'")
        if t.has("generator"):
            kwargs = {p: raw[p] for p in params if p in raw}
            check_resolution(t, gen_name, kwargs)
            try:
                v, f = gen(**kwargs)
            except (TypeError, ValueError) as e:
                raise t.fail(f"generator '{gen_name}': {e}") from None
            r = clean_geometry(v, f, where)
            parts = [(Mesh(name=name, vertices=r.vertices, faces=r.faces, **fields), None, np.eye(4))]
        else:
            parts = _file_meshes(root, t, name, fields)
        ids[name] = []
        for mesh, part, transform in parts:
            ids[name].append((len(meshes), part, transform))
            meshes.append(mesh)
    return meshes, ids


RESOLUTION_PARAMS = ("sections", "rings", "segments", "subdivisions")
ICOSPHERE_GENERATORS = ("sphere", "boulder")  # subdivisions multiply triangles by 4 each


def check_resolution(t: Table, gen_name: str, kwargs: dict) -> None:
    """Resolution parameters must be whole numbers within the limits before a generator allocates."""
    lim = limits.current()
    for p in RESOLUTION_PARAMS:
        if p not in kwargs:
            continue
        v = kwargs[p]
        most = (lim.max_icosphere_subdivisions if gen_name in ICOSPHERE_GENERATORS and p == "subdivisions"
                else lim.max_generator_resolution)
        if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= most:
            raise t.fail(f"generator '{gen_name}': '{p}' must be a whole number within 0..{most}, got {v!r} "
                         f"(psao --scene-limit raises the limit)")


def _file_meshes(root: Path, t: Table, name: str, fields: dict) -> list[tuple[Mesh, str | None, np.ndarray]]:
    """The meshes a [[mesh]] with a `path` becomes, each with its part name (None: the only one) and its
    transform inside the [[mesh]]: a file without skins merged into one mesh; a skinned glTF as its meshes
    and instances, each mesh renamed NAME/PART, its double_sided and color set, its animators shifted by
    animation_offset."""
    rel = t.text("path")
    # Inside the root by the path as written ("..", not symlinks: a link to a shared asset folder is fine)
    file = Path(os.path.normpath(root / rel))
    if Path(rel).is_absolute() or root not in file.parents:
        raise t.fail(f"path '{rel}' must be relative and inside the scene's folder ({root})")
    if not file.is_file():
        raise SceneNotFound(f"{t.where}: mesh file '{rel}' not found")
    animation = t.data.get("animation", 0)
    if isinstance(animation, bool) or not isinstance(animation, (int, str)):
        raise t.fail(f"'animation' must be a name or an index, got {animation!r}")
    offset = t.number("animation_offset") if t.has("animation_offset") else None
    try:
        ms, ins = load_mesh_file(file, animation)
    except SceneError as e:  # name the scene file and the element too, not only the mesh file
        raise type(e)(f"{t.where}: {e}") from None
    if not any(m.skin is not None for m in ms):
        if t.has("animation") or t.has("animation_offset"):
            raise t.fail(f"'{rel}' has no skin: 'animation' and 'animation_offset' do not apply")
        return [(merged_mesh(name, ms, ins, **fields), None, np.eye(4))]
    alone = len(ins) == 1
    for m in ms:
        m.name = name if alone else f"{name}/{m.name}"
        m.double_sided, m.color = fields["double_sided"], fields["color"]
        if m.skin is not None and offset is not None:
            m.skin.animator = TimeShift(m.skin.animator, offset)
    return [(ms[i.mesh], None if alone else i.name, i.transform) for i in ins]


def _instances(path: Path, tables: list, mesh_ids: dict[str, list[Part]]) -> list[list[Instance]]:
    """The scene's instances, by [[instance]]: the parts each places."""
    most = limits.current().max_instances
    if len(tables) > most:
        raise SceneFormatError(f"{path}: {len(tables)} instances, over the limit of {most} "
                               f"(psao --scene-limit max_instances=N raises it)")
    placed = sum(len(mesh_ids.get(raw.get("mesh"), ())) for raw in tables
                 if isinstance(raw, dict) and isinstance(raw.get("mesh"), str))
    if placed > most:
        raise SceneFormatError(f"{path}: {len(tables)} instances place {placed} parts, over the limit of {most} "
                               f"(psao --scene-limit max_instances=N raises it)")
    out: list[list[Instance]] = []
    names: set[str] = set()
    for k, raw in enumerate(tables):
        label = raw.get("name", f"#{k}") if isinstance(raw, dict) else f"#{k}"
        t = Table(raw, f"{path}: instance '{label}'",
                  {"name", "mesh", "translate", "rotate", "scale", "animation"})
        name = t.text("name")
        if name in names:
            raise t.fail("duplicate instance name")
        names.add(name)
        mesh = t.text("mesh")
        if mesh not in mesh_ids:
            raise t.fail(f"unknown mesh '{mesh}' (known: {', '.join(mesh_ids) or 'none'})")
        transform = trs(t.vec("translate", 3, [0, 0, 0]), rotation_of(t), scale_of(t))
        animation = None
        if t.has("animation"):
            animation = parse_animation(t.data["animation"], f"{t.where}: animation", transform)
            transform = animation.matrix(0.0)
        out.append([])
        for index, part, local in mesh_ids[mesh]:
            part_name = name if part is None else f"{name}/{part}"
            if part_name in names and part is not None:
                raise t.fail(f"part '{part_name}' has the name of another instance")
            names.add(part_name)
            moved = animation
            if animation is not None and not np.array_equal(local, np.eye(4)):
                moved = PartAnimation(animation, local)
            out[-1].append(Instance(name=part_name, mesh=index, transform=transform @ local, animation=moved))
    return out


def _camera_paths(path: Path, tables: list) -> dict[str, CameraPath]:
    out: dict[str, CameraPath] = {}
    for k, raw in enumerate(tables):
        label = raw.get("name", f"#{k}") if isinstance(raw, dict) else f"#{k}"
        t = Table(raw, f"{path}: camera_path '{label}'", {"name", "fov_y", "loop", "key"})
        name = t.text("name")
        if name in out:
            raise t.fail("duplicate camera path name")
        fov = t.number("fov_y", 60.0)
        if not 0 < fov < 180:
            raise t.fail(f"'fov_y' must be in (0, 180) degrees, got {fov}")
        keys = []
        for j, kraw in enumerate(t.tables("key")):
            kt = Table(kraw, f"{t.where}: key {j}", {"time", "eye", "target"})
            key = CameraKey(kt.number("time"), tuple(kt.vec("eye").tolist()), tuple(kt.vec("target").tolist()))
            if keys and key.time <= keys[-1].time:
                raise kt.fail(f"time {key.time} is not after the previous key's {keys[-1].time}")
            if np.allclose(key.eye, key.target):
                raise kt.fail("eye and target coincide")
            keys.append(key)
        if not keys:
            raise t.fail("needs at least one [[camera_path.key]]")
        out[name] = CameraPath(name=name, keys=keys, fov_y=fov, loop=t.flag("loop", True))
    return out
