"""The one GLSL loader: `#version` on line 1, `#include "file.glsl"`, `#define` injection, readable errors.

Every shader lives in `shaders/*.glsl` at the repository root; Python never holds shader source. The
loader expands includes recursively (each file at most once per program, so an include needs no guard)
and emits `#line LINE FILE_INDEX` directives so that the driver's error log names file and line: the
driver reports `FILE_INDEX:LINE`, which `compile_program` maps back to the file name.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

from psao_client.errors import RenderError

SHADER_DIR = Path(__file__).resolve().parents[2] / "shaders"

_INCLUDE = re.compile(r'^\s*#\s*include\s+"([^"]+)"\s*$')
_VERSION = re.compile(r"^\s*#\s*version\s+\d+")
# Mesa: "0:12(5): error: ...", NVIDIA: "0(12) : error C0000: ...".
_LOG_LOCATION = re.compile(r"(?m)^\s*(?:ERROR:\s*)?(\d+)[:(](\d+)")


@dataclass
class ShaderSource:
    """Expanded source of one stage plus the table that maps `#line` file indices to file names."""

    text: str
    files: list[str] = field(default_factory=list)

    def locate(self, log: str) -> str:
        """First `file:line` named by a driver log, or '' when the log names none."""
        m = _LOG_LOCATION.search(log)
        if not m:
            return ""
        index, line = int(m.group(1)), int(m.group(2))
        name = self.files[index] if index < len(self.files) else f"<source {index}>"
        return f"{name}:{line}"


def _define_lines(defines: dict[str, object] | None) -> list[str]:
    lines = []
    for name, value in (defines or {}).items():
        if not re.fullmatch(r"[A-Za-z_]\w*", name):
            raise RenderError(f"bad shader define name {name!r}")
        if isinstance(value, bool):
            value = int(value)
        if isinstance(value, float):
            value = repr(value) if "e" in repr(value) or "." in repr(value) else f"{value}.0"
        lines.append(f"#define {name} {value}")
    return lines


def load_shader(name: str, defines: dict[str, object] | None = None, shader_dir: Path | None = None) -> ShaderSource:
    """Read `shaders/NAME`, inject defines after its `#version` line and expand includes."""
    root = Path(shader_dir) if shader_dir is not None else SHADER_DIR
    src = ShaderSource(text="", files=[])
    lines = _read(root, name, src)
    if not lines or not _VERSION.match(lines[0]):
        raise RenderError(f"shader {name}: line 1 must be the #version directive")
    out = [lines[0], *_define_lines(defines), "#line 2 0"]
    included: set[str] = {name}
    out.extend(_expand(root, name, lines[1:], 0, 2, src, included))
    src.text = "\n".join(out) + "\n"
    return src


def _read(root: Path, name: str, src: ShaderSource) -> list[str]:
    path = root / name
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise RenderError(f"shader file not found: {path}") from None
    src.files.append(name)
    return text.splitlines()


def _expand(root, name, lines, file_index, first_line, src, included) -> list[str]:
    out: list[str] = []
    for offset, line in enumerate(lines):
        m = _INCLUDE.match(line)
        if not m:
            if _VERSION.match(line):
                raise RenderError(f"shader {name}:{first_line + offset}: #version is only allowed on line 1")
            out.append(line)
            continue
        child = m.group(1)
        if child in included:
            out.append(f"// {child} already included")
            continue
        included.add(child)
        child_index = len(src.files)
        child_lines = _read(root, child, src)
        out.append(f"#line 1 {child_index}")
        out.extend(_expand(root, child, child_lines, child_index, 1, src, included))
        out.append(f"#line {first_line + offset + 1} {file_index}")
    return out


def compile_program(ctx, defines: dict[str, object] | None = None, shader_dir: Path | None = None, **stages: str):
    """Build a moderngl Program (or ComputeShader with `compute=NAME`) from shader files.

    stages: vertex_shader / fragment_shader / compute = file names under shaders/. A compile or link
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
    # moderngl prefixes the driver log with the stage name ("fragment_shader", "GLSL Compiler failed").
    stage = next((s for s in sources if s in log), None)
    candidates = [stage] if stage else list(sources)
    first_error = next((ln.strip() for ln in log.splitlines() if "error" in ln.lower() and ":" in ln), "")
    for s in candidates:
        where = sources[s].locate(first_error or log)
        if where:
            return f"GLSL compile error in {where}: {first_error or log.strip().splitlines()[-1]}"
    summary = first_error or " ".join(log.split())[:200]
    return f"GLSL error in {', '.join(stages.values())}: {summary}"
