// The web client's point normals for the shared lookup (shaders/psao_lookup.glsl): WebGL2 promises only
// 224 fragment uniform vectors, so the PSAO_NORMAL_CODES oct-code normals (pointword.oct_decode, exact
// float32 from /psao_constants.js) are a 256 x 1 RGBA32F texture read with texelFetch.
uniform highp sampler2D u_psao_normals;

vec3 psao_point_normal(uint word) {
    return texelFetch(u_psao_normals, ivec2(int((word >> PSAO_SHIFT_NORMAL) & PSAO_CODE_MASK), 0), 0).xyz;
}
