// Geometry pass: mesh-local vertices with flat (face) normals, one draw per instance. A skinned mesh is
// drawn posed (in_position, in_normal) and carries its rest pose (in_rest_*: the same vertex of the same
// triangle), where the server keeps its AO points: the lookup's local position and normal are the rest
// pose's (src/psao/client/shaders/gbuffer.vert.glsl). For other meshes both pairs are the same.
layout(location = 0) in vec3 in_position;
layout(location = 1) in vec3 in_normal;
layout(location = 2) in vec3 in_rest_position;
layout(location = 3) in vec3 in_rest_normal;
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
    v_local = in_rest_position;
    v_depth = -eye.z;
    v_local_normal = in_rest_normal;
    v_world_normal = u_normal_matrix * in_normal;
    gl_Position = u_proj * eye;
}
