// Geometry pass: mesh-local vertices with flat (face) normals, one draw per instance.
layout(location = 0) in vec3 in_position;
layout(location = 1) in vec3 in_normal;
uniform mat4 u_model;          // local -> world (the last transform received from the server)
uniform mat4 u_view;
uniform mat4 u_proj;
uniform mat3 u_normal_matrix;  // inverse transpose of the model's linear part
out vec3 v_local;
out float v_depth;
flat out vec3 v_local_normal;
flat out vec3 v_world_normal;
void main() {
    vec4 world = u_model * vec4(in_position, 1.0);
    vec4 eye = u_view * world;
    v_local = in_position;
    v_depth = -eye.z;
    v_local_normal = in_normal;
    v_world_normal = u_normal_matrix * in_normal;
    gl_Position = u_proj * eye;
}
