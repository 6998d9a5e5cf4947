"""shaderlib: includes, defines, #version rule, and compile errors that name file and line."""
from __future__ import annotations

import numpy as np
import pytest

from psao.client.errors import RenderError
from psao.client.render.shaderlib import SHADER_DIR, compile_program, load_shader


def write(tmp_path, name, text):
    (tmp_path / name).write_text(text)


def test_include_is_expanded_once_and_lines_map_back(tmp_path):
    write(tmp_path, "a.glsl", "// a\nfloat fa() { return 1.0; }\n")
    write(tmp_path, "b.glsl", '#include "a.glsl"\nfloat fb() { return fa(); }\n')
    write(tmp_path, "main.comp.glsl", '#version 430\n#include "a.glsl"\n#include "b.glsl"\nvoid main() {}\n')
    src = load_shader("main.comp.glsl", {"K": 3}, tmp_path)
    lines = src.text.splitlines()
    assert lines[0] == "#version 430" and lines[1] == "#define K 3"
    assert src.text.count("float fa()") == 1  # a.glsl included twice, expanded once
    assert len(src.origins) == len(lines)
    assert src.origins[lines.index("float fb() { return fa(); }")] == ("b.glsl", 2)
    assert src.origins[lines.index("void main() {}")] == ("main.comp.glsl", 4)
    assert src.locate("0:%d(3): error: x" % (lines.index("float fa() { return 1.0; }") + 1)) == "a.glsl:2"


def test_version_must_be_on_line_one(tmp_path):
    write(tmp_path, "nov.glsl", "// no version\nvoid main() {}\n")
    with pytest.raises(RenderError, match="line 1 must be the #version"):
        load_shader("nov.glsl", None, tmp_path)
    write(tmp_path, "inc.glsl", "#version 430\n")
    write(tmp_path, "top.glsl", '#version 430\n#include "inc.glsl"\n')
    with pytest.raises(RenderError, match="inc.glsl:1: #version is only allowed on line 1"):
        load_shader("top.glsl", None, tmp_path)


def test_missing_include_and_bad_define_name(tmp_path):
    write(tmp_path, "top.glsl", '#version 430\n#include "gone.glsl"\n')
    with pytest.raises(RenderError, match="shader file not found: .*gone.glsl"):
        load_shader("top.glsl", None, tmp_path)
    write(tmp_path, "ok.glsl", "#version 430\n")
    with pytest.raises(RenderError, match="bad shader define name"):
        load_shader("ok.glsl", {"1X": 1}, tmp_path)


def test_defines_reach_the_compiled_program(ctx, tmp_path):
    write(tmp_path, "out.glsl", "layout(std430, binding = 3) buffer Out { float v[]; };\n")
    write(tmp_path, "k.comp.glsl", '#version 430\n#include "out.glsl"\nlayout(local_size_x = 1) in;\n'
                                  "void main() { v[0] = SCALE * float(COUNT); v[1] = FLAG ? 1.0 : -1.0; }\n")
    buf = ctx.buffer(reserve=8)
    for scale, count, flag in ((0.25, 3, True), (2.0, 5, False)):
        prog = compile_program(ctx, {"SCALE": scale, "COUNT": count, "FLAG": flag}, tmp_path, compute="k.comp.glsl")
        buf.bind_to_storage_buffer(3)
        prog.run(1)
        got = np.frombuffer(buf.read(), np.float32)
        assert got[0] == pytest.approx(scale * count) and got[1] == (1.0 if flag else -1.0)
        prog.release()
    buf.release()


def test_compile_error_names_the_included_file_and_line(ctx, tmp_path):
    write(tmp_path, "helpers.glsl", "// helpers\n\nfloat broken() {\n    return undefined_name;\n}\n")
    write(tmp_path, "e.frag.glsl", '#version 430\n#include "helpers.glsl"\nout vec4 o;\nvoid main() { o = vec4(1.0); }\n')
    write(tmp_path, "v.vert.glsl", "#version 430\nvoid main() { gl_Position = vec4(0.0); }\n")
    with pytest.raises(RenderError) as info:
        compile_program(ctx, {"A": 1, "B": 2}, tmp_path, vertex_shader="v.vert.glsl", fragment_shader="e.frag.glsl")
    msg = str(info.value)
    assert "helpers.glsl:4" in msg and "undefined_name" in msg and "\n" not in msg


def test_compile_error_in_the_main_file_counts_lines_after_defines(ctx, tmp_path):
    write(tmp_path, "m.comp.glsl", "#version 430\nlayout(local_size_x = 1) in;\n\nvoid main() {\n    int x = nope;\n}\n")
    with pytest.raises(RenderError, match=r"m\.comp\.glsl:5: .*nope"):
        compile_program(ctx, {"A": 1, "B": 2, "C": 3}, tmp_path, compute="m.comp.glsl")


def test_every_project_shader_compiles(ctx):
    for path in sorted(SHADER_DIR.glob("*.glsl")):
        stage = path.name.split(".")[-2]
        if stage == "comp":
            compile_program(ctx, compute=path.name).release()
        elif stage == "frag":
            vert = "gbuffer.vert.glsl" if path.name.startswith("gbuffer") else "fullscreen.vert.glsl"
            compile_program(ctx, vertex_shader=vert, fragment_shader=path.name).release()
        else:
            assert stage in ("vert", "psao_common", "psao_lookup"), path.name  # vertex shaders compile with their pair, includes with the passes
