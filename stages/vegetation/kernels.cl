/* vegetation kernels: local attributes (slope, aspect, curvature, sky view,
 * sunlight), suitability, splat weights, the ecosystem simulation (seeding,
 * growth, death, self-thinning), Poisson-disk dart throwing by grid phases,
 * and jittered-grid grass tufts.
 *
 * Every kernel is mirrored operation by operation in reference.py (numpy,
 * float32). fma contraction is off and divisions and square roots are
 * correctly rounded (the host builds with
 * -cl-fp32-correctly-rounded-divide-sqrt), so on a conforming device the two
 * agree to the bit except where a library function (atan, atan2) is used:
 * slope and aspect, compared within a few ulps.
 *
 * Determinism: one work-item writes only its own cell, reads only buffers no
 * work-item of the same launch writes (ping-pong buffers), no atomics;
 * random numbers are counter-based: hash(key, cell, step, stream) with the
 * key derived from the seed and the species name on the host. Results do
 * not depend on the work-group size.
 */
#pragma OPENCL FP_CONTRACT OFF

#define INLINE inline __attribute__((always_inline))

#include "worldbake_hash.h"

INLINE uint hash4(uint k, uint a, uint b, uint c)
{
    return mix32(mix32(mix32(k ^ a) ^ b) ^ c);
}

/* uniform in [0, 1) with 24 bits, exact in float32 */
INLINE float unit(uint h)
{
    return (float)(h >> 8) * 5.9604645e-08f;
}

INLINE float clamp01(float x)
{
    return fmin(fmax(x, 0.0f), 1.0f);
}

/* smoothstep from e0 over 1/inv: t = clamp((x - e0) * inv), t*t*(3 - 2t) */
INLINE float sstep(float e0, float inv, float x)
{
    float t = clamp01((x - e0) * inv);
    return t * t * (3.0f - 2.0f * t);
}

/* A window of a world grid (a tile and its halo): the array h holds `rows`
 * x `cols` cells whose first is the world's cell (row0, col0), of a world of
 * wrows x wcols. The kernels that take one index and clamp in world cells, so
 * a tile with a wide enough halo computes the bits the whole world does
 * (the whole world is the window 0, 0, rows, cols). */
#define WINDOW_ARGS const int rows, const int cols, const int row0, const int col0, const int wrows, const int wcols
#define WINDOW rows, cols, row0, col0, wrows, wcols

INLINE float world_at(__global const float *h, WINDOW_ARGS, int r, int c)
{
    r = clamp(r, 0, wrows - 1) - row0;
    c = clamp(c, 0, wcols - 1) - col0;
    return h[r * cols + c];
}

/* a b on the upper row, c d on the lower; tr, tc the fractions down and across */
INLINE float bilinear(float a, float b, float c, float d, float tr, float tc)
{
    float top = a + (b - a) * tc;
    float bot = c + (d - c) * tc;
    return top + (bot - top) * tr;
}

/* bilinear at fractional world (row, col) indices, clamped to the world */
INLINE float world_bilinear(__global const float *h, WINDOW_ARGS, float fr, float fc)
{
    float r0f = floor(fr), c0f = floor(fc);
    float tr = fr - r0f, tc = fc - c0f;
    int r0 = (int)r0f, c0 = (int)c0f;
    float a = world_at(h, WINDOW, r0, c0);
    float b = world_at(h, WINDOW, r0, c0 + 1);
    float c = world_at(h, WINDOW, r0 + 1, c0);
    float d = world_at(h, WINDOW, r0 + 1, c0 + 1);
    return bilinear(a, b, c, d, tr, tc);
}

/* ------------------------------------------------------------------ attributes
 * Two kernels, one work-item per cell.
 * horizon: for one direction (east, north unit vector e), the largest
 *   tangent of the terrain seen from the cell, marching outwards at the
 *   distances of `steps` (cell units, growing geometrically) with bilinear
 *   heights, until the first sample off the world.
 * Both read a window of the world (WINDOW_ARGS) and compute its orows x
 *   ocols cells from (orow, ocol); their outputs are that size.
 * shade: gradient by central differences (one-sided at the border),
 *   curvature = Laplacian over +-k cells, sky view = mean cos^2 of the
 *   horizon elevations, direct sun = sum over the sun table of w * max(0,
 *   n.s) where the sun clears the horizon (tangent interpolated between the
 *   two nearest directions), times inv_direct (the flat open value).
 *   sun0[k] = (east, up, south, weight); sun1[k] = (azimuth in direction
 *   units [0, nd), tan elevation, 0, 0)
 *   outputs: slope (deg), aspect (deg clockwise from north, the way the
 *   slope faces), gradient magnitude (m/m), curvature (1/m), sky view
 *   (0..1), sunlight (relative insolation).
 */
