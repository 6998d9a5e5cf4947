"""load_scene: the one entry point both the server and the client use to get a Scene.

spec is `builtin:NAME` (a scene generated in code, or one of the example TOML scenes shipped as package
data in src/psao/scene/scenes), a `.toml` scene file or a bare mesh file (.gltf .glb .obj .ply .stl .off).
The result is validated (finite, invertible instance transforms; at least one instance) so that a bad
scene fails here, at load time, with a one-line SceneError naming the file and the element.
"""
from __future__ import annotations

from importlib import resources
from pathlib import Path

import numpy as np

from psao.scene.errors import GeometryError, SceneFormatError, SceneNotFound
from psao.scene import limits
from psao.scene.meshfile import MESH_EXTENSIONS, load_mesh_file
from psao.scene.model import DEFAULT_AO_FRACTION, Scene
from psao.scene.repeat import MAX_COPIES, parse_repeat, repeat_scene
from psao.scene.tomlscene import load_toml_scene

BUILTIN_PREFIX = "builtin:"
# An instance transform whose linear part has |det| below this (relative to its largest column norm
# cubed) is treated as a zero scale.
SINGULAR_DET = 1e-12
# An instance placed smaller than this fraction of its own reach (its largest world coordinate) is below what
# float32 positions resolve there (2^-23 relative, a few steps across it): a scale out of range.
MIN_RELATIVE_SIZE = 1e-6
# Times (seconds) at which animated transforms are checked at load time.
ANIMATION_CHECK_TIMES = tuple(float(t) for t in np.linspace(0.0, 30.0, 13))


def load_scene(spec: str | Path, ao_distance: float | None = None) -> Scene:
    if ao_distance is not None and not (np.isfinite(ao_distance) and ao_distance > 0):
        raise SceneFormatError(f"{spec}: ao_distance must be a finite number > 0, got {ao_distance}")
    text = str(spec)
    if text.startswith(BUILTIN_PREFIX):
        # Imported here: the built-ins' shapes come from trimesh, which a mesh file or TOML scene need not load.
        from psao.scene.builtin import BUILTINS

        name = text[len(BUILTIN_PREFIX):]
        examples = example_scenes()
        if name in BUILTINS:
            scene = BUILTINS[name]()
        elif name in examples:
            with resources.as_file(examples[name]) as path:
                scene = load_toml_scene(path)
            scene.source = text
        elif (repeat := parse_repeat(name)) and repeat[0] in BUILTINS:
            scene = _repeated(repeat, text)
        else:
            known = ", ".join(BUILTIN_PREFIX + n for n in [*BUILTINS, *examples])
            raise SceneNotFound(f"unknown scene '{text}' (known: {known}; or {BUILTIN_PREFIX}NAME-NXxNZ for copies "
                                f"on a grid)")
    else:
        scene = _load_file(Path(spec))
    if ao_distance is not None:
        scene.ao_distance = float(ao_distance)
        for inst in scene.instances:  # an explicit AO distance sets every instance's sampling too
            inst.sampling_scale = 0.0
    elif not scene.ao_distance > 0:
        scene.ao_distance = DEFAULT_AO_FRACTION * scene.diagonal()
    validate_scene(scene)
    for inst in scene.instances:  # an object's own scale, never coarser than the scene's
        inst.sampling_scale = min(inst.sampling_scale, scene.ao_distance)
    return scene


def _repeated(repeat: tuple[str, int, int], text: str) -> Scene:
    """A builtin copied on a grid (`NAME-NXxNZ`, src/psao/scene/repeat.py)."""
    name, nx, nz = repeat
    from psao.scene.builtin import BUILTINS

    if not (1 <= nx * nz <= MAX_COPIES):
        raise SceneFormatError(f"{text}: between 1 and {MAX_COPIES} copies, got {nx} x {nz}")
    return repeat_scene(BUILTINS[name](), nx, nz)


