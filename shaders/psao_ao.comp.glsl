#version 430
// PSAO pass, compute variant: the same lookup as psao_ao.frag.glsl, one invocation per pixel.
#include "psao_common.glsl"

layout(local_size_x = 8, local_size_y = 8) in;

uniform sampler2D u_local;
uniform sampler2D u_local_normal;
uniform usampler2D u_instance;
layout(rg32f, binding = 0) writeonly uniform image2D u_out;

void main() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    if (any(greaterThanEqual(p, imageSize(u_out)))) return;
    uint id = texelFetch(u_instance, p, 0).r;
    vec2 ao = vec2(1.0, 0.0);
    if (id != 0u) {
        ao = psao_reconstruct(id - 1u, texelFetch(u_local, p, 0).xyz, texelFetch(u_local_normal, p, 0).xyz);
    }
    imageStore(u_out, p, vec4(ao, 0.0, 0.0));
}
