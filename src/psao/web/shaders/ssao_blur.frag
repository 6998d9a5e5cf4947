// Depth- and normal-aware 4x4 blur of the raw SSAO (removes the noise-tile pattern).
uniform highp sampler2D u_ao;
uniform highp sampler2D u_normal_depth;
uniform float u_radius;
layout(location = 0) out vec4 o_ao;
void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    ivec2 size = textureSize(u_ao, 0);
    vec4 nd0 = texelFetch(u_normal_depth, p, 0);
    if (nd0.w == 0.0) {
        o_ao = vec4(1.0);
        return;
    }
    float depth_scale = 1.0 / (0.25 * u_radius);
    float sum = 0.0;
    float wsum = 0.0;
    for (int y = -2; y < 2; ++y) {
        for (int x = -2; x < 2; ++x) {
            ivec2 q = clamp(p + ivec2(x, y), ivec2(0), size - 1);
            vec4 nd = texelFetch(u_normal_depth, q, 0);
            if (nd.w == 0.0) continue;
            float wn = max(dot(nd.xyz, nd0.xyz), 0.0);
            float wd = max(1.0 - abs(nd.w - nd0.w) * depth_scale, 0.0);
            float w = wn * wn * wd;
            sum += w * texelFetch(u_ao, q, 0).r;
            wsum += w;
        }
    }
    o_ao = vec4(wsum > 0.0 ? sum / wsum : texelFetch(u_ao, p, 0).r);
}
