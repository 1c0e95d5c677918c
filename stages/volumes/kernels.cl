/* Volume kernels: surface samples of textured triangles (voxelization) and
 * front-to-back compositing of a voxel grid (the error views).
 * Both one work-item per output record (triangle, pixel): no atomics, no
 * shared memory, so results do not depend on the work-group size. float64
 * throughout so the numpy reference (reference.py) gives the same numbers.
 */
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL EXTENSION cl_khr_int64_base_atomics : enable

/* Triangle t's corners, normals and uv into p, n, w; returns the weight
 * (m^2) of each of its m^2 samples. */
static double load_triangle(__global const double *pos, __global const double *nrm, __global const double *uv,
                            const int t, const int m, double *p, double *n, double *w)
{
    for (int i = 0; i < 9; ++i) { p[i] = pos[9 * t + i]; n[i] = nrm[9 * t + i]; }
    for (int i = 0; i < 6; ++i) w[i] = uv[6 * t + i];
    const double e1x = p[3] - p[0], e1y = p[4] - p[1], e1z = p[5] - p[2];
    const double e2x = p[6] - p[0], e2y = p[7] - p[1], e2z = p[8] - p[2];
    const double cx = e1y * e2z - e1z * e2y, cy = e1z * e2x - e1x * e2z, cz = e1x * e2y - e1y * e2x;
    const double area = 0.5 * sqrt(cx * cx + cy * cy + cz * cz);
    return area / ((double)m * (double)m);
}

/* Sample (b0, b1, b2) of a triangle (corners p, normals n, uv w, tint,
 * texture k or -1): its albedo (tint x the texel under it, nearest,
 * wrapping uv, as worldlib/render), its voxel (x fastest, clamped to the
 * grid) and its interpolated unit normal; 0 where the texel's alpha fails
 * the test (no surface: the alpha test of the cards), else 1. */
static int sample_at(const double *p, const double *n, const double *w, __global const double *tint, const int k,
                     __global const float *textures, const int tw, const int th, const float alpha_threshold,
                     const double b0, const double b1, const double b2, const double ox, const double oy,
                     const double oz, const double voxel, const int nx, const int ny, const int nz,
                     double *rgb, double *q, long *at)
{
    rgb[0] = tint[0]; rgb[1] = tint[1]; rgb[2] = tint[2];
    int keep = 1;
    if (k >= 0) {
        const double u = b0 * w[0] + b1 * w[2] + b2 * w[4];
        const double v = b0 * w[1] + b1 * w[3] + b2 * w[5];
        const double fu = u - floor(u), fv = v - floor(v);
        const int x = min((int)(fu * (double)tw), tw - 1);
        const int y = min((int)((1.0 - fv) * (double)th), th - 1);
        __global const float *texel = textures + 4 * (((long)k * th + y) * tw + x);
        rgb[0] *= (double)texel[0]; rgb[1] *= (double)texel[1]; rgb[2] *= (double)texel[2];
        keep = (double)texel[3] >= (double)alpha_threshold;
    }
    const double px = b0 * p[0] + b1 * p[3] + b2 * p[6];
    const double py = b0 * p[1] + b1 * p[4] + b2 * p[7];
    const double pz = b0 * p[2] + b1 * p[5] + b2 * p[8];
    const int ix = clamp((int)floor((px - ox) / voxel), 0, nx - 1);
    const int iy = clamp((int)floor((py - oy) / voxel), 0, ny - 1);
    const int iz = clamp((int)floor((pz - oz) / voxel), 0, nz - 1);
    q[0] = b0 * n[0] + b1 * n[3] + b2 * n[6];
    q[1] = b0 * n[1] + b1 * n[4] + b2 * n[7];
    q[2] = b0 * n[2] + b1 * n[5] + b2 * n[8];
    const double ql = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2]);
    if (ql > 0.0) { q[0] /= ql; q[1] /= ql; q[2] /= ql; }
    *at = ((long)iz * ny + iy) * nx + ix;
    return keep;
}

/* The centroids of a triangle's m^2 sub-triangles (a regular barycentric
 * grid), in the reference's order: the m (m + 1) / 2 upright ones row by
 * row, then the m (m - 1) / 2 inverted ones. Start with sub_grid(m); each
 * sub_next gives the next centroid's barycentric coordinates, 0 after the last. */
typedef struct { int m, up, i, j; } SubGrid;

static SubGrid sub_grid(const int m)
{
    SubGrid g = {m, 1, 0, 0};
    return g;
}

static int sub_next(SubGrid *g, double *b0, double *b1, double *b2)
{
    for (;;) {
        if (g->up < 0) return 0;
        const int rows = g->up ? g->m : g->m - 1;
        if (g->i >= rows) { --g->up; g->i = 0; g->j = 0; continue; }
        if (g->j >= rows - g->i) { ++g->i; g->j = 0; continue; }
        const double shift = g->up ? 1.0 / 3.0 : 2.0 / 3.0;
        *b1 = ((double)g->i + shift) / (double)g->m;
        *b2 = ((double)g->j + shift) / (double)g->m;
        *b0 = 1.0 - *b1 - *b2;
        ++g->j;
        return 1;
    }
}

