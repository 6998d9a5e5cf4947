// PSAO pass: AO per pixel from the streamed grid (paper eq. 2-4), the same lookup as the desktop client.
uniform highp sampler2D u_local;
uniform highp sampler2D u_local_normal;
layout(location = 0) out vec4 o_ao;  // (AO, weight sum, 0, 1); background (1, 0)
void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    vec4 local = texelFetch(u_local, p, 0);
    if (local.w < 0.5) {
        o_ao = vec4(1.0, 0.0, 0.0, 1.0);
        return;
    }
    vec4 n = texelFetch(u_local_normal, p, 0);
    o_ao = vec4(psao_reconstruct(uint(local.w + 0.5) - 1u, local.xyz, n.xyz, n.w > 0.5), 0.0, 1.0);
}
