#version 410
// G-buffer: everything later passes need, at full float precision (PSAO reads the local position and
// normal exactly as src/psao/protocol/reconstruct.py receives them in the tests).
in vec3 v_world;
in vec3 v_local;
in float v_depth;
flat in vec3 v_local_normal;
flat in vec3 v_world_normal;

uniform vec3 u_albedo;          // linear RGB
uniform uint u_instance;        // instance index
uniform bool u_double_sided;    // back faces show the other side: flip the normal towards the camera
uniform bool u_mirrored;        // model transform has a negative determinant: winding is reversed
uniform vec3 u_light_dir;       // unit, towards the light, world space
uniform float u_ambient;        // ambient term
uniform float u_diffuse;        // directional term

layout(location = 0) out vec4 o_world;         // xyz world position, w = 1 where covered
layout(location = 1) out vec4 o_normal;        // xyz world normal (unit)
layout(location = 2) out vec4 o_local;         // xyz instance-local position (a skinned mesh's rest pose)
layout(location = 3) out vec4 o_local_normal;  // xyz instance-local normal (unit, rest pose), w = 1 on a back side
layout(location = 4) out vec4 o_color;         // lit colour without AO, linear
layout(location = 5) out uint o_instance;      // instance index + 1, 0 = background
layout(location = 6) out float o_depth;        // view depth, 0 = background

void main() {
    vec3 n_local = normalize(v_local_normal);
    vec3 n_world = normalize(v_world_normal);
    bool front = gl_FrontFacing != u_mirrored;
    bool back_side = u_double_sided && !front;  // PSAO looks this side up in the back-side cells
    if (back_side) {
        n_local = -n_local;
        n_world = -n_world;
    }
    float light = u_ambient + u_diffuse * max(dot(n_world, u_light_dir), 0.0);
    o_world = vec4(v_world, 1.0);
    o_normal = vec4(n_world, 0.0);
    o_local = vec4(v_local, 1.0);
    o_local_normal = vec4(n_local, back_side ? 1.0 : 0.0);
    o_color = vec4(u_albedo * light, 1.0);
    o_instance = u_instance + 1u;
    o_depth = v_depth;
}
