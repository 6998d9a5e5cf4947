"""The web client's files over plain HTTP on the serve port: a fixed allow-list, nothing else.

`GET /` is the page (index.html of the package psao.web, read through importlib.resources, so an
installed wheel serves it as the source tree does); its ES modules, GLSL ES shaders and the `fzstd`
decoder (psao.web's vendor/fzstd.mjs, a copy of the npm package's ESM build) are served by exact path
from ASSETS, as are the three.js integration (three/) and the three.js files its example imports (vendor/three/). Any other path (`..`, absolute paths, encoded slashes, query tricks) is a 404: the path is
only ever a dictionary key, never joined to a directory. `/psao_constants.js` is generated from
src/psao/protocol/ (constants_module), so the page's parser and its GLSL ES lookup read the same numbers
as the Python oracle and the server.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from importlib import resources
from importlib.resources.abc import Traversable
from pathlib import Path

import numpy as np

from psao.protocol import gridformat as gf
from psao.protocol import messages as m
from psao.protocol import pointword as pw
from psao.protocol import scenefile as sf
from psao.protocol.codecs import Codec
from psao.protocol.limits import DEFAULT_LIMITS, HEADER_SIZE
from psao.protocol.session import GRID_REPLACED_CLOSE
from psao.protocol import ssao_kernel
from psao.protocol.shader_constants import LOOKUP_SHADER_DIR, define_block
from psao.protocol.updates import RAW, Layout

# The web client, package data of psao.web.
WEB_DIR = resources.files("psao.web")
# The lookup shared with the desktop client, package data of psao.protocol.
SHADER_DIR = LOOKUP_SHADER_DIR

_JS, _HTML, _GLSL, _CSS = ("text/javascript; charset=utf-8", "text/html; charset=utf-8", "text/plain; charset=utf-8",
                           "text/css; charset=utf-8")
ASSETS = {  # URL path -> (file of psao.web, or a Path, content type)
    "/": ("index.html", _HTML),
    "/index.html": ("index.html", _HTML),
    "/style.css": ("style.css", _CSS),
    "/main.js": ("main.js", _JS),
    "/wire.js": ("wire.js", _JS),
    "/scene.js": ("scene.js", _JS),
    "/render.js": ("render.js", _JS),
    "/camera.js": ("camera.js", _JS),
    "/digest.js": ("digest.js", _JS),
    "/shaders/psao_lookup.glsl": (SHADER_DIR / "psao_lookup.glsl", _GLSL),
    "/shaders/psao_normals.glsl": ("shaders/psao_normals.glsl", _GLSL),
    "/shaders/gbuffer.vert": ("shaders/gbuffer.vert", _GLSL),
    "/shaders/gbuffer.frag": ("shaders/gbuffer.frag", _GLSL),
    "/shaders/fullscreen.vert": ("shaders/fullscreen.vert", _GLSL),
    "/shaders/psao.frag": ("shaders/psao.frag", _GLSL),
    "/shaders/ssao.frag": ("shaders/ssao.frag", _GLSL),
    "/shaders/ssao_blur.frag": ("shaders/ssao_blur.frag", _GLSL),
    "/shaders/composite.frag": ("shaders/composite.frag", _GLSL),
    "/vendor/fzstd.js": ("vendor/fzstd.mjs", _JS),
    # The three.js integration (psao-three.js, the npm module of web/three/) and its example page.
    "/three/": ("three/index.html", _HTML),
    "/three/index.html": ("three/index.html", _HTML),
    "/three/example.js": ("three/example.js", _JS),
    "/three/psao-three.js": ("three/psao-three.js", _JS),
}
# three.js as web/three/package-lock.json pins it: the files the example imports, copied from its npm package
# into psao.web's vendor/three/ (tests/test_web_vendor.py compares them).
THREE_FILES = ("three.module.js", "three.core.js", *(f"addons/{f}.js" for f in (
    "postprocessing/EffectComposer", "postprocessing/RenderPass", "postprocessing/OutputPass", "postprocessing/GTAOPass",
    "postprocessing/SAOPass", "postprocessing/ShaderPass", "postprocessing/Pass", "postprocessing/MaskPass",
    "shaders/CopyShader", "shaders/OutputShader", "shaders/GTAOShader", "shaders/PoissonDenoiseShader",
    "shaders/SAOShader", "shaders/DepthLimitedBlurShader", "math/SimplexNoise")))
ASSETS.update({f"/vendor/three/{f}": (f"vendor/three/{f}", _JS) for f in THREE_FILES})
# --web-example NAME: the page GET / answers instead of the PSAO page.
EXAMPLES = {"three": "three/index.html"}
CONSTANTS_PATH = "/psao_constants.js"


TABLE_WIDTHS = (2048, 4096)  # WebGL2 guarantees MAX_TEXTURE_SIZE 2048; the desktop client's width is 4096


def constants_module() -> str:
    """An ES module with every number the page shares with src/psao/protocol/ (wire format and lookup)."""
    limits = DEFAULT_LIMITS
    consts = {
        "MAGIC": m.MAGIC.decode(), "PROTOCOL_VERSION": m.PROTOCOL_VERSION, "HEADER_SIZE": HEADER_SIZE,
        "SCENE_HASH_BYTES": m.SCENE_HASH_BYTES,
        "MessageType": {t.name: int(t) for t in m.MessageType},
        "ErrorCode": {c.name: int(c) for c in m.ErrorCode},
        "StatusPhase": {p.name: int(p) for p in m.StatusPhase},
        "GRID_REPLACED_CLOSE": GRID_REPLACED_CLOSE,
        "Codec": {c.name: int(c) for c in Codec},
        "Layout": {x.name: int(x) for x in Layout},
        "RAW": RAW,
        "CELL_WORDS": gf.CELL_WORDS, "KEY_WORD": gf.KEY_WORD, "POINTS_PER_CELL": gf.POINTS_PER_CELL,
        "BUCKET_ENTRIES": gf.BUCKET_ENTRIES, "EMPTY": int(gf.EMPTY), "INSTANCE_BYTES": gf.INSTANCE_DTYPE.itemsize,
        "INSTANCE_DTYPE_STR": gf.INSTANCE_DTYPE.str,
        "ALLOCATED_BIT": int(pw.ALLOCATED_BIT), "OCT_LEVELS_HALF": pw.OCT_LEVELS_HALF,
        "SCENE_MAGIC": sf.MAGIC.decode(), "SCENE_VERSION": sf.VERSION,
        "FLAG_DOUBLE_SIDED_MESH": sf.FLAG_DOUBLE_SIDED, "FLAG_SKINNED": sf.FLAG_SKINNED,
        "LIMITS": {k: getattr(limits, k) for k in ("server_message_bytes", "server_payload_bytes", "max_instances",
                                                   "max_buckets", "max_cell_capacity", "max_cells_per_message",
                                                   "max_buckets_per_message", "scene_bytes", "scene_payload_bytes",
                                                   "token_bytes", "error_text_bytes")},
    }
    lines = ["// Generated by src/psao/server/net/webpage.py from src/psao/protocol/: do not edit (the server serves it)."]
    lines += [f"export const {k} = {json.dumps(v)};" for k, v in consts.items()]
    # The lookup's #define block (psao.protocol.shader_constants, as the desktop client's) for each table width
    # the page may pick for its MAX_TEXTURE_SIZE.
    blocks = {w: define_block(table_width=w) for w in TABLE_WIDTHS}
    lines.append(f"export const GLSL_DEFINES = {json.dumps(blocks)};")
    # The oct-code normals exactly as pointword.oct_decode gives them (float32 values, exact in JSON).
    lines.append(f"export const NORMAL_CODES = {pw.NORMAL_CODES};")
    lines.append(f"export const OCT_NORMALS = {json.dumps(pw.oct_decode(np.arange(pw.NORMAL_CODES)).reshape(-1).tolist())};")
    # The SSAO baseline's kernel and noise tile, the desktop SsaoPass's defaults (psao.protocol.ssao_kernel).
    lines.append(f"export const SSAO_SAMPLES = {ssao_kernel.SAMPLES};")
    lines.append(f"export const SSAO_KERNEL = {json.dumps(ssao_kernel.hemisphere_kernel().reshape(-1).tolist())};")
    lines.append(f"export const SSAO_NOISE = {json.dumps(ssao_kernel.rotation_noise().reshape(-1).tolist())};")
    return "\n".join(lines) + "\n"


@dataclass(frozen=True)
class HttpAnswer:
    status: int
    reason: str
    content_type: str
    body: bytes


def not_found(path: str) -> HttpAnswer:
    return HttpAnswer(404, "Not Found", _GLSL, f"404: {path[:200]} is not a file of the PSAO page\n".encode())


def answer(path: str, web_dir: Traversable = WEB_DIR, example: str = "") -> HttpAnswer:
    """The response to `GET path`: an allow-listed asset (a name read from `web_dir`, a Path as itself), the
    generated constants, or 404; `example` (a key of EXAMPLES) is the page at `/` instead of index.html."""
    path = path.split("?", 1)[0]
    if path == CONSTANTS_PATH:
        return HttpAnswer(200, "OK", _JS, constants_module().encode())
    entry = (EXAMPLES[example], _HTML) if example and path == "/" else ASSETS.get(path)
    if entry is None:
        return not_found(path)
    name, ctype = entry
    try:
        body = (name if isinstance(name, Path) else web_dir.joinpath(*name.split("/"))).read_bytes()
    except OSError:
        return not_found(path)
    return HttpAnswer(200, "OK", ctype, body)
