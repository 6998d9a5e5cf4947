// PSAO grid lookup and point decode, shared by every pass that reads the streamed AO.
// Mirrors src/psao/protocol/gridformat.py (layout, hash) and src/psao/protocol/pointword.py (point word, oct code) bit for
// bit; src/psao/protocol/reconstruct.py is the Python oracle of psao_reconstruct() (paper eq. 2-4).
//
// Storage: the three tables are integer textures used as flat arrays (PSAO_TABLE_WIDTH texels per row,
// RGBA32UI): instances PSAO_INSTANCE_TEXELS texels per record, buckets PSAO_BUCKET_TEXELS (2 entries
// each), cells PSAO_CELL_TEXELS (7 point words + key); the bytes are gridformat's, texel for texel.
// Normals come from u_psao_normals, the results of pointword.oct_decode in float32. Cells farther than
// the lookup's widest radius from the fragment are skipped before hashing.
//
// Every constant below (PSAO_*) comes from src/psao/protocol/ through the generated include: the shader holds
// no copy of a layout value or threshold (tests/test_shader_constants.py checks).
#include "psao_constants.glsl"

uniform vec4 u_psao_normals[PSAO_NORMAL_CODES];  // oct code -> unit normal (xyz)

// Normals: u_psao_normals[code] is pointword.oct_decode(code) (4+4-bit octahedral, levels 0..14,
// level 15 clamped to 14), from gpu_grid.normal_table().
vec3 psao_point_normal(uint word) {
    return u_psao_normals[(word >> PSAO_SHIFT_NORMAL) & PSAO_CODE_MASK].xyz;
}

#include "psao_lookup.glsl"
