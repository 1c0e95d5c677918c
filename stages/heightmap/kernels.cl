/* heightmap kernels: gradient noise (fBm, ridged multifractal, domain warp)
 * and fault formation, one work-item per cell.
 *
 * The maths is mirrored operation by operation in reference.py (numpy,
 * float32). Contraction of a*b+c into fma is switched off so that every
 * conforming device rounds exactly like numpy does; no fast-math anywhere.
 *
 * Positions are in cell units of the *whole world* (X = global column + 0.5,
 * Z = global row + 0.5), so a window (tile) computes bit-identical values to
 * the same cells of the whole map. The host converts metres to lattice units
 * per octave (scale = cell size / wavelength), so the same config gives the
 * same landforms at any resolution.
 *
 * Compile-time switches (-D):
 *   RIDGED  0: fBm basis, 1: ridged multifractal basis (Musgrave)
 *   WARP    0/1: domain warp the basis by two fBm fields
 *   FAULT   0/1: add the fault-formation sum
 *
 * Octave table (constant memory, built by noise.py):
 *   octf[i] = (scale lattice/cell, offset x, offset z, amplitude)
 *   octi[i] = (period in lattice cells or 0, seed hash, 0, 0)
 * entries [0, n_main) are the basis octaves, [n_main, n_main+n_warp) the warp
 * x field, [n_main+n_warp, n_main+2*n_warp) the warp z field.
 * Fault table: fault[i] = (normal x, normal z, offset in cells, weight).
 */
#pragma OPENCL FP_CONTRACT OFF

#ifndef RIDGED
#define RIDGED 0
#endif
#ifndef WARP
#define WARP 0
#endif
#ifndef FAULT
#define FAULT 0
#endif

/* 16 gradient directions at 11.25 + k * 22.5 degrees: never axis aligned */
#define GA1 0.98078528f /* cos 11.25 */
#define GB1 0.19509032f /* sin 11.25 */
#define GA2 0.83146961f /* cos 33.75 */
#define GB2 0.55557023f /* sin 33.75 */
#define NOISE_SCALE 1.41421356f /* 2D gradient noise lies in [-1/sqrt2, 1/sqrt2] */

#define HX 0x8da6b343u
#define HZ 0xd8163841u

/* lowbias32 (Chris Wellons): a full-avalanche 32-bit mixer */
inline uint mix32(uint h)
{
    h ^= h >> 16;
    h *= 0x7feb352du;
    h ^= h >> 15;
    h *= 0x846ca68bu;
    h ^= h >> 16;
    return h;
}

inline float grad(uint h, float fx, float fz)
{
    float ga = (h & 8u) ? GA2 : GA1;
    float gb = (h & 8u) ? GB2 : GB1;
    float gx = (h & 4u) ? gb : ga;
    float gz = (h & 4u) ? ga : gb;
    gx = (h & 1u) ? -gx : gx;
    gz = (h & 2u) ? -gz : gz;
    return gx * fx + gz * fz;
}

inline float fade(float t)
{
    return t * t * t * (t * (t * 6.0f - 15.0f) + 10.0f);
}

inline int wrap(int i, int period)
{
    int m = i % period;
    return m < 0 ? m + period : m;
}

/* gradient noise at lattice position (px, pz), in [-1, 1] */
inline float gnoise(float px, float pz, int period, uint seed)
{
    float flx = floor(px);
    float flz = floor(pz);
    float fx = px - flx;
    float fz = pz - flz;
    int ix0 = (int)flx;
    int iz0 = (int)flz;
    int ix1 = ix0 + 1;
    int iz1 = iz0 + 1;
    if (period > 0) {
        ix0 = wrap(ix0, period);
        iz0 = wrap(iz0, period);
        ix1 = wrap(ix1, period);
        iz1 = wrap(iz1, period);
    }
    uint hx0 = (uint)ix0 * HX;
    uint hx1 = (uint)ix1 * HX;
    uint hz0 = (uint)iz0 * HZ + seed;
    uint hz1 = (uint)iz1 * HZ + seed;
    float fx1 = fx - 1.0f;
    float fz1 = fz - 1.0f;
    float d00 = grad(mix32(hx0 ^ hz0), fx, fz);
    float d10 = grad(mix32(hx1 ^ hz0), fx1, fz);
    float d01 = grad(mix32(hx0 ^ hz1), fx, fz1);
    float d11 = grad(mix32(hx1 ^ hz1), fx1, fz1);
    float u = fade(fx);
    float v = fade(fz);
    float a = d00 + u * (d10 - d00);
    float b = d01 + u * (d11 - d01);
    return (a + v * (b - a)) * NOISE_SCALE;
}

