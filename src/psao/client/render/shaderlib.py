"""The one GLSL loader: `#version` on line 1, `#include "file.glsl"`, `#define` injection, readable errors.

Every shader lives in `src/psao/client/shaders/*.glsl` (package data, found through importlib.resources), except the
lookup shared with the web client, `src/psao/protocol/shaders/` (an include is looked up in the program's folder,
then there); Python never holds shader source. One include is generated
rather than read: `psao_constants.glsl` is src/psao/protocol/shader_constants.define_block(), the lookup's
constants from src/psao/protocol/ (so the shader holds no copy of them). The loader expands includes recursively (each file at most once per program, so an include needs no guard)
and keeps, for every line of the expanded text, the file and line it came from. Drivers report errors
as a line of the text they compiled (Mesa "0:LINE(COL)", NVIDIA "0(LINE)"); `compile_program` maps
that back to `file:line`. (`#line` directives are not used: Mesa attributes some errors to the wrong
source-string number, while the physical line is always right.)
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

from psao.protocol import shader_constants
from psao.client.errors import RenderError

SHADER_DIR = Path(str(resources.files("psao.client").joinpath("shaders")))

_INCLUDE = re.compile(r'^\s*#\s*include\s+"([^"]+)"\s*$')
_VERSION = re.compile(r"^\s*#\s*version\s+\d+")
_LOG_LOCATION = re.compile(r"(?m)^\s*(?:ERROR:\s*)?\d+[:(](\d+)")


@dataclass
class ShaderSource:
    """Expanded source of one stage; origins[i] is the (file, line) that line i + 1 of text came from."""

    text: str
    origins: list[tuple[str, int]] = field(default_factory=list)

    def locate(self, log: str) -> str:
        """First `file:line` named by a driver log, or '' when the log names none."""
        m = _LOG_LOCATION.search(log)
        if not m:
            return ""
        line = int(m.group(1))
        if 1 <= line <= len(self.origins):
            name, original = self.origins[line - 1]
            return f"{name}:{original}"
        return ""


def _define_lines(defines: dict[str, object] | None) -> list[str]:
    lines = []
    for name, value in (defines or {}).items():
        if not re.fullmatch(r"[A-Za-z_]\w*", name):
            raise RenderError(f"bad shader define name {name!r}")
        if isinstance(value, bool):
            value = "true" if value else "false"  # GLSL bool literals (not usable in #if)
        elif isinstance(value, float):
            value = repr(value)
        lines.append(f"#define {name} {value}")
    return lines


def load_shader(name: str, defines: dict[str, object] | None = None, shader_dir: Path | None = None) -> ShaderSource:
    """Read `NAME` from the shader folder, inject defines right after its `#version` line and expand includes."""
    root = Path(shader_dir) if shader_dir is not None else SHADER_DIR
    lines = _read(root, name)
    if not lines or not _VERSION.match(lines[0]):
        raise RenderError(f"shader {name}: line 1 must be the #version directive")
    out = [(lines[0], name, 1)]
    out += [(d, "<defines>", i + 1) for i, d in enumerate(_define_lines(defines))]
    out += _expand(root, name, lines[1:], 2, {name})
    return ShaderSource(text="\n".join(t for t, _, _ in out) + "\n", origins=[(f, ln) for _, f, ln in out])


# Includes answered by a function of src/psao/protocol/ values instead of a file.
GENERATED_INCLUDES = {shader_constants.INCLUDE_NAME: shader_constants.define_block}


def _read(root: Path, name: str) -> list[str]:
    if name in GENERATED_INCLUDES:
        return GENERATED_INCLUDES[name]().splitlines()
    path = root / name
    if not path.is_file() and (shader_constants.LOOKUP_SHADER_DIR / name).is_file():
        path = shader_constants.LOOKUP_SHADER_DIR / name
    try:
        return path.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise RenderError(f"shader file not found: {path}") from None


def _expand(root: Path, name: str, lines: list[str], first_line: int, included: set[str]) -> list[tuple[str, str, int]]:
    out: list[tuple[str, str, int]] = []
    for offset, line in enumerate(lines):
        number = first_line + offset
        m = _INCLUDE.match(line)
        if m is None:
            if _VERSION.match(line):
                raise RenderError(f"shader {name}:{number}: #version is only allowed on line 1")
            out.append((line, name, number))
            continue
        child = m.group(1)
        if child in included:
            out.append((f"// {child} already included", name, number))
            continue
        included.add(child)
        out.extend(_expand(root, child, _read(root, child), 1, included))
    return out


def compile_program(ctx, defines: dict[str, object] | None = None, shader_dir: Path | None = None, **stages: str):
    """Build a moderngl Program (or ComputeShader with `compute=NAME`) from shader files.

    stages: vertex_shader / fragment_shader / compute = file names under SHADER_DIR. A compile or link
    error becomes a RenderError naming the file and line the driver complained about.
    """
    import moderngl

    sources = {stage: load_shader(fname, defines, shader_dir) for stage, fname in stages.items()}
    try:
        if "compute" in sources:
            return ctx.compute_shader(sources["compute"].text)
        return ctx.program(**{stage: s.text for stage, s in sources.items()})
    except moderngl.Error as exc:
        raise RenderError(_describe_failure(str(exc), stages, sources)) from None


def _describe_failure(log: str, stages: dict[str, str], sources: dict[str, ShaderSource]) -> str:
    # moderngl prefixes the driver log with the stage name ("GLSL Compiler failed / fragment_shader").
    stage = next((s for s in sources if s in log), None)
    candidates = [stage] if stage else list(sources)
    first_error = next((ln.strip() for ln in log.splitlines() if "error" in ln.lower() and ":" in ln), "")
    message = _LOG_LOCATION.sub("", first_error).lstrip(" :()0123456789") or first_error
    for s in candidates:
        where = sources[s].locate(first_error)
        if where:
            return f"GLSL compile error in {where}: {message}"
    summary = message or " ".join(log.split())[:200]
    return f"GLSL error in {', '.join(stages.values())}: {summary}"