__kernel void horizon(__global const float *h, WINDOW_ARGS, const int orow, const int ocol, const int orows,
                      const int ocols, const float dx, const float ex, const float ez, __constant float *steps,
                      const int nsteps, const int d, __global float *out)
{
    const int oc = get_global_id(0), orr = get_global_id(1);
    if (oc >= ocols || orr >= orows)
        return;
    const int r = row0 + orow + orr, c = col0 + ocol + oc;  /* world cell */
    const float h0 = world_at(h, WINDOW, r, c);
    float tmax = 0.0f;
    /* Most rays stay inside the world and the window: their samples need no clamp and no end test (the
     * scan's inner loop on a fine tile); the same bilinear as world_bilinear's. */
    const float smax = steps[nsteps - 1];
    const float fc_end = (float)c + smax * ex, fr_end = (float)r - smax * ez;
    const int c_lo = (int)floor(fmin((float)c, fc_end)), c_hi = (int)floor(fmax((float)c, fc_end)) + 1;
    const int r_lo = (int)floor(fmin((float)r, fr_end)), r_hi = (int)floor(fmax((float)r, fr_end)) + 1;
    if (c_lo >= max(col0, 0) && r_lo >= max(row0, 0) && c_hi < min(col0 + cols, wcols - 1)
        && r_hi < min(row0 + rows, wrows - 1)) {
        for (int m = 0; m < nsteps; ++m) {
            const float s = steps[m];
            const float fc = (float)c + s * ex;
            const float fr = (float)r - s * ez;
            const float r0f = floor(fr), c0f = floor(fc);
            const float tr = fr - r0f, tc = fc - c0f;
            __global const float *q = h + ((int)r0f - row0) * cols + ((int)c0f - col0);
            const float t = (bilinear(q[0], q[1], q[cols], q[cols + 1], tr, tc) - h0) / (s * dx);
            tmax = fmax(tmax, t);
        }
        out[d * orows * ocols + orr * ocols + oc] = tmax;
        return;
    }
    for (int m = 0; m < nsteps; ++m) {
        const float s = steps[m];
        const float fc = (float)c + s * ex;
        const float fr = (float)r - s * ez;
        /* the samples move away monotonically: the first one off the world ends the scan */
        if (fc < 0.0f || fr < 0.0f || fc > (float)(wcols - 1) || fr > (float)(wrows - 1))
            break;
        const float t = (world_bilinear(h, WINDOW, fr, fc) - h0) / (s * dx);
        tmax = fmax(tmax, t);
    }
    out[d * orows * ocols + orr * ocols + oc] = tmax;
}

