/* The offline renderer: one work-item per pixel casts samples x samples
 * primary rays on a fixed sub-pixel grid through a BVH (bvh.py), with
 * alpha-tested textured triangles, and ao_rays cosine-weighted AO rays per
 * covered sample whose directions are counter-based hashes of (seed,
 * pixel, sample, ray). Each pixel's sums run in a fixed order inside its
 * work-item, so the image does not depend on the work-group size.
 *
 * Layouts (float32 unless said):
 *   cam[16]    eye, forward, right*half_w, up*half_h, ortho flag (scene.py)
 *   nodes[32n] four-wide BVH nodes (bvh.WideBVH): min x, y, z and max x, y, z of the
 *              four children (a float4 each), their refs and counts (int4 bits)
 *   tris[48b]  the leaves' blocks of four triangle slots (__init__.triangle_blocks), a
 *              float4 row each of p0.x .. p0.z, e1.x .. e1.z, e2.x .. e2.z (e = p - p0),
 *              scene triangle id and texture (int bits, -1 none), pad
 *   tri_nrm[9s], tri_uv[6s]: the corners per slot; tri_tint[3s]
 *   tex_min_alpha[k]: a texture's least alpha (at or above the threshold: no alpha test)
 *   tex[k*H*W*4] RGBA rows top first
 *   outputs per pixel: albedo[3], alpha, normal[3], depth, ao
 */

#define STACK 80

inline uint mix32(uint x)
{
    x ^= x >> 16; x *= 0x7feb352dU; x ^= x >> 15; x *= 0x846ca68bU; x ^= x >> 16;
    return x;
}

inline float unit_random(uint seed, uint pixel, uint stream)
{
    const uint h = mix32(mix32(mix32(seed ^ 0x9e3779b9U) ^ pixel) ^ stream);
    return (float)(h >> 8) * (1.0f / 16777216.0f);
}

inline float3 load3(__global const float *a, int i) { return (float3)(a[3 * i], a[3 * i + 1], a[3 * i + 2]); }

/* RGBA of the texel under barycentric (b1, b2) of triangle tri in texture k. */
inline float4 texel(__global const float *tri_uv, __global const float *tex, int tw, int th, int tri, int k,
                    float b1, float b2)
{
    const float b0 = 1.0f - b1 - b2;
    const float u = b0 * tri_uv[6 * tri] + b1 * tri_uv[6 * tri + 2] + b2 * tri_uv[6 * tri + 4];
    const float v = b0 * tri_uv[6 * tri + 1] + b1 * tri_uv[6 * tri + 3] + b2 * tri_uv[6 * tri + 5];
    const float fu = u - floor(u), fv = v - floor(v);
    const int x = min((int)(fu * (float)tw), tw - 1);
    const int y = min((int)((1.0f - fv) * (float)th), th - 1);
    return vload4((k * th + y) * tw + x, tex);
}

/* Closest (any_hit = 0) or any (1) alpha-passing hit with t in (tmin, tmax),
 * through the four-wide BVH (bvh.widen): a node's four child boxes are tested
 * at once in float4 lanes (the slab test; NaN slabs, a ray in a box face, are
 * dropped by fmin/fmax), and the children entered are pushed nearest on top,
 * each with its entry distance, which culls it when it is popped behind the
 * best hit so far. Stack entries: a node's index, or a leaf as
 * -(first * 16 + count) - 1. Of hits at exactly the same distance the one
 * with the smallest scene triangle id wins, as in the numpy reference: the
 * result does not depend on the order the BVH visits triangles in. */
