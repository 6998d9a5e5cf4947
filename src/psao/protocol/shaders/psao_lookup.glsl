// The PSAO grid lookup itself, one text for the desktop client (psao_common.glsl includes it, GLSL 4.10)
// and the web client (web/shaders/psao.frag, GLSL ES 3.00, served from this folder). The includer first
// defines the PSAO_* constants (src/psao/protocol/shader_constants.define_block) and
// `vec3 psao_point_normal(uint word)`: the desktop client reads the normals from a uniform array, WebGL2
// (224 fragment uniform vectors guaranteed) from a 256 x 1 texture.

struct PsaoInstance {
    vec3 origin;        // local-space corner of cell (0, 0, 0)
    float cell_size;    // local units
    uvec3 dims;         // Dx, Dy, Dz
    uint bucket_offset; // first bucket of this instance
    uint bucket_count;  // B, a power of two
    float radius;       // interpolation radius r, local units
    uint flags;
};

uniform usampler2D u_psao_instances;  // INSTANCE_DTYPE records, PSAO_INSTANCE_TEXELS texels each
uniform usampler2D u_psao_buckets;    // (key, slot) x PSAO_BUCKET_ENTRIES per bucket
uniform usampler2D u_psao_cells;      // point words + key per cell

uvec4 psao_fetch(usampler2D table, uint texel) {
    return texelFetch(table, ivec2(texel & (PSAO_TABLE_WIDTH - 1u), texel >> PSAO_TABLE_SHIFT), 0);
}

PsaoInstance psao_instance(uint id) {
    uint first = PSAO_INSTANCE_TEXELS * id;
    uvec4 a = psao_fetch(u_psao_instances, first);
    uvec4 b = psao_fetch(u_psao_instances, first + 1u);
    uvec4 c = psao_fetch(u_psao_instances, first + 2u);
    return PsaoInstance(uintBitsToFloat(a.xyz), uintBitsToFloat(a.w), b.xyz, b.w, c.x, uintBitsToFloat(c.y), c.z);
}

// Paper eq. 1 in wrapping uint arithmetic (gridformat.cell_hash).
uint psao_cell_hash(uvec3 c, uvec3 dims) {
    return c.x + c.y * (dims.x * PSAO_HASH_Y) + c.z * (dims.x * dims.y * PSAO_HASH_Z);
}

uint psao_cell_key(uvec3 c, uvec3 dims) {
    return c.x + dims.x * (c.y + dims.y * c.z);
}

float psao_point_ao(uint word) {
    return float(word & PSAO_CODE_MASK) / PSAO_AO_LEVELS;
}

// Adds the allocated points of the cell in `slot` (cell coordinates c) that pass paper eq. 3 (normal
// threshold t_n.z: n_p . n_x > t_n.z, and the tangent-plane test (n_p . d / |d|)^2 < T_d, written without the
// division as (n_p . d)^2 < T_d |d|^2, true at d = 0) to the three steps' sums, acc = (weight, weighted AO)
// of step 1 then of step 2, acc3 those of step 3: step 1 at radius r counts only points whose normal also
// passes t_n.x and whose offset passes the tangent-plane threshold first_t_d, step 2 at radius R those whose
// normal passes t_n.y, step 3 at R every one. inv_radii = (1 / r, 1 / R). Everything is in grid units (one
// cell = 1): cg is the cell's first position step relative to the fragment's grid coordinate, so a point's
// offset from the fragment is one multiply-add of its 5-bit codes. Weight max(0, 1 - d / rho)^PSAO_WEIGHT_POWER
// (paper eq. 2: power 1).
void psao_accumulate(uint slot, vec3 cg, vec3 nx, vec2 inv_radii, vec3 t_n, float first_t_d, inout vec4 acc, inout vec2 acc3) {
    uvec4 lo = psao_fetch(u_psao_cells, PSAO_CELL_TEXELS * slot);
    uvec4 hi = psao_fetch(u_psao_cells, PSAO_CELL_TEXELS * slot + 1u);
    uint words[PSAO_POINTS_PER_CELL] = uint[PSAO_POINTS_PER_CELL](lo.x, lo.y, lo.z, lo.w, hi.x, hi.y, hi.z);
    float outer2 = 1.0 / (inv_radii.y * inv_radii.y);
    for (int k = 0; k < PSAO_POINTS_PER_CELL; ++k) {  // allocated words come first
        uint word = words[k];
        if ((word & PSAO_ALLOCATED) == 0u) break;
        uvec3 q = uvec3(word >> PSAO_SHIFT_X, word >> PSAO_SHIFT_Y, word >> PSAO_SHIFT_Z) & PSAO_POSITION_MASK;
        vec3 d = cg + vec3(q) * (1.0 / PSAO_POSITION_LEVELS);
        float dist2 = dot(d, d);
        vec3 np = psao_point_normal(word);
        float ndot = dot(np, nx);
        float c = dot(np, d);
        float c2 = c * c;
        if (dist2 >= outer2 || ndot <= t_n.z || !(c2 < PSAO_T_D * dist2 || dist2 == 0.0)) continue;
        vec2 tent = max(vec2(0.0), 1.0 - sqrt(dist2) * inv_radii);
        vec2 w = tent;
        for (int p = 1; p < PSAO_WEIGHT_POWER; ++p) w *= tent;
        float w1 = (ndot > t_n.x && (c2 < first_t_d * dist2 || dist2 == 0.0)) ? w.x : 0.0;
        float w2 = ndot > t_n.y ? w.y : 0.0;
        float ao = psao_point_ao(word);
        acc += vec4(w1, w1 * ao, w2, w2 * ao);
        acc3 += vec2(w.y, w.y * ao);
    }
}