__kernel void shade(__global const float *h, WINDOW_ARGS, const int orow, const int ocol, const int orows,
                    const int ocols, const float dx, const int kc, const float inv_kc2, __global const float *hz,
                    const int nd, __constant float4 *sun0, __constant float4 *sun1, const int nsun,
                    const float inv_direct, const float diffuse,
                    __global float *slope, __global float *aspect, __global float *grad,
                    __global float *curv, __global float *sky, __global float *sunlight)
{
    const int oc = get_global_id(0), orr = get_global_id(1);
    if (oc >= ocols || orr >= orows)
        return;
    const int n = orows * ocols;
    const int i = orr * ocols + oc;
    const int r = row0 + orow + orr, c = col0 + ocol + oc;  /* world cell */
    const float h0 = world_at(h, WINDOW, r, c);
    const int cl = max(c - 1, 0), cr = min(c + 1, wcols - 1);
    const int ru = max(r - 1, 0), rd = min(r + 1, wrows - 1);
    const float gx = (world_at(h, WINDOW, r, cr) - world_at(h, WINDOW, r, cl)) / ((float)(cr - cl) * dx);
    const float gz = (world_at(h, WINDOW, rd, c) - world_at(h, WINDOW, ru, c)) / ((float)(rd - ru) * dx);
    const float g = sqrt(gx * gx + gz * gz);
    slope[i] = atan(g) * 57.29577951f;
    float asp = atan2(-gx, gz) * 57.29577951f;
    aspect[i] = asp < 0.0f ? asp + 360.0f : asp;
    grad[i] = g;
    const float lap = world_at(h, WINDOW, r, c + kc) + world_at(h, WINDOW, r, c - kc)
                    + world_at(h, WINDOW, r + kc, c) + world_at(h, WINDOW, r - kc, c) - 4.0f * h0;
    curv[i] = lap * inv_kc2;

    float svf = 0.0f;
    for (int d = 0; d < nd; ++d) {
        const float t = hz[d * n + i];
        svf = svf + 1.0f / (1.0f + t * t);
    }
    svf = svf / (float)nd;
    sky[i] = svf;

    const float nn = sqrt(gx * gx + gz * gz + 1.0f);
    const float nx = -gx / nn, ny = 1.0f / nn, nz = -gz / nn;
    float direct = 0.0f;
    for (int k = 0; k < nsun; ++k) {
        const float4 s0 = sun0[k];
        const float4 s1 = sun1[k];
        const float a0 = floor(s1.x);
        const float f = s1.x - a0;
        const int d0 = (int)a0 % nd;
        const int d1 = (d0 + 1) % nd;
        const float h0t = hz[d0 * n + i], h1t = hz[d1 * n + i];
        const float th = h0t + (h1t - h0t) * f;
        const float cosi = nx * s0.x + ny * s0.y + nz * s0.z;
        if (s1.y > th && cosi > 0.0f)
            direct = direct + s0.w * cosi;
    }
    sunlight[i] = (1.0f - diffuse) * (direct * inv_direct) + diffuse * svf;
}

/* ------------------------------------------------------------------ moisture filter
 * Seed 004's jittered 3x3 moisture filter with its normalisation fixed: the
 * centre (weight 4) at the cell, the four diagonal (2) and four axial (1)
 * neighbours at a per-cell jittered offset (up to +-jitter cells), bilinear,
 * divided by the sum of the weights, 16 (the thesis divides by 12). A
 * window of the world (WINDOW_ARGS), its orows x ocols cells from (orow, ocol).
 */
__kernel void moisture_filter(__global const float *m, WINDOW_ARGS, const int orow, const int ocol,
                              const int orows, const int ocols, const float jitter, const uint key,
                              __global float *out)
{
    const int oc = get_global_id(0), orr = get_global_id(1);
    if (oc >= ocols || orr >= orows)
        return;
    const int r = row0 + orow + orr, c = col0 + ocol + oc;  /* world cell: its jitter and clamping */
    const uint i = (uint)r * (uint)wcols + (uint)c;
    const float jx = (unit(hash4(key, i, 0u, 0u)) - 0.5f) * 2.0f * jitter;
    const float jz = (unit(hash4(key, i, 1u, 0u)) - 0.5f) * 2.0f * jitter;
    const float fr = (float)r + jz, fc = (float)c + jx;
    float diag = world_bilinear(m, WINDOW, fr - 1.0f, fc - 1.0f);
    diag = diag + world_bilinear(m, WINDOW, fr - 1.0f, fc + 1.0f);
    diag = diag + world_bilinear(m, WINDOW, fr + 1.0f, fc - 1.0f);
    diag = diag + world_bilinear(m, WINDOW, fr + 1.0f, fc + 1.0f);
    float axial = world_bilinear(m, WINDOW, fr - 1.0f, fc);
    axial = axial + world_bilinear(m, WINDOW, fr + 1.0f, fc);
    axial = axial + world_bilinear(m, WINDOW, fr, fc - 1.0f);
    axial = axial + world_bilinear(m, WINDOW, fr, fc + 1.0f);
    out[orr * ocols + oc] = (4.0f * world_at(m, WINDOW, r, c) + 2.0f * diag + axial) * 0.0625f;
}

/* ------------------------------------------------------------------ suitability
 * Per species (table of NPREF preferences x (min, max, inv_edge, 0); inv_edge
 * 0 means a hard edge) the product of the soft range factors of altitude,
 * slope, moisture, sunlight and curvature; 0 where blocked (water, no data).
 */
#define NPREF 5

INLINE float ramp(float d, float inv)
{
    if (inv > 0.0f) {
        float t = clamp01(d * inv);
        return t * t * (3.0f - 2.0f * t);
    }
    return d > 0.0f ? 1.0f : 0.0f;
}

