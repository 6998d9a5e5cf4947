"""Pass 1: rasterise the scene's instances into a G-buffer (src/psao/client/shaders/gbuffer.vert.glsl, gbuffer.frag.glsl).

Attachments (GL's bottom-up rows; `read()` flips them to top-down images):
    world        RGBA32F  world position, w = 1 where covered (the mask)
    normal       RGBA32F  world normal, facing the camera on double-sided meshes
    local        RGBA32F  instance-local position (what the PSAO lookup needs, full float precision); on a
                          skinned mesh, the fragment's place in the rest pose (where the server keeps its points)
    local_normal RGBA32F  instance-local normal (a skinned mesh's rest pose), w = 1 where it shows the back
                          side of a double-sided mesh
    color        RGBA16F  lit colour without AO (directional light + ambient), linear
    instance     R32UI    instance index + 1, 0 = background
    depth        R32F     view depth (> 0), 0 = background (the SSAO taps read this one channel)
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psao.client.render.shaderlib import compile_program


@dataclass
class LightSettings:
    direction: tuple[float, float, float] = (0.35, 0.9, 0.25)  # towards the light, world space (y up)
    ambient: float = 0.35  # fraction of albedo lit by the ambient term
    diffuse: float = 0.65  # fraction lit by the directional light at normal incidence


@dataclass
class GBufferArrays:
    """G-buffer read back as top-down (H, W, ...) arrays."""

    world: np.ndarray  # (H, W, 3) float32
    normal: np.ndarray  # (H, W, 3) float32
    local: np.ndarray  # (H, W, 3) float32
    local_normal: np.ndarray  # (H, W, 3) float32
    color: np.ndarray  # (H, W, 3) float32, linear
    instance: np.ndarray  # (H, W) int32, -1 = background
    depth: np.ndarray  # (H, W) float32 view depth, 0 = background
    mask: np.ndarray  # (H, W) bool, covered pixels
    back_side: np.ndarray | None = None  # (H, W) bool: back side of a double-sided mesh (PSAO reads back-side cells)


_LAYOUT = [  # name, components, dtype
    ("world", 4, "f4"),
    ("normal", 4, "f4"),
    ("local", 4, "f4"),
    ("local_normal", 4, "f4"),
    ("color", 4, "f2"),
    ("instance", 1, "u4"),
    ("depth", 1, "f4"),
]


class GBuffer:
    def __init__(self, ctx, size: tuple[int, int]):
        self.size = (int(size[0]), int(size[1]))
        self.textures = {}
        for name, comps, dtype in _LAYOUT:
            tex = ctx.texture(self.size, comps, dtype=dtype)
            tex.filter = (ctx.NEAREST, ctx.NEAREST)
            self.textures[name] = tex
        self.depth_buffer = ctx.depth_renderbuffer(self.size)
        self.fbo = ctx.framebuffer([self.textures[n] for n, _, _ in _LAYOUT], self.depth_buffer)

    def __getitem__(self, name: str):
        return self.textures[name]

    def read(self) -> GBufferArrays:
        w, h = self.size

        def grab(name, comps, dtype, keep):
            arr = np.frombuffer(self.textures[name].read(), dtype=dtype).reshape(h, w, comps)[::-1]
            out = np.uint32 if dtype is np.uint32 else np.float32
            return np.ascontiguousarray(arr[..., :keep], dtype=out)

        world = grab("world", 4, np.float32, 4)
        inst = grab("instance", 1, np.uint32, 1)[..., 0].astype(np.int64) - 1
        local_normal = grab("local_normal", 4, np.float32, 4)
        return GBufferArrays(
            world=world[..., :3],
            normal=grab("normal", 4, np.float32, 3),
            local=grab("local", 4, np.float32, 3),
            local_normal=local_normal[..., :3].copy(),
            back_side=local_normal[..., 3] > 0.5,
            color=grab("color", 4, np.float16, 3),
            instance=inst.astype(np.int32),
            depth=grab("depth", 1, np.float32, 1)[..., 0],
            mask=world[..., 3] > 0,
        )

    def release(self) -> None:
        self.fbo.release()
        self.depth_buffer.release()
        for tex in self.textures.values():
            tex.release()
        self.textures.clear()


def flat_shaded_arrays(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Mesh -> interleaved (3F, 6) float32 position + face normal: one normal per triangle, matching
    the face normals the server's points carry."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    n = np.cross(b - a, c - a)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    pos = np.stack([a, b, c], axis=1).reshape(-1, 3)
    nrm = np.repeat(n, 3, axis=0)
    return np.hstack([pos, nrm]).astype(np.float32)


class GeometryPass:
    """One vertex array per mesh; one draw per instance with its model matrix.

    Every mesh's vertex array reads its rest-pose triangles (position and face normal) for the G-buffer's
    local targets, and its drawn triangles from a second buffer, the same one for meshes without a skin.
    Skinned meshes start in their rest pose; set_skin_time(t) poses their drawn triangles at scene time t
    (the server time of the last Update) with the server's own skinning (psao.scene.skinning, Warp), so
    the picture and the world position and normal are the deformed mesh's, while the local position and
    normal stay the rest pose's at the same triangle and barycentrics: where the server keeps the AO points
    of a skinned mesh."""

    def __init__(self, ctx, scene, light: LightSettings | None = None):
        self._ctx = ctx
        self.program = compile_program(ctx, vertex_shader="gbuffer.vert.glsl", fragment_shader="gbuffer.frag.glsl")
        self._scene = scene
        self._meshes = scene.meshes
        self._mesh_of_instance = [int(inst.mesh) for inst in scene.instances]
        self._skinned = [m for m, mesh in enumerate(scene.meshes) if mesh.skin is not None and len(mesh.faces)]
        self._skinner = None  # psao.scene.skinning.SceneSkinner, built on the first set_skin_time
        self.skin_time: float | None = None  # None = rest pose
        self._vbos, self._rest_vbos, self._vaos = [], [], []
        for m, mesh in enumerate(scene.meshes):
            data = flat_shaded_arrays(mesh.vertices, mesh.faces)
            rest = ctx.buffer(data.tobytes() if data.size else np.zeros(6, np.float32).tobytes())
            vbo = ctx.buffer(rest.read()) if m in self._skinned else rest  # a skinned mesh's drawn triangles move
            self._rest_vbos.append(rest)
            self._vbos.append(vbo)
            self._vaos.append((ctx.vertex_array(self.program, [(vbo, "3f 3f", "in_position", "in_normal"),
                                                               (rest, "3f 3f", "in_rest_position", "in_rest_normal")]),
                               len(data)))
        light = light or LightSettings()
        direction = np.asarray(light.direction, dtype=np.float64)
        self.program["u_light_dir"].value = tuple((direction / np.linalg.norm(direction)).tolist())
        self.program["u_ambient"].value = float(light.ambient)
        self.program["u_diffuse"].value = float(light.diffuse)

    @property
    def has_skins(self) -> bool:
        return bool(self._skinned)

    def set_skin_time(self, t: float | None) -> None:
        """Pose every skinned mesh at scene time t seconds (None: the rest pose); rewrites their drawn
        vertex buffers in place (the rest-pose ones never change) (same size: the topology never changes)."""
        if not self._skinned or t == self.skin_time:
            return
        if t is not None and self._skinner is None:
            from psao.scene.skinning import SceneSkinner
            self._skinner = SceneSkinner(self._scene, device="cpu")
        for m in self._skinned:
            mesh = self._meshes[m]
            vertices = mesh.vertices if t is None else self._skinner.vertices(m, float(t))
            self._vbos[m].write(flat_shaded_arrays(vertices, mesh.faces).tobytes())
        self.skin_time = None if t is None else float(t)

    def draw(self, gbuffer: GBuffer, view: np.ndarray, proj: np.ndarray, transforms: np.ndarray) -> None:
        ctx = self._ctx
        gbuffer.fbo.use()
        ctx.viewport = (0, 0, *gbuffer.size)
        gbuffer.fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        ctx.enable_only(ctx.DEPTH_TEST)  # no culling: single-sided meshes may be seen from behind
        self.program["u_view"].write(gl_mat4(view))
        self.program["u_proj"].write(gl_mat4(proj))
        for i, model in enumerate(transforms):
            mesh_index = self._mesh_of_instance[i]
            vao, count = self._vaos[mesh_index]
            if count == 0:
                continue
            mesh = self._meshes[mesh_index]
            linear = np.asarray(model, dtype=np.float64)[:3, :3]
            self.program["u_model"].write(gl_mat4(model))
            self.program["u_normal_matrix"].write(np.linalg.inv(linear).astype(np.float32).tobytes())
            self.program["u_albedo"].value = tuple(float(c) for c in mesh.color)
            self.program["u_instance"].value = i
            self.program["u_double_sided"].value = bool(mesh.double_sided)
            self.program["u_mirrored"].value = bool(np.linalg.det(linear) < 0)
            vao.render(ctx.TRIANGLES, vertices=count)

    def release(self) -> None:
        for vao, _ in self._vaos:
            vao.release()
        for vbo in {id(b): b for b in self._vbos + self._rest_vbos}.values():
            vbo.release()
        self.program.release()
        self._vaos, self._vbos, self._rest_vbos = [], [], []


def gl_mat4(m: np.ndarray) -> bytes:
    """Row-major numpy matrix (math convention, M @ v) -> GLSL's column-major bytes."""
    return np.ascontiguousarray(np.asarray(m, dtype=np.float32).T).tobytes()
