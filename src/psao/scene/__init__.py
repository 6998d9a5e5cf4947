"""Scene loading shared by the server and the client: `load_scene(spec)` returns a psao.scene.model.Scene."""
from psao.scene.camera import camera_at, default_orbit, look_at, perspective, scene_camera
from psao.scene.errors import GeometryError, SceneError, SceneFormatError, SceneNotFound
from psao.scene.loader import load_scene
from psao.scene.model import CameraKey, CameraPath, Instance, Mesh, Scene, animation_hash
from psao.scene.rigid import RigidAnimation, instance_transform, is_dynamic
from psao.scene.skin import Skin

__all__ = [
    "load_scene", "Scene", "Mesh", "Instance", "CameraPath", "CameraKey",
    "camera_at", "look_at", "perspective", "default_orbit", "scene_camera",
    "instance_transform", "is_dynamic", "animation_hash", "RigidAnimation", "Skin",
    "SceneError", "SceneNotFound", "SceneFormatError", "GeometryError",
]