__kernel void suitability(__global const float *alt, __global const float *slope, __global const float *moist,
                          __global const float *sun, __global const float *curv, __global const uchar *blocked,
                          const int n, __constant float4 *prefs, const int nsp, __global float *out)
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    float v[NPREF];
    v[0] = alt[i];
    v[1] = slope[i];
    v[2] = moist[i];
    v[3] = sun[i];
    v[4] = curv[i];
    const int b = blocked[i];
    for (int s = 0; s < nsp; ++s) {
        float f = 1.0f;
        for (int k = 0; k < NPREF; ++k) {
            const float4 p = prefs[s * NPREF + k];
            f = f * (ramp(v[k] - p.x, p.z) * ramp(p.y - v[k], p.z));
        }
        out[s * n + i] = b ? 0.0f : f;
    }
}

/* ------------------------------------------------------------------ splat
 * Terrain splat weights (seed 004, algorithm 3, both defects fixed): raw
 * coverages of snow, rock, scree and mud from altitude, slope and filtered
 * moisture, then a partition in priority order snow > rock > scree > mud >
 * green grass > dry grass where each layer takes its share of what the
 * layers before it left, and dry grass the rest: every weight is in [0, 1]
 * and they sum to 1 (the thesis's mud is never limited by snow and the sum
 * can exceed 1). Water (lakes, rivers) is mud.
 *   p[0..1] snow altitude (e0, inv)    p[2..3] snow slope (e0, inv)   p[4] melt
 *   p[5..6] rock slope                 p[7..8] rock altitude
 *   p[9..10] scree slope               p[11..12] mud moisture         p[13..14] mud slope
 *   p[15..16] green moisture           p[17..18] alpine altitude
 * output channel order: rock, scree, grass, dry_grass, mud, snow
 */
__kernel void splat(__global const float *alt, __global const float *slope, __global const float *grad,
                    __global const float *moist, __global const uchar *water, const int n,
                    __constant float *p, __global float *out)
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    const float a = alt[i], s = slope[i], m = moist[i];
    const float ny = 1.0f / sqrt(1.0f + grad[i] * grad[i]);
    float rock, scree, grass, dry, mud, snow;
    if (water[i]) {
        rock = 0.0f; scree = 0.0f; grass = 0.0f; dry = 0.0f; mud = 1.0f; snow = 0.0f;
    } else {
        const float melt = fmax(m * p[4] - (1.0f - ny), 0.0f);
        const float f_snow = clamp01(sstep(p[0], p[1], a) * (1.0f - sstep(p[2], p[3], s)) - melt);
        const float f_rock = clamp01(sstep(p[5], p[6], s) + sstep(p[7], p[8], a));
        const float f_scree = sstep(p[9], p[10], s);
        const float f_mud = fmax(sstep(p[11], p[12], m) * (1.0f - sstep(p[13], p[14], s)) - 0.5f * f_rock, 0.0f);
        const float green = fmax(sstep(p[15], p[16], m), sstep(p[17], p[18], a));
        float rem = 1.0f;
        snow = f_snow * rem;
        rem = rem - snow;
        rock = f_rock * rem;
        rem = rem - rock;
        scree = f_scree * rem;
        rem = rem - scree;
        mud = f_mud * rem;
        rem = rem - mud;
        grass = green * rem;
        rem = rem - grass;
        dry = rem;
    }
    out[6 * i + 0] = rock;
    out[6 * i + 1] = scree;
    out[6 * i + 2] = grass;
    out[6 * i + 3] = dry;
    out[6 * i + 4] = mud;
    out[6 * i + 5] = snow;
}

/* ------------------------------------------------------------------ ecosystem
 * Deussen et al. 1998 self-thinning with Benes's vitality, on a grid of
 * nx x nz cells holding at most one plant each: sp = species (-1 empty),
 * birth = year of birth. Lengths are in cell units. Species table, 12
 * floats per species:
 *   0 maturity (years)   1 1 / maturity   2 lifespan   3 lifespan spread
 *   4 radius of influence at maturity (cells)   5 shade survival per step
 *   6 establishment per mature neighbour-count per step   7 background per step
 *   8 seed window half-width (cells, as float)   9 species key (uint bits)
 *   10 height when young (m)   11 height gained when fully grown (m)
 * Plant quantities, from (species, cell, birth) alone:
 *   jitter = unit(hash(key_s, cell, birth, 1..2)) inside its cell
 *   life   = lifespan * (1 - spread + 2 spread unit(hash(key_s, cell, birth, 3)))
 *   R(age) = Rmax * min(1, 0.1 + 0.9 age / maturity)   (sphere of influence)
 *   height(age) = h_young + h_gain * min(1, age / maturity)
 *   vitality = 0.5 + 0.5 tent(age / life)   (tent peaks at mid-life: Benes 2002)
 *   strength = height * vitality * (0.25 + 0.75 suitability): where spheres
 *   overlap, the taller, fitter plant shades the other (competition for
 *   light, as in Lane and Prusinkiewicz's multilevel communities)
 */