inline int trace(float3 o, float3 d, float tmin, float tmax, int any_hit,
                 __global const float4 *nodes, __global const float4 *tris, __global const float *tri_uv,
                 __global const float *tex_min_alpha, __global const float *tex, int tw, int th, float alpha_threshold,
                 float *t_out, float *b1_out, float *b2_out)
{
    const float3 inv = (float3)(1.0f / d.x, 1.0f / d.y, 1.0f / d.z);
    const float4 ox = (float4)(o.x), oy = (float4)(o.y), oz = (float4)(o.z);
    const float4 ix = (float4)(inv.x), iy = (float4)(inv.y), iz = (float4)(inv.z);
    int stack[STACK];
    float stack_enter[STACK];
    int sp = 1;
    stack[0] = 0;
    stack_enter[0] = tmin;
    int best = -1, best_id = 0;
    float tbest = tmax;
    while (sp > 0) {
        --sp;
        if (stack_enter[sp] > tbest) continue;
        const int ref = stack[sp];
        if (ref >= 0) {
            __global const float4 *nd = nodes + 8 * ref;
            const float4 tx0 = (nd[0] - ox) * ix, tx1 = (nd[3] - ox) * ix;
            const float4 ty0 = (nd[1] - oy) * iy, ty1 = (nd[4] - oy) * iy;
            const float4 tz0 = (nd[2] - oz) * iz, tz1 = (nd[5] - oz) * iz;
            const float4 enter = fmax(fmax(fmin(tx0, tx1), fmin(ty0, ty1)), fmax(fmin(tz0, tz1), (float4)(tmin)));
            const float4 leave = fmin(fmin(fmax(tx0, tx1), fmax(ty0, ty1)), fmin(fmax(tz0, tz1), (float4)(tbest)));
            const int4 refs = as_int4(nd[6]), counts = as_int4(nd[7]);
            const int base = sp;
#define PUSH_LANE(c)                                                                                      \
            if (counts.c >= 0 && !(enter.c > leave.c) && sp < STACK) {                                    \
                const int item = counts.c == 0 ? refs.c : -(refs.c * 16 + counts.c) - 1;                 \
                const float e = enter.c;                                                                  \
                int j = sp++;                                                                             \
                while (j > base && stack_enter[j - 1] < e) {                                              \
                    stack[j] = stack[j - 1]; stack_enter[j] = stack_enter[j - 1]; --j;                    \
                }                                                                                         \
                stack[j] = item; stack_enter[j] = e;                                                      \
            }
            PUSH_LANE(s0) PUSH_LANE(s1) PUSH_LANE(s2) PUSH_LANE(s3)
#undef PUSH_LANE
            continue;
        }
        /* a leaf: its block of four triangles tested at once (Moller-Trumbore in float4 lanes) */
        const int block = (-ref - 1) >> 4;
        __global const float4 *bl = tris + 12 * block;
        const float4 dx = (float4)(d.x), dy = (float4)(d.y), dz = (float4)(d.z);
        const float4 e1x = bl[3], e1y = bl[4], e1z = bl[5], e2x = bl[6], e2y = bl[7], e2z = bl[8];
        const float4 pvx = dy * e2z - dz * e2y, pvy = dz * e2x - dx * e2z, pvz = dx * e2y - dy * e2x;
        const float4 det = e1x * pvx + e1y * pvy + e1z * pvz;
        const float4 inv_det = 1.0f / det;
        const float4 tvx = ox - bl[0], tvy = oy - bl[1], tvz = oz - bl[2];
        const float4 b1 = (tvx * pvx + tvy * pvy + tvz * pvz) * inv_det;
        const float4 qvx = tvy * e1z - tvz * e1y, qvy = tvz * e1x - tvx * e1z, qvz = tvx * e1y - tvy * e1x;
        const float4 b2 = (dx * qvx + dy * qvy + dz * qvz) * inv_det;
        const float4 t = (e2x * qvx + e2y * qvy + e2z * qvz) * inv_det;
        const int4 ok = (fabs(det) >= (float4)(1e-20f)) & (b1 >= (float4)(0.0f)) & (b1 <= (float4)(1.0f)) &
                        (b2 >= (float4)(0.0f)) & (b1 + b2 <= (float4)(1.0f)) & (t > (float4)(tmin)) &
                        (t <= (float4)(tbest));
        if (!any(ok)) continue;
        const int4 ids = as_int4(bl[9]), texs = as_int4(bl[10]);
#define HIT_LANE(c, lane)                                                                                 \
        if (ok.c && t.c <= tbest && !(t.c == tbest && (best < 0 || ids.c > best_id))) {                  \
            const int k = texs.c;                                                                         \
            if (k < 0 || tex_min_alpha[k] >= alpha_threshold ||                                           \
                texel(tri_uv, tex, tw, th, 4 * block + lane, k, b1.c, b2.c).w >= alpha_threshold) {      \
                best = 4 * block + lane; best_id = ids.c; tbest = t.c; *b1_out = b1.c; *b2_out = b2.c;    \
                if (any_hit) { *t_out = tbest; return best; }                                             \
            }                                                                                             \
        }
        HIT_LANE(s0, 0) HIT_LANE(s1, 1) HIT_LANE(s2, 2) HIT_LANE(s3, 3)
#undef HIT_LANE
    }
    *t_out = tbest;
    return best;
}

