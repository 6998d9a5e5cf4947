// G-buffer in 4 targets (WebGL2 guarantees 4 draw buffers): what PSAO, SSAO and the composite read.
in vec3 v_local;
in float v_depth;
flat in vec3 v_local_normal;
flat in vec3 v_world_normal;
uniform vec3 u_albedo;
uniform float u_instance;      // instance index + 1
uniform bool u_double_sided;
uniform bool u_mirrored;
uniform vec3 u_light_dir;
uniform float u_ambient;
uniform float u_diffuse;
layout(location = 0) out vec4 o_local;         // instance-local position, w = instance index + 1 (0: background)
layout(location = 1) out vec4 o_local_normal;  // instance-local normal, w = 1 on the back side of a double-sided mesh
layout(location = 2) out vec4 o_normal_depth;  // world normal, w = view depth
layout(location = 3) out vec4 o_color;         // lit colour without AO, linear
void main() {
    vec3 n_local = normalize(v_local_normal);
    vec3 n_world = normalize(v_world_normal);
    bool front = gl_FrontFacing != u_mirrored;
    bool back_side = u_double_sided && !front;
    if (back_side) {
        n_local = -n_local;
        n_world = -n_world;
    }
    float light = u_ambient + u_diffuse * max(dot(n_world, u_light_dir), 0.0);
    o_local = vec4(v_local, u_instance);
    o_local_normal = vec4(n_local, back_side ? 1.0 : 0.0);
    o_normal_depth = vec4(n_world, v_depth);
    o_color = vec4(u_albedo * light, 1.0);
}