def example_scenes() -> dict:
    """NAME -> the example TOML scene shipped as package data (src/psao/scene/scenes/NAME.toml)."""
    folder = resources.files("psao.scene").joinpath("scenes")
    return {f.name[: -len(".toml")]: f for f in sorted(folder.iterdir(), key=lambda f: f.name) if f.name.endswith(".toml")}


def _load_file(path: Path) -> Scene:
    ext = path.suffix.lower()
    if ext == ".toml":
        return load_toml_scene(path)
    if ext not in MESH_EXTENSIONS:
        raise SceneFormatError(
            f"{path}: unsupported scene format '{ext or '(none)'}' (supported: .toml, {', '.join(MESH_EXTENSIONS)}, "
            f"or {BUILTIN_PREFIX}NAME)")
    if not path.is_file():
        raise SceneNotFound(f"{path}: file not found")
    meshes, instances = load_mesh_file(path)
    return Scene(name=path.stem, meshes=meshes, instances=instances, ao_distance=0.0, source=str(path))


def validate_scene(scene: Scene) -> None:
    """Checks every consumer relies on; raises GeometryError naming the scene and the element."""
    if not scene.instances:
        raise GeometryError(f"{scene.source}: scene has no instances")
    for m in scene.meshes:
        if len(m.faces) == 0 or not np.isfinite(m.vertices).all():
            raise GeometryError(f"{scene.source}: mesh '{m.name}' has no faces or non-finite vertices")
    for inst in scene.instances:
        check_transform(inst.transform, f"{scene.source}: instance '{inst.name}'")
        if inst.animation is not None:  # a bad motion fails here, not in the middle of serving
            for t in ANIMATION_CHECK_TIMES:
                check_transform(inst.animation.matrix(t), f"{scene.source}: instance '{inst.name}' at t={t:g} s")
        if not 0 <= inst.mesh < len(scene.meshes):
            raise GeometryError(f"{scene.source}: instance '{inst.name}' refers to missing mesh {inst.mesh}")
    lim = limits.current()
    if len(scene.instances) > lim.max_instances:
        raise GeometryError(f"{scene.source}: {len(scene.instances)} instances, over the limit of {lim.max_instances} "
                            f"(psao --scene-limit max_instances=N raises it)")
    lo, hi = scene.world_bounds()
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        raise GeometryError(f"{scene.source}: scene bounds are not finite")
    reach = float(max(np.abs(lo).max(), np.abs(hi).max()))
    if reach > lim.max_coordinate:
        raise GeometryError(f"{scene.source}: the placed scene reaches {reach:.3g} world units from the origin, over "
                            f"the limit of {lim.max_coordinate:g} (a scale or translation out of range? "
                            f"psao --scene-limit max_coordinate=X raises it)")
    for inst in scene.instances:
        lo, hi = scene.world_bounds([inst])
        size, at = float(np.linalg.norm(hi - lo)), float(max(np.abs(lo).max(), np.abs(hi).max()))
        if size < MIN_RELATIVE_SIZE * at:
            raise GeometryError(f"{scene.source}: instance '{inst.name}' is placed {size:.3g} world units across, "
                                f"{at:.3g} from the origin: too small for float32 positions to resolve there "
                                f"(a scale out of range?)")


def check_transform(t: np.ndarray, where: str) -> None:
    t = np.asarray(t, dtype=np.float64)
    if t.shape != (4, 4) or not np.isfinite(t).all():
        raise GeometryError(f"{where}: transform is not a finite 4x4 matrix")
    if not np.allclose(t[3], [0, 0, 0, 1]):
        raise GeometryError(f"{where}: transform has a projective last row {t[3].tolist()}")
    lin = t[:3, :3]
    scale = float(np.linalg.norm(lin, axis=0).max())
    if scale == 0 or abs(np.linalg.det(lin)) <= SINGULAR_DET * scale ** 3:
        raise GeometryError(f"{where}: transform has a zero scale (singular matrix)")
