/* heightmap kernels: gradient noise (fBm, ridged multifractal, domain warp)
 * and fault formation.
 *
 * The maths is mirrored operation by operation in reference.py (numpy,
 * float32). Contraction of a*b+c into fma is switched off and no library
 * maths is used, so every conforming device rounds exactly like numpy does;
 * no fast-math anywhere.
 *
 * Work decomposition: one work-item per VW consecutive cells of a row, one
 * SIMD lane per cell (VW = 1 on GPUs: one work-item per cell). Each lane
 * computes its own cell from its own global position and writes only that
 * cell, so the result does not depend on the work-group size, the vector
 * width or the row bands. (PoCL does not vectorise the implicit work-item
 * loop of a kernel with an inner octave loop, hence the explicit vectors.)
 *
 * Positions are in cell units of the *whole world* (X = global column + 0.5,
 * Z = global row + 0.5), so a window (tile) computes bit-identical values to
 * the same cells of the whole map. The host converts metres to lattice units
 * per octave (scale = cell size / wavelength), so the same config gives the
 * same landforms at any resolution.
 *
 * Compile-time switches (-D):
 *   VW        vector width: 1, 2, 4, 8 or 16 (the host uses at most 8: PoCL 3.0 / LLVM 14
 *             fails to build the 16-wide kernel for AVX-512)
 *   RIDGED    0: fBm basis, 1: ridged multifractal basis (Musgrave)
 *   WARP      0/1: domain warp the basis by two fBm fields
 *   FAULT     0/1: add the fault-formation sum
 *   TILEABLE  0/1: wrap lattice indices with each octave's period
 *
 * Octave table (constant memory, built by noise.py), 4 words per octave:
 *   octf[4i..4i+3] = scale (lattice units per cell), offset x, offset z, amplitude
 *   octi[4i..4i+3] = period in lattice cells (0: none), seed hash (uint32
 *                    bits), float32 bits of 1/period, 0
 * octaves [0, n_main) are the basis, [n_main, n_main+n_warp) the warp x
 * field, [n_main+n_warp, n_main+2 n_warp) the warp z field.
 * Fault table, 4 floats per line, lengths in units of the fault softness w:
 *   normal x / w, normal z / w, offset / w - 1/2 (w and offset in cells), weight.
 */
#pragma OPENCL FP_CONTRACT OFF

#ifndef VW
#define VW 8
#endif
#ifndef RIDGED
#define RIDGED 0
#endif
#ifndef WARP
#define WARP 0
#endif
#ifndef FAULT
#define FAULT 0
#endif
#ifndef TILEABLE
#define TILEABLE 0
#endif

#define INLINE inline __attribute__((always_inline))
#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)

#if VW == 1
typedef float floatv;
typedef int intv;
typedef uint uintv;
#define convert_intv convert_int
#define convert_floatv convert_float
#define as_floatv as_float
#define as_uintv as_uint
#define LANES 0
#else
typedef CAT(float, VW) floatv;
typedef CAT(int, VW) intv;
typedef CAT(uint, VW) uintv;
#define convert_intv CAT(convert_int, VW)
#define convert_floatv CAT(convert_float, VW)
#define as_floatv CAT(as_float, VW)
#define as_uintv CAT(as_uint, VW)
#define vstorev CAT(vstore, VW)
#if VW == 2
#define LANES (intv)(0, 1)
#elif VW == 4
#define LANES (intv)(0, 1, 2, 3)
#elif VW == 8
#define LANES (intv)(0, 1, 2, 3, 4, 5, 6, 7)
#elif VW == 16
#define LANES (intv)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15)
#else
#error "VW must be 1, 2, 4, 8 or 16"
#endif
#endif

/* 16 gradient directions at 11.25 + k * 22.5 degrees: never axis aligned */
#define GA1 0.98078528f /* cos 11.25 */
#define GB1 0.19509032f /* sin 11.25 */
#define GA2 0.83146961f /* cos 33.75 */
#define GB2 0.55557023f /* sin 33.75 */
#define NOISE_SCALE 1.41421356f /* 2D gradient noise lies in [-1/sqrt2, 1/sqrt2] */

