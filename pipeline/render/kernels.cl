/* The offline renderer: one work-item per pixel casts samples x samples
 * primary rays on a fixed sub-pixel grid through a BVH (bvh.py), with
 * alpha-tested textured triangles, and ao_rays cosine-weighted AO rays per
 * covered sample whose directions are counter-based hashes of (seed,
 * pixel, sample, ray). Each pixel's sums run in a fixed order inside its
 * work-item, so the image does not depend on the work-group size.
 *
 * Layouts (float32 unless said):
 *   cam[16]    eye, forward, right*half_w, up*half_h, ortho flag (scene.py)
 *   nodes[8n]  bmin.xyz, first|child (int bits), bmax.xyz, count (int bits)
 *   tri_pos[9m], tri_nrm[9m], tri_uv[6m]: the corners of the triangles in BVH leaf order
 *   tri_tint[3m], tri_tex[m] (int, -1 none), tex[k*H*W*4] RGBA rows top first
 *   outputs per pixel: albedo[3], alpha, normal[3], depth, ao
 */

#define STACK 64

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

/* Alpha of the texel under (u, v) of triangle tri; 1 for untextured ones. */
inline float texel_alpha(__global const float *tri_uv, __global const int *tri_tex, __global const float *tex,
                         int tw, int th, int tri, float b1, float b2, float4 *rgba)
{
    const int k = tri_tex[tri];
    if (k < 0) { *rgba = (float4)(1.0f, 1.0f, 1.0f, 1.0f); return 1.0f; }
    const float b0 = 1.0f - b1 - b2;
    const float u = b0 * tri_uv[6 * tri] + b1 * tri_uv[6 * tri + 2] + b2 * tri_uv[6 * tri + 4];
    const float v = b0 * tri_uv[6 * tri + 1] + b1 * tri_uv[6 * tri + 3] + b2 * tri_uv[6 * tri + 5];
    const float fu = u - floor(u), fv = v - floor(v);
    const int x = min((int)(fu * (float)tw), tw - 1);
    const int y = min((int)((1.0f - fv) * (float)th), th - 1);
    const int at = ((k * th + y) * tw + x) * 4;
    *rgba = (float4)(tex[at], tex[at + 1], tex[at + 2], tex[at + 3]);
    return tex[at + 3];
}

/* Closest (any_hit = 0) or any (1) alpha-passing hit with t in (tmin, tmax). */
inline int trace(float3 o, float3 d, float tmin, float tmax, int any_hit,
                 __global const float *nodes, __global const float *tri_pos, __global const float *tri_uv,
                 __global const int *tri_tex, __global const float *tex, int tw, int th, float alpha_threshold,
                 float *t_out, float *b1_out, float *b2_out)
{
    const float3 inv = (float3)(1.0f / d.x, 1.0f / d.y, 1.0f / d.z);
    int stack[STACK];
    int sp = 0;
    stack[sp++] = 0;
    int best = -1;
    float tbest = tmax;
    while (sp > 0) {
        const int ni = stack[--sp];
        __global const float *nd = nodes + 8 * ni;
        const float3 t0 = ((float3)(nd[0], nd[1], nd[2]) - o) * inv;
        const float3 t1 = ((float3)(nd[4], nd[5], nd[6]) - o) * inv;
        const float3 tlo = fmin(t0, t1), thi = fmax(t0, t1);
        const float enter = fmax(fmax(tlo.x, tlo.y), fmax(tlo.z, tmin));
        const float leave = fmin(fmin(thi.x, thi.y), fmin(thi.z, tbest));
        if (enter > leave) continue;
        const int first = as_int(nd[3]);
        const int count = as_int(nd[7]);
        if (count == 0) {
            if (sp + 2 > STACK) continue; /* cannot happen for depth_bound < STACK (checked on the host) */
            stack[sp++] = first + 1;
            stack[sp++] = first;
            continue;
        }
        for (int tri = first; tri < first + count; ++tri) {
            const float3 p0 = load3(tri_pos, 3 * tri), p1 = load3(tri_pos, 3 * tri + 1), p2 = load3(tri_pos, 3 * tri + 2);
            const float3 e1 = p1 - p0, e2 = p2 - p0;
            const float3 pv = cross(d, e2);
            const float det = dot(e1, pv);
            if (fabs(det) < 1e-20f) continue;
            const float inv_det = 1.0f / det;
            const float3 tv = o - p0;
            const float b1 = dot(tv, pv) * inv_det;
            if (b1 < 0.0f || b1 > 1.0f) continue;
            const float3 qv = cross(tv, e1);
            const float b2 = dot(d, qv) * inv_det;
            if (b2 < 0.0f || b1 + b2 > 1.0f) continue;
            const float t = dot(e2, qv) * inv_det;
            if (t <= tmin || t >= tbest) continue;
            float4 rgba;
            if (texel_alpha(tri_uv, tri_tex, tex, tw, th, tri, b1, b2, &rgba) < alpha_threshold) continue;
            best = tri; tbest = t; *b1_out = b1; *b2_out = b2;
            if (any_hit) { *t_out = t; return best; }
        }
    }
    *t_out = tbest;
    return best;
}

__kernel void render(int width, int height, int samples, int ao_rays, float ao_radius, float alpha_threshold,
                     uint seed, int tw, int th,
                     __global const float *cam, __global const float *nodes,
                     __global const float *tri_pos, __global const float *tri_nrm, __global const float *tri_uv,
                     __global const float *tri_tint, __global const int *tri_tex, __global const float *tex,
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
            const int tri = trace(o, d, 0.0f, INFINITY, 0, nodes, tri_pos, tri_uv, tri_tex, tex, tw, th,
                                  alpha_threshold, &t, &b1, &b2);
            if (tri < 0) continue;
            const float b0 = 1.0f - b1 - b2;
            float4 rgba;
            texel_alpha(tri_uv, tri_tex, tex, tw, th, tri, b1, b2, &rgba);
            const float3 tint = load3(tri_tint, tri);
            const float3 p0 = load3(tri_pos, 3 * tri), p1 = load3(tri_pos, 3 * tri + 1), p2 = load3(tri_pos, 3 * tri + 2);
            float3 ng = normalize(cross(p1 - p0, p2 - p0));
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
                    if (trace(hit, dir, 0.0f, ao_radius, 1, nodes, tri_pos, tri_uv, tri_tex, tex, tw, th,
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