#define SPW 12
#ifndef NB
#define NB 2
#endif

INLINE float plant_life(__constant float *tab, int s, uint cell, int birth)
{
    const uint key = as_uint(tab[s * SPW + 9]);
    const float spread = tab[s * SPW + 3];
    return tab[s * SPW + 2] * (1.0f - spread + 2.0f * spread * unit(hash4(key, cell, (uint)birth, 3u)));
}

/* mature[s * n + cell] = 1 where a plant of species s is mature */
__kernel void sim_sources(__global const int *sp, __global const int *birth, const int n, const int t,
                          __constant float *tab, const int nsp, __global int *mature)
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    const int s0 = sp[i];
    for (int s = 0; s < nsp; ++s) {
        int v = 0;
        if (s0 == s && (float)(t - birth[i]) >= tab[s * SPW + 0])
            v = 1;
        mature[s * n + i] = v;
    }
}

/* integer box sums of half-width w_s along x (axis 0) or z (axis 1): one
 * work-item per line (a row for axis 0, a column for axis 1) and species,
 * a running sum (one add and one subtract a cell, whatever w_s; integers,
 * so exactly the window's sum) */
__kernel void box_sum(__global const int *src, const int nx, const int nz, const int axis,
                      __constant float *tab, const int nsp, __global int *dst)
{
    const int line = get_global_id(0), s = get_global_id(1);
    const int len = axis == 0 ? nx : nz, lines = axis == 0 ? nz : nx;
    if (line >= lines || s >= nsp)
        return;
    const int stride = axis == 0 ? 1 : nx;
    const int base = s * nx * nz + (axis == 0 ? line * nx : line);
    const int w = (int)tab[s * SPW + 8];
    int acc = 0;
    for (int k = 0; k <= min(w, len - 1); ++k)
        acc += src[base + k * stride];
    for (int k = 0; k < len; ++k) {
        dst[base + k * stride] = acc;
        if (k + w + 1 < len)
            acc += src[base + (k + w + 1) * stride];
        if (k - w >= 0)
            acc -= src[base + (k - w) * stride];
    }
}

/* One step from year t: ageing and death (by age, or by stress on an
 * unsuitable site), then establishment on cells that were free: species s
 * lands with probability p_s = suit_s * lam / (1 + lam), lam = est_s *
 * count_s + bg_s; when several land, the one with the smallest u_s / p_s
 * (an exponential race). */
__kernel void sim_update(__global int *sp, __global int *birth, __global const float *suit,
                         __global const int *count, const int n, const int t, const float stress,
                         const uint key, __constant float *tab, const int nsp)
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    const int s0 = sp[i];
    if (s0 >= 0) {
        const int b = birth[i];
        const float age = (float)(t - b);
        bool dies = age > plant_life(tab, s0, (uint)i, b);
        const float u = unit(hash4(key, (uint)i, (uint)t, 12u));
        if (u < stress * (1.0f - suit[s0 * n + i]))
            dies = true;
        if (dies)
            sp[i] = -1;
        return;
    }
    int best = -1;
    float best_score = 2.0f;
    for (int s = 0; s < nsp; ++s) {
        const float lam = tab[s * SPW + 6] * (float)count[s * n + i] + tab[s * SPW + 7];
        const float pr = suit[s * n + i] * lam / (1.0f + lam);
        const uint ks = as_uint(tab[s * SPW + 9]);
        const float u = unit(hash4(ks, (uint)i, (uint)t, 13u));
        if (u < pr) {
            const float score = u / pr;
            if (score < best_score) {
                best_score = score;
                best = s;
            }
        }
    }
    if (best >= 0) {
        sp[i] = best;
        birth[i] = t;
    }
}

