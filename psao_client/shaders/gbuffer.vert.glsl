#version 410
// Geometry pass: mesh-local vertices with flat (face) normals, one draw per instance.
layout(location = 0) in vec3 in_position;  // mesh-local
layout(location = 1) in vec3 in_normal;    // mesh-local face normal (unit)

uniform mat4 u_model;          // local -> world (the last transform received from the server)
uniform mat4 u_view;           // world -> camera
uniform mat4 u_proj;           // camera -> clip
uniform mat3 u_normal_matrix;  // inverse transpose of the model's linear part

out vec3 v_world;
out vec3 v_local;
out float v_depth;             // distance along the view axis, > 0 in front of the camera
flat out vec3 v_local_normal;
flat out vec3 v_world_normal;

void main() {
    vec4 world = u_model * vec4(in_position, 1.0);
    vec4 eye = u_view * world;
    v_world = world.xyz;
    v_local = in_position;
    v_depth = -eye.z;
    v_local_normal = in_normal;
    v_world_normal = u_normal_matrix * in_normal;
    gl_Position = u_proj * eye;
}