/* One work-item per triangle. Triangle t is cut into m[t]^2 equal
 * sub-triangles (a regular barycentric grid); a sample sits at each
 * sub-triangle's centroid and carries area / m^2 (sample_at; a sample the
 * alpha test rejects has weight 0). Samples are written
 * from offset[t]: the voxel they fall in (x fastest; -1 when rejected), the
 * weight (m^2), linear albedo and the interpolated unit normal. */
__kernel void surface_samples(const int n_tris, __global const double *pos, __global const double *nrm,
                              __global const double *uv, __global const double *tint, __global const int *tex_id,
                              __global const float *textures, const int tw, const int th, const float alpha_threshold,
                              __global const int *m_sub, __global const long *offset,
                              const double ox, const double oy, const double oz, const double voxel,
                              const int nx, const int ny, const int nz,
                              __global int *s_voxel, __global double *s_weight, __global double *s_rgb,
                              __global double *s_normal)
{
    const int t = get_global_id(0);
    if (t >= n_tris) return;
    const int m = m_sub[t];
    long o = offset[t];
    double p[9], n[9], w[6];
    const double weight = load_triangle(pos, nrm, uv, t, m, p, n, w);
    const int k = tex_id[t];
    SubGrid g = sub_grid(m);
    double b0, b1, b2;
    while (sub_next(&g, &b0, &b1, &b2)) {
        double c[3], q[3];
        long at;
        const int keep = sample_at(p, n, w, tint + 3 * t, k, textures, tw, th, alpha_threshold, b0, b1, b2,
                                   ox, oy, oz, voxel, nx, ny, nz, c, q, &at);
        s_voxel[o] = keep ? (int)at : -1;
        s_weight[o] = keep ? weight : 0.0;
        s_rgb[3 * o] = c[0]; s_rgb[3 * o + 1] = c[1]; s_rgb[3 * o + 2] = c[2];
        s_normal[3 * o] = q[0]; s_normal[3 * o + 1] = q[1]; s_normal[3 * o + 2] = q[2];
        ++o;
    }
}

/* surface_samples summed per voxel where they fall, in 64-bit fixed point
 * (value x `fixed`, rounded to nearest even) with integer atomics: no
 * sample leaves the device, and integer sums do not depend on the order,
 * so they are the same for any work-group size. sums: 7 channels of
 * nx * ny * nz voxels: area, area x albedo (3), area x normal (3). */
__kernel void surface_sums(const int n_tris, __global const double *pos, __global const double *nrm,
                           __global const double *uv, __global const double *tint, __global const int *tex_id,
                           __global const float *textures, const int tw, const int th, const float alpha_threshold,
                           __global const int *m_sub, const double ox, const double oy, const double oz,
                           const double voxel, const int nx, const int ny, const int nz, const double fixed,
                           __global long *sums)
{
    const int t = get_global_id(0);
    if (t >= n_tris) return;
    const long count = (long)nx * ny * nz;
    const int m = m_sub[t];
    double p[9], n[9], w[6];
    const double weight = load_triangle(pos, nrm, uv, t, m, p, n, w);
    const int k = tex_id[t];
    /* consecutive samples mostly fall in one voxel: their fixed-point values
     * are added here first (integers: the same sums) and flushed per run */
    long run_at = -1, run[7];
    SubGrid g = sub_grid(m);
    double b0, b1, b2;
    while (sub_next(&g, &b0, &b1, &b2)) {
        double c[3], q[3];
        long at;
        if (!sample_at(p, n, w, tint + 3 * t, k, textures, tw, th, alpha_threshold, b0, b1, b2, ox, oy, oz,
                       voxel, nx, ny, nz, c, q, &at))
            continue;
        if (at != run_at) {  /* flush the run of samples that fell in one voxel */
            if (run_at >= 0)
                for (int ch = 0; ch < 7; ++ch) atom_add(sums + ch * count + run_at, run[ch]);
            run_at = at;
            for (int ch = 0; ch < 7; ++ch) run[ch] = 0;
        }
        const double val[7] = {weight, weight * c[0], weight * c[1], weight * c[2], weight * q[0], weight * q[1],
                              weight * q[2]};
        for (int ch = 0; ch < 7; ++ch) run[ch] += (long)rint(val[ch] * fixed);
    }
    if (run_at >= 0)
        for (int ch = 0; ch < 7; ++ch) atom_add(sums + ch * count + run_at, run[ch]);
}

/* Trilinear sample of a grid at voxel coordinates (voxel centres at
 * integers), zero outside. */
