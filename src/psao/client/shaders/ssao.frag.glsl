#version 410
// SSAO baseline: normal-oriented hemisphere SSAO (Crytek / LearnOpenGL style). View-space position
// and normal from the G-buffer, a 4x4 rotation-noise tile, SSAO_SAMPLES kernel samples scaled towards
// the centre, and a range check so that geometry far behind a depth edge does not occlude.
// One refinement over the textbook version: a tap only occludes when the surface found at its pixel
// lies above the fragment's tangent plane. Without it a flat floor seen at a grazing angle occludes
// itself (a pixel spans more depth than any fixed bias), which would be unfair to SSAO.
#ifndef SSAO_SAMPLES
#define SSAO_SAMPLES 16
#endif

uniform sampler2D u_world;       // xyz world position, w = 1 where covered
uniform sampler2D u_normal;      // world normal
uniform sampler2D u_depth;       // view depth (> 0), 0 = background
uniform sampler2D u_noise;       // 4x4 random rotation vectors (xy in [-1, 1], z = 0)
uniform mat4 u_view;             // world -> camera
uniform mat4 u_proj;             // camera -> clip
uniform vec3 u_kernel[SSAO_SAMPLES];  // hemisphere (z >= 0) samples, |s| <= 1
uniform float u_radius;          // world units: the scene's AO distance
uniform float u_bias;            // world units, against self-occlusion on flat surfaces
uniform vec4 u_unproject;        // (1/P00, 1/P11, P02, P12): view position from NDC and view depth

layout(location = 0) out float o_ao;

void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    ivec2 size = textureSize(u_depth, 0);
    vec4 world = texelFetch(u_world, p, 0);
    if (world.w == 0.0) {
        o_ao = 1.0;
        return;
    }
    vec3 pos = (u_view * vec4(world.xyz, 1.0)).xyz;
    vec3 n = normalize(mat3(u_view) * texelFetch(u_normal, p, 0).xyz);
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
        float scene_depth = texelFetch(u_depth, texel, 0).r;
        if (scene_depth == 0.0) continue;  // sky: nothing there to occlude
        vec2 ndc = (vec2(texel) + 0.5) / vec2(size) * 2.0 - 1.0;
        vec3 scene_pos = vec3((ndc + u_unproject.zw) * u_unproject.xy * scene_depth, -scene_depth);
        bool above = dot(n, scene_pos - pos) > u_bias;
        bool in_front = scene_depth <= -s.z - u_bias;
        float range = smoothstep(0.0, 1.0, u_radius / abs(-pos.z - scene_depth));
        occlusion += (above && in_front ? 1.0 : 0.0) * range;
    }
    o_ao = 1.0 - occlusion / float(SSAO_SAMPLES);
}
