#version 410
// AO baking with a feed-forward network (Erra et al.): one small network per rigid object maps the
// object-space normal to AO. The network is trained on 16 normals around each point; at run time the
// paper feeds the fragment's own normal to all 16 inputs, so the first layer's 16 weight blocks are
// summed into one 3 x MLP_H0 block on upload (src/psao/client/render/mlp_pass.py packs the texture).
// Row `instance` of u_weights: W0 (3 x MLP_H0, row-major), b0, W1 (MLP_H0 x MLP_H1), b1, W2 (MLP_H1), b2.
#ifndef MLP_H0
#define MLP_H0 32
#endif
#ifndef MLP_H1
#define MLP_H1 16
#endif

uniform sampler2D u_local_normal;  // xyz instance-local normal (flipped on a back side)
uniform usampler2D u_instance;     // instance index + 1, 0 = background
uniform sampler2D u_weights;       // RGBA32F, one row of packed floats per instance

layout(location = 0) out float o_ao;

float weight(int row, int i) {
    return texelFetch(u_weights, ivec2(i >> 2, row), 0)[i & 3];
}

void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    uint id = texelFetch(u_instance, p, 0).r;
    if (id == 0u) {
        o_ao = 1.0;
        return;
    }
    int row = int(id) - 1;
    vec3 n = normalize(texelFetch(u_local_normal, p, 0).xyz);
    const int B0 = 3 * MLP_H0;
    const int W1 = B0 + MLP_H0;
    const int B1 = W1 + MLP_H0 * MLP_H1;
    const int W2 = B1 + MLP_H1;
    const int B2 = W2 + MLP_H1;
    float h0[MLP_H0];
    for (int j = 0; j < MLP_H0; ++j) {
        float z = weight(row, B0 + j);
        for (int k = 0; k < 3; ++k) z += n[k] * weight(row, k * MLP_H0 + j);
        h0[j] = tanh(z);
    }
    float ao = weight(row, B2);
    for (int j = 0; j < MLP_H1; ++j) {
        float z = weight(row, B1 + j);
        for (int k = 0; k < MLP_H0; ++k) z += h0[k] * weight(row, W1 + k * MLP_H1 + j);
        ao += tanh(z) * weight(row, W2 + j);
    }
    o_ao = clamp(ao, 0.0, 1.0);
}
