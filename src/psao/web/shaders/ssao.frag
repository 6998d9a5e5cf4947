// SSAO baseline (shaders/ssao.frag.glsl of the desktop client): normal-oriented hemisphere, SSAO_SAMPLES taps,
// 4x4 rotation noise, range check, taps count only above the tangent plane. render.js defines SSAO_SAMPLES
// and uploads the kernel and noise from psao_constants.js (psao.protocol.ssao_kernel, the desktop's too).
uniform highp sampler2D u_normal_depth;  // world normal, view depth (0: background)
uniform highp sampler2D u_noise;
uniform mat4 u_view;
uniform mat4 u_proj;
uniform vec3 u_kernel[SSAO_SAMPLES];
uniform float u_radius;
uniform float u_bias;
uniform vec4 u_unproject;  // (1/P00, 1/P11, P02, P12)
layout(location = 0) out vec4 o_ao;
vec3 view_pos(ivec2 texel, ivec2 size, float depth) {
    vec2 ndc = (vec2(texel) + 0.5) / vec2(size) * 2.0 - 1.0;
    return vec3((ndc + u_unproject.zw) * u_unproject.xy * depth, -depth);
}
void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    ivec2 size = textureSize(u_normal_depth, 0);
    vec4 nd = texelFetch(u_normal_depth, p, 0);
    if (nd.w == 0.0) {
        o_ao = vec4(1.0);
        return;
    }
    vec3 pos = view_pos(p, size, nd.w);
    vec3 n = normalize(mat3(u_view) * nd.xyz);
    vec3 r = texelFetch(u_noise, p & 3, 0).xyz;
    vec3 t = normalize(r - n * dot(r, n));
    mat3 tbn = mat3(t, cross(n, t), n);
    float occlusion = 0.0;
    for (int i = 0; i < SSAO_SAMPLES; ++i) {
        vec3 s = pos + tbn * u_kernel[i] * u_radius;
        vec4 clip = u_proj * vec4(s, 1.0);
        vec2 uv = clip.xy / clip.w * 0.5 + 0.5;
        if (clip.w <= 0.0 || any(lessThan(uv, vec2(0.0))) || any(greaterThanEqual(uv, vec2(1.0)))) continue;
        ivec2 texel = ivec2(uv * vec2(size));
        float scene_depth = texelFetch(u_normal_depth, texel, 0).w;
        if (scene_depth == 0.0) continue;
        vec3 scene_pos = view_pos(texel, size, scene_depth);
        bool above = dot(n, scene_pos - pos) > u_bias;
        bool in_front = scene_depth <= -s.z - u_bias;
        float range = smoothstep(0.0, 1.0, u_radius / abs(-pos.z - scene_depth));
        occlusion += (above && in_front ? 1.0 : 0.0) * range;
    }
    o_ao = vec4(1.0 - occlusion / float(SSAO_SAMPLES));
}