__kernel void render(int width, int height, int samples, int ao_rays, float ao_radius, float alpha_threshold,
                     uint seed, float max_depth, int tw, int th,
                     __global const float *cam, __global const float4 *nodes, __global const float4 *tris,
                     __global const float *tri_nrm, __global const float *tri_uv, __global const float *tri_tint,
                     __global const float *tex_min_alpha, __global const float *tex,
                     __global float *out_albedo, __global float *out_alpha, __global float *out_normal,
                     __global float *out_depth, __global float *out_ao)
{
    const int px = get_global_id(0), py = get_global_id(1);
    if (px >= width || py >= height) return;
    const uint pixel = (uint)(py * width + px);
    const float3 eye = (float3)(cam[0], cam[1], cam[2]);
    const float3 fwd = (float3)(cam[3], cam[4], cam[5]);
    const float3 right = (float3)(cam[6], cam[7], cam[8]);
    const float3 up = (float3)(cam[9], cam[10], cam[11]);
    const int ortho = cam[12] > 0.5f;
    float3 albedo = (float3)(0.0f), normal = (float3)(0.0f);
    float covered = 0.0f, depth = INFINITY, open_sum = 0.0f;
    for (int sy = 0; sy < samples; ++sy)
        for (int sx = 0; sx < samples; ++sx) {
            const float x = 2.0f * (((float)px + ((float)sx + 0.5f) / (float)samples) / (float)width) - 1.0f;
            const float y = 1.0f - 2.0f * (((float)py + ((float)sy + 0.5f) / (float)samples) / (float)height);
            float3 o, d;
            if (ortho) { o = eye + x * right + y * up; d = fwd; }
            else { o = eye; d = normalize(fwd + x * right + y * up); }
            float t, b1, b2;
            const int tri = trace(o, d, 0.0f, max_depth, 0, nodes, tris, tri_uv, tex_min_alpha, tex, tw, th,
                                  alpha_threshold, &t, &b1, &b2);
            if (tri < 0) continue;
            const float b0 = 1.0f - b1 - b2;
            __global const float *lanes = (__global const float *)tris + 48 * (tri >> 2) + (tri & 3);
            const float3 e1 = (float3)(lanes[12], lanes[16], lanes[20]), e2 = (float3)(lanes[24], lanes[28], lanes[32]);
            const int k = as_int(lanes[40]);
            const float4 rgba = k >= 0 ? texel(tri_uv, tex, tw, th, tri, k, b1, b2) : (float4)(1.0f);
            const float3 tint = load3(tri_tint, tri);
            float3 ng = normalize(cross(e1, e2));
            float3 ns = b0 * load3(tri_nrm, 3 * tri) + b1 * load3(tri_nrm, 3 * tri + 1) + b2 * load3(tri_nrm, 3 * tri + 2);
            const float len_ns = length(ns);
            ns = len_ns > 1e-12f ? ns / len_ns : ng;
            if (dot(ng, d) > 0.0f) { ng = -ng; ns = -ns; }
            covered += 1.0f;
            albedo += tint * rgba.xyz;
            normal += ns;
            depth = fmin(depth, t);
            if (ao_rays > 0) {
                const float3 hit = o + t * d + 1e-4f * ng;
                /* a tangent frame about ns (Duff et al. 2017) */
                const float sgn = ns.z >= 0.0f ? 1.0f : -1.0f;
                const float a = -1.0f / (sgn + ns.z);
                const float bb = ns.x * ns.y * a;
                const float3 t1v = (float3)(1.0f + sgn * ns.x * ns.x * a, sgn * bb, -sgn * ns.x);
                const float3 t2v = (float3)(bb, sgn + ns.y * ns.y * a, -ns.y);
                const uint sub = (uint)(sy * samples + sx);
                int open = 0;
                for (int k = 0; k < ao_rays; ++k) {
                    const uint stream = (sub * (uint)ao_rays + (uint)k) * 2U;
                    const float u1 = unit_random(seed, pixel, stream), u2 = unit_random(seed, pixel, stream + 1U);
                    const float r = sqrt(u1), phi = 6.2831853f * u2;
                    const float3 dir = r * cos(phi) * t1v + r * sin(phi) * t2v + sqrt(fmax(0.0f, 1.0f - u1)) * ns;
                    float ta, c1, c2;
                    if (trace(hit, dir, 0.0f, ao_radius, 1, nodes, tris, tri_uv, tex_min_alpha, tex, tw, th,
                              alpha_threshold, &ta, &c1, &c2) < 0)
                        ++open;
                }
                open_sum += (float)open / (float)ao_rays;
            }
        }
    const float n = (float)(samples * samples);
    out_albedo[3 * pixel] = albedo.x / n;
    out_albedo[3 * pixel + 1] = albedo.y / n;
    out_albedo[3 * pixel + 2] = albedo.z / n;
    out_alpha[pixel] = covered / n;
    const float3 nm = covered > 0.0f ? normal / covered : (float3)(0.0f);
    out_normal[3 * pixel] = nm.x;
    out_normal[3 * pixel + 1] = nm.y;
    out_normal[3 * pixel + 2] = nm.z;
    out_depth[pixel] = depth;
    out_ao[pixel] = (covered > 0.0f && ao_rays > 0) ? open_sum / covered : 1.0f;
}
