#version 410
// NNAO (Holden et al. 2016): a 3844-4-4-4-1 network on a 31 x 31 view-space grid of samples around the
// pixel. The first layer is four filters (u_filters: texel (4 i + f, j) holds the four filter weights of
// feature f of grid cell (i, j), normalisation folded in), evaluated at NNAO_SAMPLES stratified cells
// with a per-pixel jitter and rescaled by 961 / NNAO_SAMPLES; then three small PReLU layers. The noise
// this leaves is removed by the bilateral blur. src/psao/client/render/nnao_net.py is the numpy oracle.
#ifndef NNAO_SAMPLES
#define NNAO_SAMPLES 64
#endif
const int GRID = 31;
const int CELLS = GRID * GRID;
const float HALF = 15.0;

uniform sampler2D u_depth;      // view depth (> 0), 0 = background
uniform sampler2D u_normal;     // world normal
uniform sampler2D u_noise;      // 4x4 tile, x = stratification jitter in [0, 1)
uniform sampler2D u_filters;    // RGBA32F (4 * GRID) x GRID: first-layer weights per cell and feature
uniform mat3 u_view_rot;        // world -> camera rotation
uniform mat4 u_proj;            // camera -> clip
uniform vec4 u_unproject;       // (1/P00, 1/P11, P02, P12)
uniform float u_radius;         // world units: the scene's AO distance
uniform vec4 u_b0, u_a0, u_s0;  // first layer bias (folded), PReLU slope and scale
uniform mat4 u_W1, u_W2;        // column i = weights out of unit i
uniform vec4 u_b1, u_a1, u_s1, u_b2, u_a2, u_s2;
uniform vec4 u_W3;
uniform vec3 u_out;             // b3, a3, s3

layout(location = 0) out float o_ao;

vec3 view_position(vec2 pixel, float depth, vec2 size) {
    vec2 ndc = pixel / size * 2.0 - 1.0;
    return vec3((ndc + u_unproject.zw) * u_unproject.xy * depth, -depth);
}

vec4 prelu(vec4 z, vec4 a, vec4 s) {
    return s * max(z, 0.0) + a * min(z, 0.0);
}

void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    ivec2 isize = textureSize(u_depth, 0);
    vec2 size = vec2(isize);
    float depth = texelFetch(u_depth, p, 0).r;
    if (depth == 0.0) {
        o_ao = 1.0;
        return;
    }
    vec3 P = view_position(vec2(p) + 0.5, depth, size);
    vec3 nc = normalize(u_view_rot * texelFetch(u_normal, p, 0).xyz);
    float jitter = texelFetch(u_noise, p & 3, 0).x;
    vec4 z0 = vec4(0.0);
    for (int m = 0; m < NNAO_SAMPLES; ++m) {
        int k = min(int(floor((float(m) + jitter) * (float(CELLS) / float(NNAO_SAMPLES)))), CELLS - 1);
        int i = k % GRID;
        int j = k / GRID;
        vec3 S = P + vec3((float(i) - HALF) / HALF * u_radius, (float(j) - HALF) / HALF * u_radius, 0.0);
        vec4 clip = u_proj * vec4(S, 1.0);
        if (clip.w <= 0.0) continue;
        vec2 t = floor((clip.xy / clip.w * 0.5 + 0.5) * size);
        if (any(lessThan(t, vec2(0.0))) || any(greaterThanEqual(t, size))) continue;
        ivec2 texel = ivec2(t);
        float ds = texelFetch(u_depth, texel, 0).r;
        if (ds == 0.0) continue;
        vec3 Q = view_position(t + 0.5, ds, size);
        float scale = clamp(1.0 - length(Q - P) / u_radius, 0.0, 1.0);
        if (scale == 0.0) continue;
        vec3 ns = normalize(u_view_rot * texelFetch(u_normal, texel, 0).xyz);
        vec4 f = vec4(ns - nc, (ds - depth) / u_radius) * scale;
        z0 += f.x * texelFetch(u_filters, ivec2(4 * i + 0, j), 0) + f.y * texelFetch(u_filters, ivec2(4 * i + 1, j), 0)
            + f.z * texelFetch(u_filters, ivec2(4 * i + 2, j), 0) + f.w * texelFetch(u_filters, ivec2(4 * i + 3, j), 0);
    }
    vec4 h = prelu(z0 * (float(CELLS) / float(NNAO_SAMPLES)) + u_b0, u_a0, u_s0);
    h = prelu(u_W1 * h + u_b1, u_a1, u_s1);
    h = prelu(u_W2 * h + u_b2, u_a2, u_s2);
    float z = dot(u_W3, h) + u_out.x;
    o_ao = clamp(u_out.z * max(z, 0.0) + u_out.y * min(z, 0.0), 0.0, 1.0);
}
