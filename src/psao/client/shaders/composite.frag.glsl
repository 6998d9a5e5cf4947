#version 410
// Composite: lit colour x AO, sRGB-encoded for PNG; background keeps the sky colour.
uniform sampler2D u_color;      // linear lit colour, alpha = 1 where covered
uniform sampler2D u_ao;         // AO in the red channel
uniform vec3 u_background;      // linear sky colour

layout(location = 0) out vec4 o_rgb;

vec3 linear_to_srgb(vec3 c) {
    c = clamp(c, 0.0, 1.0);
    return mix(12.92 * c, 1.055 * pow(c, vec3(1.0 / 2.4)) - 0.055, step(0.0031308, c));
}

void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    vec4 color = texelFetch(u_color, p, 0);
    float ao = texelFetch(u_ao, p, 0).r;
    vec3 rgb = color.a > 0.0 ? color.rgb * ao : u_background;
    o_rgb = vec4(linear_to_srgb(rgb), 1.0);
}
