#version 410
// GTAO (Jimenez et al. 2016, "Practical Realtime Strategies for Accurate Indirect Occlusion", the
// algorithm Intel's XeGTAO implements): per pixel, GTAO_SLICES screen-space slices through the view
// vector; in each slice a horizon search of GTAO_STEPS taps on both sides finds the highest occluder
// (cosine of its angle to the view vector), distant taps fade towards the tangent-plane horizon
// (falloff over the last u_falloff of the radius), and the thickness heuristic lets a horizon sink back
// towards a lower tap behind a thin occluder. The cosine-weighted visibility between the two horizons
// is integrated in closed form, weighted by the length of the normal projected into the slice, and
// normalised by the same integral with no occluder (an open plane gives exactly 1 with few slices),
// then raised to u_power. A normal facing away from the camera is turned towards it first.
// Slice rotation and step offset come from a 4x4 noise tile that the 4x4 bilateral blur removes.
// src/psao/client/render/gtao_oracle.py evaluates exactly this in numpy (the test compares them).
#ifndef GTAO_SLICES
#define GTAO_SLICES 4
#endif
#ifndef GTAO_STEPS
#define GTAO_STEPS 8
#endif

const float PI = 3.14159265358979;
const float HALF_PI = 1.57079632679490;

uniform sampler2D u_depth;      // view depth (> 0), 0 = background
uniform sampler2D u_normal;     // world normal
uniform sampler2D u_noise;      // 4x4 tile: x = slice rotation, y = step offset, both in [0, 1)
uniform mat3 u_view_rot;        // world -> camera rotation
uniform vec4 u_unproject;       // (1/P00, 1/P11, P02, P12): view position from NDC and view depth
uniform float u_radius;         // world units: the search radius (the scene's AO distance x a multiplier)
uniform float u_falloff;        // fraction of the radius over which taps fade out
uniform float u_power;          // the visibility is raised to this power
uniform float u_thickness;      // 0: plain max horizon; (0, 1]: blend back towards lower taps
uniform float u_pixels_per_unit;  // 0.5 * height * P11: pixels covered by one world unit at view depth 1

layout(location = 0) out float o_ao;

vec3 view_position(vec2 pixel, float depth, vec2 size) {
    vec2 ndc = pixel / size * 2.0 - 1.0;
    return vec3((ndc + u_unproject.zw) * u_unproject.xy * depth, -depth);
}

// View depth at a sub-pixel position (pixel units, texel centres at i + 0.5): 1/depth interpolated
// bilinearly, which is exact on planes, so the taps of a flat surface lie on it and do not occlude it.
// 0 when the footprint touches the sky or leaves the screen.
float tap_depth(vec2 pixel, ivec2 size) {
    if (any(lessThan(pixel, vec2(0.0))) || any(greaterThanEqual(pixel, vec2(size)))) return 0.0;
    vec2 x = pixel - 0.5;
    ivec2 i0 = ivec2(floor(x));
    vec2 f = x - vec2(i0);
    ivec2 lo = clamp(i0, ivec2(0), size - 1);
    ivec2 hi = clamp(i0 + 1, ivec2(0), size - 1);
    float a = texelFetch(u_depth, lo, 0).r;
    float b = texelFetch(u_depth, ivec2(hi.x, lo.y), 0).r;
    float c = texelFetch(u_depth, ivec2(lo.x, hi.y), 0).r;
    float d = texelFetch(u_depth, hi, 0).r;
    if (min(min(a, b), min(c, d)) == 0.0) return 0.0;
    return 1.0 / mix(mix(1.0 / a, 1.0 / b, f.x), mix(1.0 / c, 1.0 / d, f.x), f.y);
}

// Cosine of the horizon on one side after a tap at `pixel`; `low` is the tangent-plane horizon.
float horizon_tap(float horizon, float low, vec2 pixel, ivec2 size, vec3 P, vec3 V, float falloff_mul, float falloff_add) {
    float d = tap_depth(pixel, size);
    if (d == 0.0) return horizon;  // sky or off screen: no occluder
    vec3 delta = view_position(pixel, d, vec2(size)) - P;
    float dist = length(delta);
    if (dist <= 0.0) return horizon;
    float weight = clamp(dist * falloff_mul + falloff_add, 0.0, 1.0);
    float c = mix(low, dot(delta, V) / dist, weight);
    return c > horizon ? c : max(low, mix(horizon, c, u_thickness));
}

float arc(float h, float n, float cos_n, float sin_n) {
    return 0.25 * (cos_n + 2.0 * h * sin_n - cos(2.0 * h - n));
}

void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    ivec2 size = textureSize(u_depth, 0);
    float depth = texelFetch(u_depth, p, 0).r;
    if (depth == 0.0) {
        o_ao = 1.0;
        return;
    }
    vec3 P = view_position(vec2(p) + 0.5, depth, vec2(size));
    vec3 V = normalize(-P);
    vec3 N = normalize(u_view_rot * texelFetch(u_normal, p, 0).xyz);
    // A single-sided surface seen from behind: the depth buffer only describes the camera's side.
    if (dot(N, V) < 0.0) N = -N;
    vec2 noise = texelFetch(u_noise, p & 3, 0).xy;
    float radius_px = u_radius * u_pixels_per_unit / depth;
    float min_s = 1.0 / max(radius_px, 1.0);  // the first tap lands at least one pixel away
    float falloff_range = max(u_falloff, 1e-4) * u_radius;
    float falloff_mul = -1.0 / falloff_range;
    float falloff_add = u_radius / falloff_range;

    float visible = 0.0;
    float open = 0.0;
    for (int i = 0; i < GTAO_SLICES; ++i) {
        float phi = (float(i) + noise.x) * PI / float(GTAO_SLICES);
        vec2 omega = vec2(cos(phi), sin(phi));
        vec3 dir = vec3(omega, 0.0);
        vec3 ortho = dir - dot(dir, V) * V;
        vec3 axis = normalize(cross(dir, V));
        vec3 pn = N - axis * dot(N, axis);
        float pn_len = length(pn);
        if (pn_len < 1e-6) continue;
        float cos_n = clamp(dot(pn, V) / pn_len, -1.0, 1.0);
        float n = sign(dot(ortho, pn)) * acos(cos_n);
        float sin_n = sin(n);
        float low0 = cos(n + HALF_PI);
        float low1 = cos(n - HALF_PI);
        float hc0 = low0;
        float hc1 = low1;
        if (radius_px >= 1.0) {
            for (int j = 0; j < GTAO_STEPS; ++j) {
                float s = (float(j) + noise.y) / float(GTAO_STEPS);
                vec2 offset = (s * s + min_s) * radius_px * omega;
                hc0 = horizon_tap(hc0, low0, vec2(p) + 0.5 + offset, size, P, V, falloff_mul, falloff_add);
                hc1 = horizon_tap(hc1, low1, vec2(p) + 0.5 - offset, size, P, V, falloff_mul, falloff_add);
            }
        }
        float h0 = n + clamp(-acos(clamp(hc1, -1.0, 1.0)) - n, -HALF_PI, HALF_PI);
        float h1 = n + clamp(acos(clamp(hc0, -1.0, 1.0)) - n, -HALF_PI, HALF_PI);
        visible += pn_len * (arc(h0, n, cos_n, sin_n) + arc(h1, n, cos_n, sin_n));
        open += pn_len * (cos_n + n * sin_n);
    }
    o_ao = open > 0.0 ? pow(clamp(visible / open, 0.0, 1.0), u_power) : 1.0;
}
