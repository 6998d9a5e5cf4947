// The PSAO grid lookup itself, one text for the desktop client (psao_common.glsl includes it, GLSL 4.10)
// and the web client (web/shaders/psao.frag, GLSL ES 3.00, served from this folder). The includer first
// defines the PSAO_* constants (protocol/shader_constants.define_block) and
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

// Local position of a point word in cell c (gridformat.decode_point_local): centre of its 5-bit step.
vec3 psao_point_position(PsaoInstance inst, uvec3 c, uint word) {
    uvec3 q = uvec3(word >> PSAO_SHIFT_X, word >> PSAO_SHIFT_Y, word >> PSAO_SHIFT_Z) & PSAO_POSITION_MASK;
    vec3 f = (vec3(q) + 0.5) / PSAO_POSITION_LEVELS;
    return inst.origin + (vec3(c) + f) * inst.cell_size;
}

float psao_point_ao(uint word) {
    return float(word & PSAO_CODE_MASK) / PSAO_AO_LEVELS;
}

// Paper eq. 2-3: weight of a point at offset d = p - x from the fragment (dist2 = |d|^2 < r^2), normal np,
// for the fragment normal nx and radius r.
float psao_weight(vec3 d, float dist2, vec3 np, vec3 nx, float r) {
    float dist = sqrt(dist2);
    float w = max(0.0, (r - dist) / r);
    if (w <= 0.0 || dot(np, nx) <= PSAO_T_N) return 0.0;
    if (dist > 0.0) {
        float c = dot(np, d) / dist;
        if (c * c >= PSAO_T_D) return 0.0;
    }
    return w;
}

// Adds the weighted AO of the allocated points of the cell in `slot` (cell coordinates c), radius r. A point at r or
// farther has weight 0: it is skipped before its normal is decoded (most points of a 2x2x2 block are).
void psao_accumulate(PsaoInstance inst, uvec3 c, uint slot, vec3 x, vec3 nx, float r, inout float wsum, inout float aosum) {
    uvec4 lo = psao_fetch(u_psao_cells, PSAO_CELL_TEXELS * slot);
    uvec4 hi = psao_fetch(u_psao_cells, PSAO_CELL_TEXELS * slot + 1u);
    uint words[PSAO_POINTS_PER_CELL] = uint[PSAO_POINTS_PER_CELL](lo.x, lo.y, lo.z, lo.w, hi.x, hi.y, hi.z);
    float r2 = r * r;
    for (int k = 0; k < PSAO_POINTS_PER_CELL; ++k) {  // allocated words come first
        uint word = words[k];
        if ((word & PSAO_ALLOCATED) == 0u) break;
        vec3 d = psao_point_position(inst, c, word) - x;
        float dist2 = dot(d, d);
        if (dist2 >= r2) continue;
        float w = psao_weight(d, dist2, psao_point_normal(word), nx, r);
        wsum += w;
        aosum += w * psao_point_ao(word);
    }
}

