// PSAO grid lookup and point decode, shared by every pass that reads the streamed AO.
// Mirrors protocol/gridformat.py (layout, hash) and protocol/pointword.py (point word, oct code) bit for
// bit; protocol/reconstruct.py is the Python oracle of psao_reconstruct() (paper eq. 2-4).
// Bindings: 0 instances, 1 buckets, 2 cells. Requires GLSL 4.30 (storage buffers).

#ifndef PSAO_T_N
#define PSAO_T_N 0.1   // eq. 3 normal threshold
#endif
#ifndef PSAO_T_D
#define PSAO_T_D 0.7   // eq. 3 distance-direction threshold
#endif

#define PSAO_EMPTY 0xFFFFFFFFu
#define PSAO_ALLOCATED 0x80000000u
#define PSAO_CELL_WORDS 8u
#define PSAO_POINTS_PER_CELL 7u
#define PSAO_KEY_WORD 7u
#define PSAO_BUCKET_ENTRIES 8u

// INSTANCE_DTYPE, 48 bytes, std430: vec3 + float packs into 16 bytes, uvec3 + uint likewise.
struct PsaoInstance {
    vec3 origin;        // local-space corner of cell (0, 0, 0)
    float cell_size;    // local units
    uvec3 dims;         // Dx, Dy, Dz
    uint bucket_offset; // first bucket of this instance
    uint bucket_count;  // B, a power of two
    float radius;       // interpolation radius r, local units
    uint flags;
    uint pad;
};

layout(std430, binding = 0) readonly buffer PsaoInstances { PsaoInstance psao_instances[]; };
layout(std430, binding = 1) readonly buffer PsaoBuckets { uint psao_buckets[]; };  // (key, slot) x 8 per bucket
layout(std430, binding = 2) readonly buffer PsaoCells { uint psao_cells[]; };      // 7 points + key per cell

// Paper eq. 1 in wrapping uint arithmetic (gridformat.cell_hash).
uint psao_cell_hash(uvec3 c, uvec3 dims) {
    return c.x + c.y * (dims.x * 17u) + c.z * (dims.x * dims.y * 31u);
}

uint psao_cell_key(uvec3 c, uvec3 dims) {
    return c.x + dims.x * (c.y + dims.y * c.z);
}

// Slot of cell c of an instance, or PSAO_EMPTY. Used entries come first, so the scan stops at EMPTY.
uint psao_find_cell(PsaoInstance inst, uvec3 c) {
    uint bucket = inst.bucket_offset + (psao_cell_hash(c, inst.dims) & (inst.bucket_count - 1u));
    uint key = psao_cell_key(c, inst.dims);
    uint base = bucket * (2u * PSAO_BUCKET_ENTRIES);
    for (uint e = 0u; e < PSAO_BUCKET_ENTRIES; ++e) {
        uint k = psao_buckets[base + 2u * e];
        if (k == PSAO_EMPTY) break;
        if (k == key) return psao_buckets[base + 2u * e + 1u];
    }
    return PSAO_EMPTY;
}

// Octahedral 4+4-bit normal code, levels 0..14 (pointword.oct_decode; level 15 clamps to 14).
vec3 psao_oct_decode(uint code) {
    float u = (float(min((code >> 4) & 0xFu, 14u)) - 7.0) / 7.0;
    float v = (float(min(code & 0xFu, 14u)) - 7.0) / 7.0;
    float z = 1.0 - abs(u) - abs(v);
    float t = max(-z, 0.0);
    vec3 n = vec3(u + (u >= 0.0 ? -t : t), v + (v >= 0.0 ? -t : t), z);
    return normalize(n);
}

// Local position of a point word in cell c (gridformat.decode_point_local): centre of its 5-bit step.
vec3 psao_point_position(PsaoInstance inst, uvec3 c, uint word) {
    uvec3 q = uvec3((word >> 16) & 0x1Fu, (word >> 21) & 0x1Fu, (word >> 26) & 0x1Fu);
    vec3 f = (vec3(q) + 0.5) / 32.0;
    return inst.origin + (vec3(c) + f) * inst.cell_size;
}

float psao_point_ao(uint word) {
    return float(word & 0xFFu) / 255.0;
}

// Paper eq. 2-3: weight of point p (normal np) for the fragment at x with normal nx, radius r.
float psao_weight(vec3 p, vec3 np, vec3 x, vec3 nx, float r) {
    vec3 d = p - x;
    float dist = length(d);
    float w = max(0.0, (r - dist) / r);
    if (w <= 0.0 || dot(np, nx) <= PSAO_T_N) return 0.0;
    if (dist > 0.0) {
        float c = dot(np, d) / dist;
        if (c * c >= PSAO_T_D) return 0.0;
    }
    return w;
}

// Paper eq. 4 over the 2x2x2 block floor(g - 0.5) + {0,1}^3 around local position x (normal nx) of
// instance `inst_id`. Returns (AO, weight sum); AO is 1 when no point has weight.
vec2 psao_reconstruct(uint inst_id, vec3 x, vec3 nx) {
    PsaoInstance inst = psao_instances[inst_id];
    vec3 g = (x - inst.origin) / inst.cell_size;
    ivec3 base = ivec3(floor(g - 0.5));
    ivec3 dims = ivec3(inst.dims);
    float wsum = 0.0;
    float aosum = 0.0;
    for (int i = 0; i < 8; ++i) {
        ivec3 c = base + ivec3(i & 1, (i >> 1) & 1, (i >> 2) & 1);
        if (any(lessThan(c, ivec3(0))) || any(greaterThanEqual(c, dims))) continue;
        uint slot = psao_find_cell(inst, uvec3(c));
        if (slot == PSAO_EMPTY) continue;
        uint cell_base = slot * PSAO_CELL_WORDS;
        for (uint k = 0u; k < PSAO_POINTS_PER_CELL; ++k) {
            uint word = psao_cells[cell_base + k];
            if ((word & PSAO_ALLOCATED) == 0u) break;
            float w = psao_weight(psao_point_position(inst, uvec3(c), word),
                                  psao_oct_decode((word >> 8) & 0xFFu), x, nx, inst.radius);
            wsum += w;
            aosum += w * psao_point_ao(word);
        }
    }
    return vec2(wsum > 0.0 ? aosum / wsum : 1.0, wsum);
}