#define HX 0x8da6b343u
#define HZ 0xd8163841u

#define HASH_UINT uintv
#include "worldbake_hash.h"

/* dot(g, (fx, fz)) with g one of 16 unit vectors picked by 4 hash bits:
 * bit 3 picks the 11.25 or 33.75 degree pair, bit 2 swaps x and z (78.75,
 * 56.25 degrees), bits 0 and 1 flip the signs (exact: sign-bit xor) */
INLINE floatv grad(uintv h, floatv fx, floatv fz)
{
    intv b8 = (h & 8u) != 0u;
    intv b4 = (h & 4u) != 0u;
    floatv ga = select((floatv)(GA1), (floatv)(GA2), b8);
    floatv gb = select((floatv)(GB1), (floatv)(GB2), b8);
    floatv gx = select(ga, gb, b4);
    floatv gz = select(gb, ga, b4);
    gx = as_floatv(as_uintv(gx) ^ ((h & 1u) << 31));
    gz = as_floatv(as_uintv(gz) ^ ((h & 2u) << 30));
    return gx * fx + gz * fz;
}

INLINE floatv fade(floatv t)
{
    return t * t * t * (t * (t * 6.0f - 15.0f) + 10.0f);
}

/* floor as an int for |x| < 2^31, without a library call */
INLINE intv ifloor(floatv x)
{
    intv i = convert_intv(x); /* rounds toward zero */
    return select(i, i - 1, convert_floatv(i) > x);
}

/* i mod period for |i| < 2^24, branch-free: inv = 1/period rounded to
 * float32 may put the quotient one off, which the two selects correct */
INLINE intv wrap(intv i, int period, float inv)
{
    intv m = i - period * ifloor(convert_floatv(i) * inv);
    m = select(m, m - period, m >= period);
    m = select(m, m + period, m < 0);
    return m;
}

/* gradient noise at lattice position (px, pz), in [-1, 1] */
INLINE floatv gnoise(floatv px, floatv pz, int period, float inv, uint seed)
{
    intv ix0 = ifloor(px);
    intv iz0 = ifloor(pz);
    floatv fx = px - convert_floatv(ix0);
    floatv fz = pz - convert_floatv(iz0);
    intv ix1 = ix0 + 1;
    intv iz1 = iz0 + 1;
#if TILEABLE
    ix0 = wrap(ix0, period, inv);
    iz0 = wrap(iz0, period, inv);
    ix1 = wrap(ix1, period, inv);
    iz1 = wrap(iz1, period, inv);
#endif
    uintv hx0 = as_uintv(ix0) * HX;
    uintv hx1 = as_uintv(ix1) * HX;
    uintv hz0 = as_uintv(iz0) * HZ + seed;
    uintv hz1 = as_uintv(iz1) * HZ + seed;
    floatv fx1 = fx - 1.0f;
    floatv fz1 = fz - 1.0f;
    floatv d00 = grad(mix32(hx0 ^ hz0), fx, fz);
    floatv d10 = grad(mix32(hx1 ^ hz0), fx1, fz);
    floatv d01 = grad(mix32(hx0 ^ hz1), fx, fz1);
    floatv d11 = grad(mix32(hx1 ^ hz1), fx1, fz1);
    floatv u = fade(fx);
    floatv v = fade(fz);
    floatv a = d00 + u * (d10 - d00);
    floatv b = d01 + u * (d11 - d01);
    return (a + v * (b - a)) * NOISE_SCALE;
}

INLINE floatv clamp01(floatv x)
{
    x = select(x, (floatv)(0.0f), x < 0.0f);
    return select(x, (floatv)(1.0f), x > 1.0f);
}

INLINE floatv absf(floatv x)
{
    return as_floatv(as_uintv(x) & 0x7fffffffu);
}

INLINE floatv octave(floatv X, floatv Z, int i, __constant const float *restrict octf, __constant const int *restrict octi)
{
    float scale = octf[4 * i];
    floatv px = X * scale + octf[4 * i + 1];
    floatv pz = Z * scale + octf[4 * i + 2];
    return gnoise(px, pz, octi[4 * i], as_float(octi[4 * i + 2]), (uint)octi[4 * i + 1]);
}

