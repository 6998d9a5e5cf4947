#version 410
// PSAO pass, full-screen fragment variant: AO per pixel from the streamed grid (paper eq. 2-4).
#include "psao_common.glsl"

uniform sampler2D u_local;          // G-buffer instance-local position
uniform sampler2D u_local_normal;   // G-buffer instance-local normal; w = 1 on the back side of a double-sided mesh
uniform usampler2D u_instance;      // instance index + 1, 0 = background

layout(location = 0) out vec2 o_ao; // (AO, weight sum); background (1, 0)

void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    uint id = texelFetch(u_instance, p, 0).r;
    if (id == 0u) {
        o_ao = vec2(1.0, 0.0);
        return;
    }
    vec4 n = texelFetch(u_local_normal, p, 0);
    o_ao = psao_reconstruct(id - 1u, texelFetch(u_local, p, 0).xyz, n.xyz, n.w > 0.5);
}