static double trilinear(__global const float *g, const int stride, const int c, const int nx, const int ny,
                        const int nz, const double u, const double v, const double w)
{
    const double fu = floor(u), fv = floor(v), fw = floor(w);
    const int i0 = (int)fu, j0 = (int)fv, k0 = (int)fw;
    const double a = u - fu, b = v - fv, d = w - fw;
    double s = 0.0;
    for (int dk = 0; dk < 2; ++dk)
        for (int dj = 0; dj < 2; ++dj)
            for (int di = 0; di < 2; ++di) {
                const int i = i0 + di, j = j0 + dj, k = k0 + dk;
                if (i < 0 || j < 0 || k < 0 || i >= nx || j >= ny || k >= nz) continue;
                const double wt = (di ? a : 1.0 - a) * (dj ? b : 1.0 - b) * (dk ? d : 1.0 - d);
                s += wt * (double)g[stride * (((long)k * ny + j) * nx + i) + c];
            }
    return s;
}

/* One work-item per pixel: the ray through the pixel centre (camera record
 * of worldlib/render) is marched through the grid's box in steps of `step`
 * metres from the box entry; each step takes the trilinear channels (grid:
 * 7 floats a voxel: premultiplied albedo, density, surface x normal) and
 * lets exp(-sigma step) through, where the extinction along the ray
 * direction d, with S the surface and n its mean normal,
 *     sigma = density + S (|n . d| - G |n|)   (at least 0)
 * adds to the isotropic density (G = 1/2 of the surface) the part that
 * depends on how the surface faces the ray: a voxel whose surfaces are one
 * plane (|n| = 1) blocks S |n . d|, its exact projected area; one whose
 * normals spread evenly (|n| = 0) blocks G S from every side. What a step
 * stops adds the mean albedo (albedo / density). A ray stops once less
 * than 1e-4 of it is left. Out: alpha = 1 - transmittance, premultiplied
 * colour. */
__kernel void composite(const int width, const int height, __global const float *cam,
                        __global const float *grid, const double leaf_projection, const int nx, const int ny, const int nz,
                        const double ox, const double oy, const double oz,
                        const double voxel, const double step, __global float *out_alpha, __global float *out_rgb)
{
    const int px = get_global_id(0), py = get_global_id(1);
    if (px >= width || py >= height) return;
    const double x = 2.0 * (((double)px + 0.5) / (double)width) - 1.0;
    const double y = 1.0 - 2.0 * (((double)py + 0.5) / (double)height);
    double o[3], d[3];
    for (int i = 0; i < 3; ++i) {
        if (cam[12] > 0.5f) { o[i] = cam[i] + x * cam[6 + i] + y * cam[9 + i]; d[i] = cam[3 + i]; }
        else { o[i] = cam[i]; d[i] = cam[3 + i] + x * cam[6 + i] + y * cam[9 + i]; }
    }
    const double dl = sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
    const double lo[3] = {ox, oy, oz};
    const double n[3] = {(double)nx, (double)ny, (double)nz};
    double t0 = 0.0, t1 = INFINITY;
    for (int i = 0; i < 3; ++i) {
        d[i] /= dl;
        const double hi = lo[i] + n[i] * voxel;
        if (d[i] == 0.0) {
            if (o[i] < lo[i] || o[i] > hi) t1 = -1.0;
        } else {
            double ta = (lo[i] - o[i]) / d[i], tb = (hi - o[i]) / d[i];
            if (ta > tb) { const double s = ta; ta = tb; tb = s; }
            t0 = fmax(t0, ta); t1 = fmin(t1, tb);
        }
    }
    double T = 1.0, r = 0.0, g = 0.0, b = 0.0;
    for (double t = t0 + 0.5 * step; t < t1 && T >= 1e-4; t += step) {
        const double u = (o[0] + t * d[0] - ox) / voxel - 0.5;
        const double v = (o[1] + t * d[1] - oy) / voxel - 0.5;
        const double w = (o[2] + t * d[2] - oz) / voxel - 0.5;
        double c[7];
        c[3] = trilinear(grid, 7, 3, nx, ny, nz, u, v, w);
        if (c[3] <= 0.0) continue;  /* empty space costs one channel's lookups */
        for (int q = 0; q < 7; ++q)
            if (q != 3) c[q] = trilinear(grid, 7, q, nx, ny, nz, u, v, w);
        const double sn = sqrt(c[4] * c[4] + c[5] * c[5] + c[6] * c[6]);
        const double sigma = fmax(c[3] + fabs(c[4] * d[0] + c[5] * d[1] + c[6] * d[2]) - leaf_projection * sn, 0.0);
        const double a = 1.0 - exp(-sigma * step);
        const double k = T * a / c[3];
        r += k * c[0];
        g += k * c[1];
        b += k * c[2];
        T *= 1.0 - a;
    }
    const long p = (long)py * width + px;
    out_alpha[p] = (float)(1.0 - T);
    out_rgb[3 * p] = (float)r; out_rgb[3 * p + 1] = (float)g; out_rgb[3 * p + 2] = (float)b;
}