// Adds the points of cell c (g: the fragment's grid coordinate): the entries of its bucket with c's key
// (its back-side key, key | BACK_BIT, with `back` on a double-sided instance). A key holding more than 7
// points owns up to PSAO_KEY_CELLS entries, next to each other (the server keeps buckets sorted by key),
// so the scan stops at the key's first entry (or at EMPTY: used entries come first) and the cells are
// read from there while the next entry has the same key. The next entry is often in the texel the scan
// already holds; the loop's second pass runs only where some fragment's key goes on.
void psao_accumulate_cell(PsaoInstance inst, uvec3 c, bool back, vec3 g, vec3 nx, vec2 inv_radii, vec3 t_n, float first_t_d,
                          inout vec4 acc, inout vec2 acc3) {
    uint base = (inst.bucket_offset + (psao_cell_hash(c, inst.dims) & (inst.bucket_count - 1u))) * PSAO_BUCKET_TEXELS;
    uint key = psao_cell_key(c, inst.dims);
    if (back && (inst.flags & PSAO_FLAG_DOUBLE_SIDED) != 0u) key |= PSAO_BACK_BIT;
    uint e = PSAO_BUCKET_ENTRIES;  // the key's first entry
    uvec4 pair = uvec4(PSAO_EMPTY);  // the texel holding entry e: two entries (key, slot, key, slot)
    for (uint t = 0u; t < PSAO_BUCKET_TEXELS; ++t) {
        pair = psao_fetch(u_psao_buckets, base + t);
        if (pair.x == key) { e = 2u * t; break; }
        if (pair.x == PSAO_EMPTY || pair.z == PSAO_EMPTY) break;
        if (pair.z == key) { e = 2u * t + 1u; break; }
    }
    if (e == PSAO_BUCKET_ENTRIES) return;
    vec3 cg = vec3(c) + 0.5 / PSAO_POSITION_LEVELS - g;
    uint slot = (e & 1u) == 0u ? pair.y : pair.w;
    for (int k = 0; k < PSAO_KEY_CELLS; ++k) {
        psao_accumulate(slot, cg, nx, inv_radii, t_n, first_t_d, acc, acc3);
        e += 1u;
        if (e == PSAO_BUCKET_ENTRIES) break;
        if ((e & 1u) == 0u) pair = psao_fetch(u_psao_buckets, base + (e >> 1u));
        uvec2 entry = (e & 1u) == 0u ? pair.xy : pair.zw;
        if (entry.x != key) break;
        slot = entry.y;
    }
}

// Squared distance, in cells, from grid coordinate g to the unit box of cell c.
float psao_cell_distance2(vec3 g, vec3 c) {
    vec3 d = max(max(c - g, g - (c + 1.0)), 0.0);
    return dot(d, d);
}