/* the plant record (x, z, R, strength) and contest state (1 for every plant) */
__kernel void thin_init(__global const int *sp, __global const int *birth, __global const float *suit,
                        const int nx, const int nz, const int t, __constant float *tab,
                        __global float4 *rec, __global uchar *st)
{
    const int x = get_global_id(0), z = get_global_id(1);
    if (x >= nx || z >= nz)
        return;
    const int n = nx * nz;
    const int i = z * nx + x;
    const int s = sp[i];
    if (s < 0) {
        st[i] = 0;
        rec[i] = (float4)(0.0f, 0.0f, 0.0f, 0.0f);
        return;
    }
    const int b = birth[i];
    const uint key = as_uint(tab[s * SPW + 9]);
    const float jx = unit(hash4(key, (uint)i, (uint)b, 1u));
    const float jz = unit(hash4(key, (uint)i, (uint)b, 2u));
    const float age = (float)(t - b);
    const float grown = fmin(1.0f, age * tab[s * SPW + 1]);
    const float R = tab[s * SPW + 4] * fmin(1.0f, 0.1f + 0.9f * (age * tab[s * SPW + 1]));
    const float height = tab[s * SPW + 10] + tab[s * SPW + 11] * grown;
    const float a = age / plant_life(tab, s, (uint)i, b);
    const float tent = fmax(1.0f - fabs(2.0f * a - 1.0f), 0.0f);
    const float strength = height * (0.5f + 0.5f * tent) * (0.25f + 0.75f * suit[s * n + i]);
    rec[i] = (float4)((float)x + jx, (float)z + jz, R, strength);
    st[i] = 1;
}

INLINE bool overlap(float4 p, float4 q)
{
    const float ddx = p.x - q.x, ddz = p.y - q.y;
    const float rr = p.z + q.z;
    return ddx * ddx + ddz * ddz < rr * rr;
}

/* mark = 1 for a contestant no overlapping contestant is stronger than
 * (ties: the larger cell index wins) */
__kernel void thin_mark(__global const float4 *rec, __global const uchar *st, const int nx, const int nz,
                        __global uchar *mark)
{
    const int x = get_global_id(0), z = get_global_id(1);
    if (x >= nx || z >= nz)
        return;
    const int i = z * nx + x;
    if (st[i] != 1) {
        mark[i] = 0;
        return;
    }
    const float4 p = rec[i];
    uchar top = 1;
    for (int dz = -NB; dz <= NB && top; ++dz) {
        const int zz = z + dz;
        if (zz < 0 || zz >= nz)
            continue;
        for (int dx = -NB; dx <= NB; ++dx) {
            const int xx = x + dx;
            if (xx < 0 || xx >= nx || (dx == 0 && dz == 0))
                continue;
            const int j = zz * nx + xx;
            if (st[j] != 1)
                continue;
            const float4 q = rec[j];
            if (overlap(p, q) && (q.w > p.w || (q.w == p.w && j > i))) {
                top = 0;
                break;
            }
        }
    }
    mark[i] = top;
}

/* local maxima win (st 2); a contestant overlapping a winner is dominated:
 * it survives suppressed (st 3) with the species' shade survival, else dies;
 * the others stay in the contest for the next round */
__kernel void thin_resolve(__global const float4 *rec, __global const uchar *st_in, __global const uchar *mark,
                           const int nx, const int nz, const int t, const int round, __constant float *tab,
                           __global int *sp, __global uchar *st_out)
{
    const int x = get_global_id(0), z = get_global_id(1);
    if (x >= nx || z >= nz)
        return;
    const int i = z * nx + x;
    const uchar s_in = st_in[i];
    if (s_in != 1) {
        st_out[i] = s_in;
        return;
    }
    if (mark[i]) {
        st_out[i] = 2;
        return;
    }
    const float4 p = rec[i];
    bool dominated = false;
    for (int dz = -NB; dz <= NB && !dominated; ++dz) {
        const int zz = z + dz;
        if (zz < 0 || zz >= nz)
            continue;
        for (int dx = -NB; dx <= NB; ++dx) {
            const int xx = x + dx;
            if (xx < 0 || xx >= nx || (dx == 0 && dz == 0))
                continue;
            const int j = zz * nx + xx;
            if (st_in[j] == 1 && mark[j] && overlap(p, rec[j])) {
                dominated = true;
                break;
            }
        }
    }
    if (!dominated) {
        st_out[i] = 1;
        return;
    }
    const int s = sp[i];
    const uint key = as_uint(tab[s * SPW + 9]);
    if (unit(hash4(key, (uint)i, (uint)t, 100u + (uint)round)) < tab[s * SPW + 5]) {
        st_out[i] = 3;
    } else {
        st_out[i] = 0;
        sp[i] = -1;
    }
}

