// Composite: lit colour x AO (PSAO, SSAO, none, or the AO alone), sRGB-encoded; background sky colour.
uniform highp sampler2D u_color;
uniform highp sampler2D u_ao;
uniform vec3 u_background;
uniform int u_mode;  // 0 colour x AO, 1 colour only, 2 AO only
out vec4 o_rgb;
vec3 linear_to_srgb(vec3 c) {
    c = clamp(c, 0.0, 1.0);
    return mix(12.92 * c, 1.055 * pow(c, vec3(1.0 / 2.4)) - 0.055, step(0.0031308, c));
}
void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    vec4 color = texelFetch(u_color, p, 0);
    float ao = texelFetch(u_ao, p, 0).r;
    vec3 rgb = color.a > 0.0 ? (u_mode == 2 ? vec3(ao) : u_mode == 1 ? color.rgb : color.rgb * ao) : u_background;
    o_rgb = vec4(u_mode == 2 ? rgb : linear_to_srgb(rgb), 1.0);
}