// Adds the points of cell c: the entries of its bucket with c's key (its back-side key, key | BACK_BIT,
// with `back` on a double-sided instance). A key holding more than 7 points owns up to PSAO_KEY_CELLS
// entries, and the server keeps them next to each other, so the scan stops at the key's first entry (or
// at EMPTY: used entries come first) and the accumulation reads on only while the next entry has the same
// key.
void psao_accumulate_cell(PsaoInstance inst, uvec3 c, bool back, vec3 x, vec3 nx, float r, inout float wsum, inout float aosum) {
    uint base = (inst.bucket_offset + (psao_cell_hash(c, inst.dims) & (inst.bucket_count - 1u))) * PSAO_BUCKET_TEXELS;
    uint key = psao_cell_key(c, inst.dims);
    if (back && (inst.flags & PSAO_FLAG_DOUBLE_SIDED) != 0u) key |= PSAO_BACK_BIT;
    uint e = PSAO_BUCKET_ENTRIES;  // the key's first entry
    for (uint t = 0u; t < PSAO_BUCKET_TEXELS; ++t) {
        uvec4 pair = psao_fetch(u_psao_buckets, base + t);  // two entries: (key, slot, key, slot)
        if (pair.x == key) { e = 2u * t; break; }
        if (pair.x == PSAO_EMPTY || pair.z == PSAO_EMPTY) break;
        if (pair.z == key) { e = 2u * t + 1u; break; }
    }
    // A trip count the compiler cannot bound to a constant: it keeps one copy of psao_accumulate instead of
    // unrolling PSAO_KEY_CELLS copies (measured slower on llvmpipe).
    uint cells = e < PSAO_BUCKET_ENTRIES ? min(uint(PSAO_KEY_CELLS), PSAO_BUCKET_ENTRIES - e) : 0u;
    for (uint k = 0u; k < cells; ++k, ++e) {
        uvec4 pair = psao_fetch(u_psao_buckets, base + (e >> 1u));
        uvec2 entry = (e & 1u) == 0u ? pair.xy : pair.zw;
        if (entry.x != key) break;
        psao_accumulate(inst, c, entry.y, x, nx, r, wsum, aosum);
    }
}

// Squared distance, in cells, from grid coordinate g to the unit box of cell c.
float psao_cell_distance2(vec3 g, vec3 c) {
    vec3 d = max(max(c - g, g - (c + 1.0)), 0.0);
    return dot(d, d);
}

// Paper eq. 4 over the 2x2x2 block floor(g - 0.5) + {0,1}^3 around local position x (normal nx) of
// instance `inst_id`. Where no point there has weight (a hole: a gap in the sampling wider than r, or a
// small face whose points went to its neighbours), the fallback ring: the 3x3x3 block floor(g) + {-1,0,1}^3
// with radius PSAO_FALLBACK_SCALE * r (it holds every point within one cell, s >= 2 r, of x). Returns
// (AO, weight sum); AO is 1 when even the ring finds no weight. `back`: the fragment shows the back side
// of a double-sided surface (the G-buffer flipped its normal), so only back-side cells can hold points
// that pass eq. 3's normal test: one key per cell, as for one-sided instances. One loop and one call of
// psao_accumulate_cell for both blocks keeps one copy of the lookup in the compiled shader.
vec2 psao_reconstruct(uint inst_id, vec3 x, vec3 nx, bool back) {
    PsaoInstance inst = psao_instance(inst_id);
    vec3 g = (x - inst.origin) / inst.cell_size;
    ivec3 base = ivec3(floor(g - 0.5));
    ivec3 dims = ivec3(inst.dims);
    float r = inst.radius;
    // A cell whose box is farther than r cannot hold a point with weight > 0 (small slack for rounding).
    float reach = r / inst.cell_size * 1.001;
    float reach2 = reach * reach;
    float wsum = 0.0;
    float aosum = 0.0;
    for (int i = 0; i < 8 + 27; ++i) {
        if (i == 8) {
            if (wsum > 0.0) break;
            base = ivec3(floor(g)) - 1;
            r *= PSAO_FALLBACK_SCALE;
            reach *= PSAO_FALLBACK_SCALE;
            reach2 = reach * reach;
        }
        int j = i < 8 ? i : i - 8;
        ivec3 c = i < 8 ? base + ivec3(j & 1, (j >> 1) & 1, (j >> 2) & 1) : base + ivec3(j % 3, (j / 3) % 3, j / 9);
        if (any(lessThan(c, ivec3(0))) || any(greaterThanEqual(c, dims))) continue;
        if (psao_cell_distance2(g, vec3(c)) > reach2) continue;
        psao_accumulate_cell(inst, uvec3(c), back, x, nx, r, wsum, aosum);
    }
    return vec2(wsum > 0.0 ? aosum / wsum : 1.0, wsum);
}