/* fBm: sum of amplitude * noise over the octaves [first, first + n) */
inline float fbm(float X, float Z, int first, int n,
                 __constant const float4 *octf, __constant const int4 *octi)
{
    float sum = 0.0f;
    for (int i = first; i < first + n; ++i) {
        float4 o = octf[i];
        float px = X * o.x + o.y;
        float pz = Z * o.x + o.z;
        sum = sum + o.w * gnoise(px, pz, octi[i].x, (uint)octi[i].y);
    }
    return sum;
}

/* ridged multifractal (Musgrave, Texturing & Modeling ch. 16) */
inline float ridged(float X, float Z, int n, float roffset, float rgain,
                    __constant const float4 *octf, __constant const int4 *octi)
{
    float sum = 0.0f;
    float weight = 1.0f;
    for (int i = 0; i < n; ++i) {
        float4 o = octf[i];
        float px = X * o.x + o.y;
        float pz = Z * o.x + o.z;
        float s = roffset - fabs(gnoise(px, pz, octi[i].x, (uint)octi[i].y));
        s = s * s;
        s = s * weight;
        sum = sum + s * o.w;
        weight = clamp(s * rgain, 0.0f, 1.0f);
    }
    return sum;
}

/* one work-item per cell of a (rows, cols) tile whose top-left cell is the
 * world cell (col0, row0); this launch covers tile rows [row_base, ...).
 * height = hb + hs * value */
__kernel void terrain(__global float *out,
                      const int cols, const int rows,
                      const int col0, const int row0, const int row_base,
                      const int n_main, const int n_warp,
                      __constant const float4 *octf, __constant const int4 *octi,
                      const float hs, const float hb,
                      const float roffset, const float rgain,
                      const float warp_cells,
                      const int n_fault, __constant const float4 *fault,
                      const float fault_inv_w)
{
    const int c = get_global_id(0);
    const int r = get_global_id(1) + row_base;
    if (c >= cols || r >= rows)
        return;
    float X = (float)(col0 + c) + 0.5f;
    float Z = (float)(row0 + r) + 0.5f;
    float value = 0.0f;

#if FAULT
    for (int i = 0; i < n_fault; ++i) {
        float4 f = fault[i];
        float s = f.x * X + f.y * Z - f.z;
        float t = clamp(s * fault_inv_w + 0.5f, 0.0f, 1.0f);
        float S = t * t * (3.0f - 2.0f * t);
        value = value + f.w * (S + S - 1.0f);
    }
#endif

#if WARP
    float wx = fbm(X, Z, n_main, n_warp, octf, octi);
    float wz = fbm(X, Z, n_main + n_warp, n_warp, octf, octi);
    X = X + warp_cells * wx;
    Z = Z + warp_cells * wz;
#endif

#if RIDGED
    value = value + ridged(X, Z, n_main, roffset, rgain, octf, octi);
#else
    value = value + fbm(X, Z, 0, n_main, octf, octi);
#endif

    out[(size_t)r * (size_t)cols + (size_t)c] = hb + hs * value;
}

/* the roofline: a trivial kernel writing one float per cell, same launch
 * geometry as terrain() */
__kernel void fill(__global float *out, const int cols, const int rows,
                   const int row_base, const float value)
{
    const int c = get_global_id(0);
    const int r = get_global_id(1) + row_base;
    if (c >= cols || r >= rows)
        return;
    out[(size_t)r * (size_t)cols + (size_t)c] = value + (float)c;
}

/* a copy kernel: reads and writes one float per cell */
__kernel void copy(__global const float *src, __global float *dst, const int n)
{
    const int i = get_global_id(0);
    if (i < n)
        dst[i] = src[i];
}