/* ------------------------------------------------------------------ Poisson disk
 * One dart per free cell of one phase: world cells (xfirst + P gx, zfirst + P gz) of a grid
 * of cell c (metres), P = PN + 1. The dart is uniform in its cell; its
 * radius r comes from the radius field of the terrain cell it lands in (0:
 * nothing may grow there). It is kept when no point of the species within
 * PN cells is closer than max(r, r_q) + margin and no obstacle (a plant of
 * a species placed before) is closer than its clearance + margin. Radii are
 * at most PN * c / sqrt(2)... by construction (r <= 2 sqrt(2) c with PN = 3),
 * and points of one phase are at least (P - 1) c apart, so the darts of a
 * launch never conflict with each other and the result is the same in any
 * order. pts[cell] = (x, z, r, key), r = 0 for a free cell; x, z in metres
 * from the domain origin (the first terrain cell centre).
 * Windows: pts holds the wnx x wnz cells from the world's (x0, z0) of an nx x
 * nz grid, and rad the rows x cols terrain cells from (trow0, tcol0) of a
 * wrows x wcols terrain; darts are hashed and placed by world cell, and cells
 * outside the window count as free. A window's cells k cells from its edge
 * are the world's after k / PN phases (a dart reads PN cells around it): a
 * tile with a halo of PN x the phases of a round is exact (placement.py).
 */
#ifndef PN
#define PN 3
#endif
#define PP (PN + 1)

/* A free cell whose whole square lies within distance `reach` of a point
 * (with 1 % to spare for float rounding) rejects every later dart of that
 * point's test, which only the distance decides: marked r = -1, later
 * passes skip it at once. Marks change no result, only the work (the host
 * reads them as free cells). */
INLINE void poisson_dead_cell(__global float4 *pts, const int i, const int x, const int z, const float c,
                              const float qx, const float qz, const float reach)
{
    const float fx = fmax(fabs((float)x * c - qx), fabs((float)(x + 1) * c - qx));
    const float fz = fmax(fabs((float)z * c - qz), fabs((float)(z + 1) * c - qz));
    if (fx * fx + fz * fz < 0.98f * reach * reach)
        pts[i] = (float4)(0.0f, 0.0f, -1.0f, 0.0f);
}

