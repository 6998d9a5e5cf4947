"""One source for the lookup's constants: the shader gets them from src/psao/protocol/, the oracle calls gridformat."""
import ast
import re
from pathlib import Path

import numpy as np
import pytest

from psao.protocol import gridformat as gf
from psao.protocol import pointword as pw
from psao.protocol import shader_constants as sc
from psao.client.render.shaderlib import load_shader
from psao.protocol.shader_constants import LOOKUP_SHADER_DIR

ROOT = Path(__file__).resolve().parents[1]
# Numbers the lookup shader may write out: component indices, the 2x2x2 block and the 3x3x3 fallback ring,
# the step centre 0.5, 1.0 and the rounding slack of the reach test. Anything else is a protocol value and
# must be a PSAO_ define.
STRUCTURAL_LITERALS = {"0", "1", "2", "3", "8", "9", "27", "0u", "1u", "2u", "0.0", "0.5", "1.0", "1.001"}
_LITERAL = re.compile(r"(?<![\w.])(0[xX][0-9a-fA-F]+[uU]?|\d+\.\d*(?:[eE][-+]?\d+)?|\.\d+|\d+[uU]?)(?![\w.])")


def _code(path: Path) -> str:
    text = re.sub(r"/\*.*?\*/", "", path.read_text(), flags=re.S)
    return re.sub(r"//[^\n]*", "", text)


def test_lookup_shader_holds_no_protocol_literal():
    code = _code(LOOKUP_SHADER_DIR / "psao_common.glsl") + _code(LOOKUP_SHADER_DIR / "psao_lookup.glsl")
    stray = sorted(set(_LITERAL.findall(code)) - STRUCTURAL_LITERALS)
    assert stray == [], f"the lookup shaders write protocol values as literals: {stray}"
    assert not re.search(r"#\s*define\s+PSAO_", code), "PSAO_ constants must come from src/psao/protocol/shader_constants.py"
    used = set(re.findall(r"\bPSAO_[A-Z_]+\b", code))
    assert used <= set(sc.define_values()), used - set(sc.define_values())


def test_generated_defines_are_the_protocol_values():
    values = sc.define_values()

    def num(name):
        return float(values[name]) if "." in values[name] else int(values[name].rstrip("uU"), 0)

    assert num("PSAO_T_N") == gf.T_N and num("PSAO_T_D") == gf.T_D
    assert num("PSAO_EMPTY") == int(gf.EMPTY) and num("PSAO_BACK_BIT") == int(gf.BACK_BIT)
    assert num("PSAO_HASH_Y") == gf.HASH_Y and num("PSAO_HASH_Z") == gf.HASH_Z
    assert num("PSAO_ALLOCATED") == int(pw.ALLOCATED_BIT)
    assert (num("PSAO_SHIFT_X"), num("PSAO_SHIFT_Y"), num("PSAO_SHIFT_Z")) == (pw.SHIFT_X, pw.SHIFT_Y, pw.SHIFT_Z)
    assert num("PSAO_POSITION_LEVELS") == pw.POSITION_LEVELS and num("PSAO_AO_LEVELS") == pw.AO_LEVELS
    assert num("PSAO_INSTANCE_TEXELS") * 16 == gf.INSTANCE_DTYPE.itemsize
    assert num("PSAO_CELL_TEXELS") * 4 == gf.CELL_WORDS
    assert 1 << num("PSAO_TABLE_SHIFT") == num("PSAO_TABLE_WIDTH") == sc.TABLE_WIDTH
    # The point word's bit fields, as the defines describe them, pack what pointword packs.
    word = pw.pack_point(np.array([3, 17, 30]), np.array([0xA5]), np.array([77]))[0]
    q = [(int(word) >> num(f"PSAO_SHIFT_{a}")) & num("PSAO_POSITION_MASK") for a in "XYZ"]
    assert q == [3, 17, 30]
    assert (int(word) >> num("PSAO_SHIFT_NORMAL")) & num("PSAO_CODE_MASK") == 0xA5
    assert int(word) & num("PSAO_CODE_MASK") == 77


def test_loader_expands_the_generated_block_with_overridable_thresholds():
    src = load_shader("psao_ao.frag.glsl", {"PSAO_T_N": 0.25})
    lines = src.text.splitlines()
    assert lines.index("#define PSAO_T_N 0.25") < lines.index("#ifndef PSAO_T_N")
    assert f"#define PSAO_HASH_Y {gf.HASH_Y}u" in lines
    assert sc.INCLUDE_NAME in {name for name, _ in src.origins}
    with pytest.raises(ValueError, match="power of two"):
        sc.define_block(table_width=3000)


def test_no_other_copy_of_the_thresholds_or_hash_in_python():
    """T_N, T_D and the eq. 1 multipliers are assigned once, in gridformat; the oracle calls gridformat's
    key and bucket functions instead of re-writing them."""
    for path in [*ROOT.glob("src/psao/**/*.py")]:
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Assign) and path.name != "gridformat.py":
                names = {t.id for t in node.targets if isinstance(t, ast.Name)}
                assert not names & {"T_N", "T_D", "HASH_Y", "HASH_Z"}, f"{path} assigns {names}"
    oracle = (ROOT / "src" / "psao" / "protocol" / "reconstruct.py").read_text()
    assert "gf.cell_key(" in oracle and "gf.bucket_index(" in oracle
    assert not re.search(r"\b(17|31)\b", _code_py(oracle))


def _code_py(text: str) -> str:
    return "\n".join(line.split("#", 1)[0] for line in text.splitlines())
