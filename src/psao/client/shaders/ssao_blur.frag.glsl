#version 410
// Depth- and normal-aware 4x4 blur of the raw SSAO: removes the 4x4 noise-tile pattern without
// bleeding AO across depth edges (bilateral weights: depth difference relative to the AO radius,
// normal agreement).
uniform sampler2D u_ao;       // raw SSAO
uniform sampler2D u_depth;    // view depth, 0 = background
uniform sampler2D u_normal;   // world normal
uniform float u_radius;       // world units

layout(location = 0) out float o_ao;

void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    ivec2 size = textureSize(u_ao, 0);
    float d0 = texelFetch(u_depth, p, 0).r;
    if (d0 == 0.0) {
        o_ao = 1.0;
        return;
    }
    vec3 n0 = texelFetch(u_normal, p, 0).xyz;
    float depth_scale = 1.0 / (0.25 * u_radius);
    float sum = 0.0;
    float wsum = 0.0;
    for (int y = -2; y < 2; ++y) {
        for (int x = -2; x < 2; ++x) {
            ivec2 q = clamp(p + ivec2(x, y), ivec2(0), size - 1);
            float d = texelFetch(u_depth, q, 0).r;
            if (d == 0.0) continue;
            float wn = max(dot(texelFetch(u_normal, q, 0).xyz, n0), 0.0);
            float wd = max(1.0 - abs(d - d0) * depth_scale, 0.0);
            float w = wn * wn * wd;
            sum += w * texelFetch(u_ao, q, 0).r;
            wsum += w;
        }
    }
    o_ao = wsum > 0.0 ? sum / wsum : texelFetch(u_ao, p, 0).r;
}