/* fBm: sum of amplitude * noise over the octaves [first, first + n) */
INLINE floatv fbm(floatv X, floatv Z, int first, int n, __constant const float *restrict octf,
                  __constant const int *restrict octi)
{
    floatv sum = 0.0f;
    for (int i = first; i < first + n; ++i)
        sum = sum + octf[4 * i + 3] * octave(X, Z, i, octf, octi);
    return sum;
}

/* ridged multifractal (Musgrave, Texturing & Modeling ch. 16) */
INLINE floatv ridged(floatv X, floatv Z, int n, float roffset, float rgain, __constant const float *restrict octf,
                     __constant const int *restrict octi)
{
    floatv sum = 0.0f;
    floatv weight = 1.0f;
    for (int i = 0; i < n; ++i) {
        floatv s = roffset - absf(octave(X, Z, i, octf, octi));
        s = s * s;
        s = s * weight;
        sum = sum + s * octf[4 * i + 3];
        weight = clamp01(s * rgain);
    }
    return sum;
}

/* A (rows, cols) tile whose top-left cell is the world cell (col0, row0).
 * Work-item (i, j) computes the cells i*VW .. i*VW+VW-1 of tile row j.
 * height = hb + hs * value */
__kernel void terrain(__global float *restrict out, const int cols, const int rows, const int col0, const int row0,
                      const int n_main, const int n_warp, __constant const float *restrict octf,
                      __constant const int *restrict octi, const float hs, const float hb, const float roffset,
                      const float rgain, const float warp_cells, const int n_fault,
                      __constant const float *restrict fault)
{
    const int c = get_global_id(0) * VW;
    const int r = get_global_id(1);
    if (c >= cols || r >= rows)
        return;
    /* lanes past the last column compute a clamped cell and store nothing */
    intv col = (intv)(c) + LANES;
    col = select(col, (intv)(cols - 1), col >= cols);
    floatv X = convert_floatv(col + col0) + 0.5f;
    floatv Z = (floatv)((float)(row0 + r) + 0.5f);
    floatv value = 0.0f;

#if FAULT
    /* t = signed distance to the line / softness + 1/2, the line terms in
     * units of the softness; the row term is the same for all lanes */
    const float zrow = (float)(row0 + r) + 0.5f;
    for (int i = 0; i < n_fault; ++i) {
        float zt = fault[4 * i + 1] * zrow - fault[4 * i + 2];
        floatv t = clamp01(fault[4 * i] * X + zt);
        floatv S = t * t * (3.0f - 2.0f * t);
        value = value + fault[4 * i + 3] * (S + S - 1.0f);
    }
#endif

#if WARP
    floatv wx = fbm(X, Z, n_main, n_warp, octf, octi);
    floatv wz = fbm(X, Z, n_main + n_warp, n_warp, octf, octi);
    X = X + warp_cells * wx;
    Z = Z + warp_cells * wz;
#endif

#if RIDGED
    value = value + ridged(X, Z, n_main, roffset, rgain, octf, octi);
#else
    value = value + fbm(X, Z, 0, n_main, octf, octi);
#endif

    floatv h = hb + hs * value;
    __global float *dst = out + (size_t)r * (size_t)cols + (size_t)c;
#if VW == 1
    *dst = h;
#else
    if (c + VW <= cols) {
        vstorev(h, 0, dst);
    } else {
        float tmp[VW];
        vstorev(h, 0, tmp);
        for (int k = 0; k < cols - c; ++k)
            dst[k] = tmp[k];
    }
#endif
}

/* the roofline: a trivial kernel writing one float per cell */
__kernel void fill(__global float *out, const int n, const float value)
{
    const int i = get_global_id(0);
    if (i < n)
        out[i] = value;
}

/* a copy kernel: reads and writes one float per cell */
__kernel void copy(__global const float *src, __global float *dst, const int n)
{
    const int i = get_global_id(0);
    if (i < n)
        dst[i] = src[i];
}