__kernel void poisson_phase(__global float4 *pts, const int nx, const int nz, const int x0, const int z0,
                            const int wnx, const int wnz, const int xfirst, const int zfirst, const float c,
                            const float wdom, const float ddom, const uint pass, const uint key,
                            __global const float *rad, const int rows, const int cols, const int trow0,
                            const int tcol0, const int wrows, const int wcols, const float dx, const float margin,
                            __global const int *obs_start, __global const float4 *obs, const int onx,
                            const int onz, const float oc, const int ox0, const int oz0, const int onwx,
                            const int onwz)
{
    const int gx = get_global_id(0), gz = get_global_id(1);
    const int x = xfirst + gx * PP, z = zfirst + gz * PP;  /* world cells */
    if (x >= x0 + wnx || z >= z0 + wnz)
        return;
    const int li = (z - z0) * wnx + (x - x0);
    const int i = z * nx + x;
    if (pts[li].z != 0.0f)  /* a point, or a cell no dart can use (below) */
        return;
    const float u1 = unit(hash4(key, (uint)i, pass, 1u));
    const float u2 = unit(hash4(key, (uint)i, pass, 2u));
    const float fx = ((float)x + u1) * c;
    const float fz = ((float)z + u2) * c;
    if (fx > wdom || fz > ddom)
        return;
    const int tc = min((int)floor(fx / dx + 0.5f), wcols - 1) - tcol0;
    const int tr = min((int)floor(fz / dx + 0.5f), wrows - 1) - trow0;
    const float r = rad[tr * cols + tc];
    if (!(r > 0.0f))
        return;
    /* the points of the species within PN cells, nearest ring first (a
     * conflict is most likely close by, and any one rejects the dart, so the
     * order changes nothing but how soon a rejected dart stops) */
    for (int k = 1; k <= PN; ++k) {
        for (int dz = -k; dz <= k; ++dz) {
            const int zz = z + dz;
            if (zz < z0 || zz >= z0 + wnz)
                continue;
            const int step = (dz == -k || dz == k) ? 1 : 2 * k;  /* the ring's rows, else its two ends */
            for (int ddx = -k; ddx <= k; ddx += step) {
                const int xx = x + ddx;
                if (xx < x0 || xx >= x0 + wnx)
                    continue;
                const float4 q = pts[(zz - z0) * wnx + (xx - x0)];
                if (q.z > 0.0f) {
                    const float ex = fx - q.x, ez = fz - q.y;
                    const float rr = fmax(r, q.z) + margin;
                    if (ex * ex + ez * ez < rr * rr) {
                        poisson_dead_cell(pts, li, x, z, c, q.x, q.y, q.z);
                        return;
                    }
                }
            }
        }
    }
    /* obstacles: the plants of the species placed before */
    if (onx > 0) {
        const int ox = min((int)(fx / oc), onx - 1), oz = min((int)(fz / oc), onz - 1);
        /* obs_start covers the onwx x onwz cells from (ox0, oz0): the whole grid, or the part of it a
         * tile's darts reach (cells beyond it hold no obstacle this window's darts could meet) */
        for (int dz = -1; dz <= 1; ++dz) {
            const int zz = oz + dz;
            if (zz < 0 || zz >= onz || zz < oz0 || zz >= oz0 + onwz)
                continue;
            for (int ddx = -1; ddx <= 1; ++ddx) {
                const int xx = ox + ddx;
                if (xx < 0 || xx >= onx || xx < ox0 || xx >= ox0 + onwx)
                    continue;
                const int cell = (zz - oz0) * onwx + (xx - ox0);
                for (int k = obs_start[cell]; k < obs_start[cell + 1]; ++k) {
                    const float4 q = obs[k];
                    const float ex = fx - q.x, ez = fz - q.y;
                    const float cl = q.z + margin;
                    if (ex * ex + ez * ez < cl * cl) {
                        poisson_dead_cell(pts, li, x, z, c, q.x, q.y, q.z);
                        return;
                    }
                }
            }
        }
    }
    pts[li] = (float4)(fx, fz, r, unit(hash4(key, (uint)i, pass, 3u)));
}

/* ------------------------------------------------------------------ grass tufts
 * One candidate tuft per cell of a grid of spacing sp (metres): jittered
 * inside the middle `jitter` share of its cell, kept with probability equal
 * to the grass density of the terrain cell it lands in (seed 000:
 * P(keep) = density). out[cell] = (x, z, random, kept ? 1 : 0), for the
 * wnx x wnz cells from the world's (x0, z0); dens: the rows x cols terrain
 * cells from (trow0, tcol0) of a wrows x wcols terrain.
 */
__kernel void grass_tufts(__global const float *dens, const int rows, const int cols, const int trow0,
                          const int tcol0, const int wrows, const int wcols, const float dx, const int nx,
                          const int nz, const int x0, const int z0, const int wnx, const int wnz, const float sp,
                          const float jitter, const float wdom, const float ddom, const uint key,
                          __global float4 *out)
{
    const int ox = get_global_id(0), oz = get_global_id(1);
    if (ox >= wnx || oz >= wnz)
        return;
    const int x = x0 + ox, z = z0 + oz;  /* world cell */
    const uint i = (uint)(z * nx + x);
    const float lo = 0.5f - 0.5f * jitter;
    const float fx = ((float)x + (lo + jitter * unit(hash4(key, i, 1u, 0u)))) * sp;
    const float fz = ((float)z + (lo + jitter * unit(hash4(key, i, 2u, 0u)))) * sp;
    float kept = 0.0f;
    if (fx <= wdom && fz <= ddom) {
        const int tc = min((int)floor(fx / dx + 0.5f), wcols - 1) - tcol0;
        const int tr = min((int)floor(fz / dx + 0.5f), wrows - 1) - trow0;
        if (unit(hash4(key, i, 3u, 0u)) < dens[tr * cols + tc])
            kept = 1.0f;
    }
    out[oz * wnx + ox] = (float4)(fx, fz, unit(hash4(key, i, 4u, 0u)), kept);
}