// Paper eq. 4 at local position x (normal nx) of instance `inst_id`, the first of these steps that finds
// weight (one pass over the 2x2x2 block floor(g - 0.5) + {0,1}^3 computes the sums of steps 1-3, so steps
// 2 and 3 cost no extra cell reads):
//   1. radius r, counting only points whose normal is within PSAO_FIRST_T_N of the fragment's and that lie
//      near its tangent plane (PSAO_FIRST_T_D): the fragment's own face, not the other face at a crease;
//   2. radius R = PSAO_FALLBACK_SCALE * r, normals within PSAO_SECOND_T_N (a face narrower than r);
//   3. radius R and eq. 3 alone;
//   4. the 3x3x3 block floor(g) + {-1,0,1}^3 (every point within one cell, s >= R, of x) with radius
//      PSAO_RING_SCALE * r and eq. 3's normal threshold loosened to PSAO_RING_T_N (the faces across a sharp
//      edge). Only groups of fragments holding such a fragment run these 27 cells.
// Returns (AO, weight sum of the step that answered); AO is 1 when even step 4 finds no weight. `back`:
// the fragment shows the back side of a double-sided surface (the G-buffer flipped its normal), so only
// back-side cells can hold points that pass eq. 3's normal test: one key per cell, as for one-sided
// instances. One loop and one call of psao_accumulate_cell for both blocks keeps one copy of the lookup
// in the compiled shader; the cell offsets are stepped, not divided out of the loop counter.
vec2 psao_reconstruct(uint inst_id, vec3 x, vec3 nx, bool back) {
    PsaoInstance inst = psao_instance(inst_id);
    vec3 g = (x - inst.origin) / inst.cell_size;
    ivec3 base = ivec3(floor(g - 0.5));
    ivec3 dims = ivec3(inst.dims);
    vec2 radii = inst.radius / inst.cell_size * vec2(1.0, PSAO_FALLBACK_SCALE);  // grid units
    // A cell whose box is farther than R cannot hold a point with weight > 0 (small slack for rounding).
    float reach = radii.y * 1.001;
    float reach2 = reach * reach;
    vec2 inv_radii = 1.0 / radii;
    vec4 acc = vec4(0.0);  // (weight sum, weighted AO) of step 1, then of step 2
    vec2 acc3 = vec2(0.0); // the same of step 3
    vec3 t_n = vec3(PSAO_FIRST_T_N, PSAO_SECOND_T_N, PSAO_T_N);  // normal thresholds of steps 1-3; step 4's
    float first_t_d = PSAO_FIRST_T_D;
    int side = 2;          // the block's edge in cells: 2, then 3 for step 4
    ivec3 o = ivec3(0);    // the cell's offset in the block
    for (int i = 0; i < 8 + 27; ++i) {
        ivec3 c = base + o;
        if (all(greaterThanEqual(c, ivec3(0))) && all(lessThan(c, dims)) && psao_cell_distance2(g, vec3(c)) <= reach2)
            psao_accumulate_cell(inst, uvec3(c), back, g, nx, inv_radii, t_n, first_t_d, acc, acc3);
        o.x += 1;
        if (o.x == side) { o.x = 0; o.y += 1; }
        if (o.y == side) { o.y = 0; o.z += 1; }
        if (i + 1 == 8) {  // the 2x2x2 block is done: the loop ends here unless step 4 is needed
            if (acc3.x > 0.0) break;
            base = ivec3(floor(g)) - 1;
            side = 3;
            o = ivec3(0);
            float ring = radii.x * PSAO_RING_SCALE;
            inv_radii = vec2(1.0 / ring);  // every step now sums the ring's points alike
            reach2 = (ring * 1.001) * (ring * 1.001);
            t_n = vec3(PSAO_RING_T_N);
            first_t_d = PSAO_T_D;
        }
    }
    if (acc.x > 0.0) return vec2(acc.y / acc.x, acc.x);
    if (acc.z > 0.0) return vec2(acc.w / acc.z, acc.z);
    return vec2(acc3.x > 0.0 ? acc3.y / acc3.x : 1.0, acc3.x);
}
