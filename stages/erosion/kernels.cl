/* worldbake erosion kernels: thermal weathering (Olsen's multi-neighbour talus
 * rule) and hydraulic erosion on the virtual-pipe shallow-water model.
 *
 * Every kernel reads its neighbours and writes only its own cells: no atomics,
 * no races, results independent of the work-group size. Every transfer between
 * two cells (water through a pipe, sediment carried with it, scree sliding
 * down) is one float computed from the same stored floats by the same
 * expression in both cells, so what leaves one cell is exactly what enters the
 * other; only the final rounding of each cell's own state is left.
 * stages/erosion/reference.py is the numpy twin of every kernel, operation for
 * operation (the two agree bit for bit).
 *
 * Work-items: each per-step kernel work-item handles VW consecutive cells of a
 * row as one floatVW vector (the same IEEE operations on every lane), in the
 * storm kernels a tile of such vectors (up to NV along a row, NR rows). PoCL
 * vectorizes across work-items only when clang's SLP pass has not already
 * packed pieces of the kernel into short vectors, which it does to these
 * kernels; writing the vectors ourselves is robust and is still plain
 * per-cell arithmetic for a GPU.
 *
 * Layout: every per-cell array has a one-cell halo ring and is padded so the
 * NDRange is a whole number of work-groups: cell (r, c) sits at
 * i = AT(r, c) = (r+1)*P + X0 + c, with X0 = 16 (the west halo at X0 - 1) and
 * the pitch P a multiple of 16 floats, so every row of cells starts on a 64-byte
 * boundary and a work-item's own vectors are aligned loads and stores (the
 * buffers are at least 128-byte aligned); P >= X0 + (work-items along a row) * (cells per work-item) + 1
 * (of every kernel) and (rows rounded up to the work-group) + 2 rows, so
 * neighbours are i+-1 and i+-P
 * without index clamping (clamped indices are gathers) and no bounds guard is
 * needed. Lanes beyond the grid compute on the padding and their results are
 * never read. Closed and open grids mask the ring out by the cell position;
 * periodic grids fill it with the wrapped values (kernel `halo`) after every
 * kernel that writes a field. Row r runs north to south, column c west to east.
 *
 * Interior work-items (all their cells and neighbours inside the grid) run
 * the same code with the neighbour masks known to be all true at compile time
 * (no selects); the masks only change which value a lane takes where a
 * neighbour is missing, so both paths give the same bits.
 *
 * Pipes: QE, QS, QW, QN hold each cell's outflow through its east, south,
 * west and north face per unit face width (m^2/s), never negative.
 *
 * Heights: h = Tb + dT where Tb is the input terrain (never changed) and dT
 * the accumulated change. dT is small, so erosion steps far below one ulp of
 * a 2000 m height are still represented; the mass budget sums dT + S.
 *
 * Only + - * / sqrt and compare-select in the per-step kernels: PoCL's fmax,
 * fmin and fabs builtins are scalar library calls, and correctly rounded IEEE
 * operations give the same bits at every vector width and on every device.
 *
 * X86_AVX512: PoCL 3.0's LLVM 14 takes Zen 4 for Zen 3 and compiles kernels
 * for AVX2 only, so a float16 lives in two ymm registers and the storm kernels
 * spill. With X86_AVX512 defined (pipeline.opencl.x86_avx512: PoCL on a CPU
 * that has AVX-512F/VL/DQ) the storm code is compiled for AVX-512 through a
 * clang target attribute. PoCL builds its work-group loops without it, and a
 * function for more features cannot be inlined into one for fewer, so the
 * work-item calls the body as a function: the vectors of a whole tile per
 * call pay for the call's arguments. The same IEEE operations run either way: same bits.
 *
 * Compile-time: BOUNDARY 0 closed, 1 open (free outfall), 2 periodic;
 * VW vector width (8 or 16); NV most vectors along a row and NR rows per
 * storm work-item (its tile); X86_AVX512.
 */
#pragma OPENCL FP_CONTRACT OFF
#pragma OPENCL EXTENSION cl_khr_fp64 : enable

#ifndef BOUNDARY
#define BOUNDARY 0
#endif
#ifndef VW
#define VW 8
#endif
#ifndef X0
#define X0 16
#endif
#ifndef NV
#define NV 1
#endif
#ifdef X86_AVX512
#define BODY __attribute__((noinline))
#else
#define BODY __attribute__((always_inline)) inline
#endif
#define AT(r, c) (((r) + 1) * P + X0 + (c))

#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)
#define floatV CAT(float, VW)
#define intV CAT(int, VW)
/* Unaligned vector access through a vector type whose alignment is lowered to
 * that of a float (vloadn/vstoren are out-of-line library calls in PoCL). */
typedef floatV __attribute__((aligned(4))) floatV_u;
#define LD(p, k) (*(__global const floatV_u *)((p) + (k)))
#define ST(v, p, k) (*(__global floatV_u *)((p) + (k)) = (v))
#define as_floatV CAT(as_float, VW)
#define as_intV CAT(as_int, VW)
#if VW == 8
#define LANES ((int8)(0, 1, 2, 3, 4, 5, 6, 7))
#elif VW == 16
#define LANES ((int16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15))
#endif

#define HMIN 1e-6f        /* face flow depth (m) below which a pipe carries nothing */
#define VEL_HMIN 1e-3f    /* depth floor (m) when dividing discharge by depth for velocity */
#define TINY 1e-30f
#define MAX(a, b) ((a) > (b) ? (a) : (b))
#define MIN(a, b) ((a) < (b) ? (a) : (b))
#define F(x) ((floatV)(x))
#define ZERO F(0.0f)

/* Cells (r, c0 .. c0+VW-1) of one vector and which neighbours exist. */
#if BOUNDARY == 2
#define MASKS                                                    \
    const intV exE = (intV)(-1), exW = (intV)(-1);               \
    const intV exS = (intV)(-1), exN = (intV)(-1);
#else
#define MASKS                                                    \
    const intV col = LANES + c0;                                 \
    const intV exE = col + 1 < cols, exW = col > 0;              \
    const intV exS = (intV)(r + 1 < rows ? -1 : 0);              \
    const intV exN = (intV)(r > 0 ? -1 : 0);
#endif
#define CELLS                                                    \
    const int c0 = get_global_id(0) * VW, r = get_global_id(1);  \
    const int i = AT(r, c0);                                     \
    MASKS
/* The storm kernels: each work-item runs a tile of NR rows of the grid's width
 * in vectors of VW cells, NV at most (TILE_VECTORS; see X86_AVX512), row after
 * row: a tile spans whole rows, so it reads every array in long runs that the
 * prefetchers follow from DRAM. Neighbouring cells of a tile share what they
 * have in common instead of computing it twice: the geometry of the face
 * between them in `flux`, and in `update` the sediment one sends the other
 * and its spq.
 * Whatever crosses from one vector to the next is carried in registers
 * (shifted by a lane), from one row to the next in per-vector arrays. The
 * first vector of a tile row and the first row of a tile compute everything
 * themselves, so no value ever comes from outside the tile and a cell on the
 * grid's edge (always first in its tile) applies its own neighbour masks.
 * Where a tile's data stay in a core's L2 the step is bound by the FP pipes,
 * not by memory, so the cells code is written for the fewest operations per
 * vector (bench/erosion.py measures the kernels against a roofline copy). */
#define TILE_VECTORS MIN((cols + VW - 1) / VW, NV)
#ifndef NR
#define NR 1
#endif
/* body(fresh_w, fresh_n, fresh_e) for every vector of the tile, with the flags
 * known at compile time in each copy (no branches in the cells code): the
 * first row computes everything itself, later rows share with the row above,
 * and along a row with the vectors before and after. */
#define STORM_TILE(body)                                                        \
    for (int rr = 0; rr < NR; rr++) {                                           \
        const int r = r00 + rr;                                                 \
        if (rr == 0) {                                                          \
            for (int v = 0; v < nv; v++) { TILE_CELLS(body, 1, 1, 1) }          \
        } else {                                                                \
            { const int v = 0; TILE_CELLS(body, 1, 0, nv == 1) }                \
            for (int v = 1; v + 1 < nv; v++) { TILE_CELLS(body, 0, 0, 0) }      \
            if (nv > 1) { const int v = nv - 1; TILE_CELLS(body, 0, 0, 1) }     \
        }                                                                       \
    }
#define TILE_CELLS(body, fresh_w, fresh_n, fresh_e) \
    const int c0 = c00 + v * VW;                    \
    const int i = AT(r, c0);                        \
    MASKS                                           \
    body(fresh_w, fresh_n, fresh_e)
/* Lane shifts between consecutive vectors of a row: [prev[VW-1], cur[0..VW-2]]
 * (the western neighbours of cur) and [cur[1..VW-1], next[0]] (the eastern). */
#if VW == 8
#define WEST_OF(prev, cur) __builtin_shufflevector(prev, cur, 7, 8, 9, 10, 11, 12, 13, 14)
#define EAST_OF(cur, next) __builtin_shufflevector(cur, next, 1, 2, 3, 4, 5, 6, 7, 8)
#elif VW == 16
#define WEST_OF(prev, cur) \
    __builtin_shufflevector(prev, cur, 15, 16, 17, 18, 19, 20, 21, 22, 23, 24, 25, 26, 27, 28, 29, 30)
#define EAST_OF(cur, next) \
    __builtin_shufflevector(cur, next, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16)
#endif
/* every cell of the vector and all its neighbours inside the grid */
#define INNER ((c0 > 0) & (c0 + VW < cols) & (r > 0) & (r + 1 < rows))
#define ALL ((intV)(-1))
/* Call fn(args..., i, exE, exS, exW, exN) for the cells of one vector:
 * with masks known to be all true (no selects) for interior work-items. */
#if BOUNDARY == 2
#define DISPATCH(fn, ...) fn(__VA_ARGS__, i, exE, exS, exW, exN)
#else
#define DISPATCH(fn, ...)                                   \
    if (INNER)                                              \
        fn(__VA_ARGS__, i, ALL, ALL, ALL, ALL);             \
    else                                                    \
        fn(__VA_ARGS__, i, exE, exS, exW, exN)
#endif

#ifdef X86_AVX512 /* everything the storm kernels call, up to their __kernel entries */
#pragma clang attribute push (__attribute__((target("avx512f,avx512vl,avx512dq"))), apply_to = function)
#endif

/* Square root, correctly rounded (IEEE): the same bits as numpy's np.sqrt on
 * every device. load_program builds with -cl-fp32-correctly-rounded-divide-sqrt,
 * so the builtin sqrt is exact everywhere; on x86 PoCL turns a float16 sqrt
 * into an LLVM crash and a float8 one into library calls, so there the AVX
 * instruction itself (vsqrtps, also exact) is called, 8 lanes at a time, or
 * 16 with X86_AVX512 (4: the current rounding mode, round to nearest). */
#if defined(__x86_64__) && defined(__AVX__)
typedef float v8sf_ __attribute__((vector_size(32)));
inline float8 sqrt8_avx(float8 x)
{
    return __builtin_astype(__builtin_ia32_sqrtps256(__builtin_astype(x, v8sf_)), float8);
}
#if VW == 8
inline floatV sqrt_v(floatV x) { return sqrt8_avx(x); }
#elif VW == 16 && defined(X86_AVX512)
typedef float v16sf_ __attribute__((vector_size(64)));
inline floatV sqrt_v(floatV x)
{
    return __builtin_astype(__builtin_ia32_sqrtps512(__builtin_astype(x, v16sf_), 4), float16);
}
#elif VW == 16
inline floatV sqrt_v(floatV x) { return (floatV)(sqrt8_avx(x.lo), sqrt8_avx(x.hi)); }
#endif
#else
inline floatV sqrt_v(floatV x) { return sqrt(x); }
#endif

/* ---------------------------------------------------------------------------
 * 1. Pipe fluxes: Mei et al. 2007 virtual pipes whose cross-section is the flow
 * depth at the face (the local-inertial shallow-water momentum equation of
 * Bates et al. 2010), semi-implicit Darcy-Weisbach friction, then the outflow
 * scaling that keeps water non-negative.
 *   hf = max(eta_i, eta_j) - max(h_i, h_j)
 *   q <- max(0, (q + g dt hf (eta_i - eta_j) / dx) / (1 + dt (f/8) q / hf^2))
 *   (evaluated as (q + ...) hf^2 / (hf^2 + dt (f/8) q): one division; a face
 *   at most HMIN deep carries nothing)
 *   q <- q * min(1, (1 - eps) W dx / (dt sum q))
 * A missing neighbour of an open grid is a dry ghost at the same ground height
 * (free outfall); of a closed grid, a wall (q = 0).
 * ------------------------------------------------------------------------- */
/* What the two cells of a face share: the face depth hf, hf^2 and the gravity
 * term g dt/dx hf (eta_i - eta_j), from the side of cell i. From the side of j
 * the same face has the same hf and h2 and exactly -gt: IEEE subtraction and
 * multiplication are symmetric in sign, and the branches of hf are each
 * other's mirror image (a difference of +0 on both sides is the one case not
 * mirrored, where hf is max(wi, wj) either way and gt a zero that q + gt and
 * q - gt absorb alike). So a face computed once serves both cells bit for bit. */
typedef struct { floatV hf, h2, gt; } Face;

inline Face face_geo(floatV hi, floatV wi, floatV hj, floatV wj, intV ex, float g_dt_dx)
{
    Face f;
    floatV dh = ex ? hi - hj : ZERO;
    wj = ex ? wj : ZERO;
    /* the face depth, written so thin films stay exact at any altitude */
    f.hf = dh >= 0.0f ? MAX(wi, wj - dh) : MAX(wi + dh, wj);
    floatV deta = dh + (wi - wj);
    f.h2 = f.hf > HMIN ? f.hf * f.hf : ZERO;  /* a face at most HMIN deep carries nothing (face_q) */
    f.gt = g_dt_dx * f.hf * deta;
    return f;
}

/* The new outflow through a face, computed here (here = 1: gt seen from this
 * cell) or by the neighbour across it (here = 0: this cell's gt is -f.gt; a
 * compile-time constant at every call). A dry face (h2 = 0) gives 0 or 0 / 0,
 * and MAX(NaN, 0) is 0: it carries nothing. */
inline floatV face_q(floatV q, Face f, const int here, intV ex, float fric_dt)
{
    floatV qn = ((here ? q + f.gt : q - f.gt) * f.h2) / (f.h2 + fric_dt * q);  /* one division */
    qn = MAX(qn, ZERO);
#if BOUNDARY == 0
    qn = ex ? qn : ZERO;
#endif
    return qn;
}

#define FLUX_ARGS                                                                            \
    __global const float *restrict Tb, __global const float *restrict dT,                    \
    __global const float *restrict W,                                                        \
    __global float *restrict QE, __global float *restrict QS,                                \
    __global float *restrict QW, __global float *restrict QN,                                \
    __global float *restrict wave, /* when want_wave: max over faces of q/hf + sqrt(g hf) */  \
    const int rows, const int cols, const int P,                                             \
    const float g_dt_dx,    /* g dt / dx */                                                  \
    const float fric_dt,    /* (f/8) dt (s) */                                               \
    const float dx_dt,      /* (1 - eps) dx / dt (m/s) */                                    \
    const int want_wave, const float g
#define FLUX_PASS Tb, dT, W, QE, QS, QW, QN, wave, rows, cols, P, g_dt_dx, fric_dt, dx_dt, want_wave, g

/* One vector of the flux tile. fresh_w / fresh_n: compute the west / north
 * face here; otherwise they are the east face of the vector before (*fw, one
 * lane over) and the south face of the row above (*fn). On return *fw and *fn
 * hold this vector's east and south faces for the next ones. */
__attribute__((always_inline))
inline void flux_cells(FLUX_ARGS, const int fresh_w, const int fresh_n, Face *fw, Face *fn,
                       const int i, const intV exE, const intV exS, const intV exW, const intV exN)
{
    floatV hi = LD(Tb, i) + LD(dT, i), wi = LD(W, i);
    Face fE = face_geo(hi, wi, LD(Tb, i + 1) + LD(dT, i + 1), LD(W, i + 1), exE, g_dt_dx);
    Face fS = face_geo(hi, wi, LD(Tb, i + P) + LD(dT, i + P), LD(W, i + P), exS, g_dt_dx);
    Face fW = fresh_w ? face_geo(hi, wi, LD(Tb, i - 1) + LD(dT, i - 1), LD(W, i - 1), exW, g_dt_dx)
                      : (Face){WEST_OF(fw->hf, fE.hf), WEST_OF(fw->h2, fE.h2), WEST_OF(fw->gt, fE.gt)};
    Face fN = fresh_n ? face_geo(hi, wi, LD(Tb, i - P) + LD(dT, i - P), LD(W, i - P), exN, g_dt_dx)
                      : *fn;
    *fw = fE;
    *fn = fS;
    floatV qE = face_q(LD(QE, i), fE, 1, exE, fric_dt);
    floatV qS = face_q(LD(QS, i), fS, 1, exS, fric_dt);
    floatV qW = face_q(LD(QW, i), fW, fresh_w, exW, fric_dt);
    floatV qN = face_q(LD(QN, i), fN, fresh_n, exN, fric_dt);
    floatV sum = ((qE + qS) + qW) + qN;
    /* sum = 0: k is 1 (W dx/dt / 0 = inf), or 0 / 0 where the select below takes 0;
     * either way it scales four zeros */
    floatV k = MIN(F(1.0f), (wi * dx_dt) / sum);
    k = wi > TINY ? k : ZERO;  /* subnormal water: W dx/dt has too few bits to bound sum q */
    qE *= k; qS *= k; qW *= k; qN *= k;
    ST(qE, QE, i); ST(qS, QS, i); ST(qW, QW, i); ST(qN, QN, i);
    if (want_wave) {
        /* the CFL speed where water moves: face velocity q/hf plus the gravity wave */
        floatV sp = sqrt_v(g * wi);
        sp = qE > 0.0f ? MAX(sp, qE / MAX(fE.hf, F(HMIN)) + sqrt_v(g * fE.hf)) : sp;
        sp = qS > 0.0f ? MAX(sp, qS / MAX(fS.hf, F(HMIN)) + sqrt_v(g * fS.hf)) : sp;
        sp = qW > 0.0f ? MAX(sp, qW / MAX(fW.hf, F(HMIN)) + sqrt_v(g * fW.hf)) : sp;
        sp = qN > 0.0f ? MAX(sp, qN / MAX(fN.hf, F(HMIN)) + sqrt_v(g * fN.hf)) : sp;
        ST(sp, wave, i);
    }
}

BODY void flux_body(FLUX_ARGS, const int c00, const int r00)
{
    const int nv = TILE_VECTORS;
    Face fw = {ZERO, ZERO, ZERO}, fn[NV];  /* east face of the vector before; south faces of the row above */
#define FLUX_TILE_CELLS(fresh_w, fresh_n, fresh_e) DISPATCH(flux_cells, FLUX_PASS, fresh_w, fresh_n, &fw, &fn[v]);
    STORM_TILE(FLUX_TILE_CELLS)
#undef FLUX_TILE_CELLS
}

/* Sediment that leaves a cell with its water through one face in one step,
 * S (q c) / W, written q * spq with the cell's sediment per unit discharge
 * spq = (S c) * (1 / W): one division and two products per cell, then one
 * product per face instead of three for S * ((q c) * (1 / W)).
 * The outflow scaling in `flux` leaves every cell at least LIMITER_EPS = 2^-20
 * of its water, far more than the roundings of q, of sum q c and of spq (about
 * 12 * 2^-24), so sum q c < W and the faces never carry off more than S; cells
 * holding TINY or less send nothing (their q is 0). The sender and the
 * receiver evaluate it from the same stored floats, so both get the same bits. */
inline floatV sed_per_q(floatV S, float c, floatV W)
{
    return (S * c) * (1.0f / MAX(W, F(TINY)));
}

/* ---------------------------------------------------------------------------
 * 2. Water, sediment, erosion/deposition, rain, evaporation, moisture.
 * Water:     W1 = W + dt/dx (sum q_in - sum q_out)
 * Sediment:  moved in flux form with the water (q spq on every face).
 * Capacity:  C = Kc |q| max(sin a, sin a_min)   (m; |q| unit discharge, m^2/s)
 * Exchange:  C > S: erode min(ks (C - S), h - min h_neighbour); else deposit
 *            kd (S - C); ks = 1-exp(-Ks dt), kd = 1-exp(-Kd dt). The amount moved
 *            is the actual change of dT, so dT + S is conserved.
 * Rain/evap: W += rain dt; evaporate min(W, E dt); water gone -> all sediment
 *            settles (instead of the exchange).
 * Moisture:  M += am (min(W/wet, 1) - M), am = 1 - exp(-dt/tau).
 * ------------------------------------------------------------------------- */
#define UPDATE_ARGS                                                                  \
    __global const float *restrict Tb, __global const float *restrict dT,            \
    __global const float *restrict W, __global const float *restrict S,              \
    __global const float *restrict QE, __global const float *restrict QS,            \
    __global const float *restrict QW, __global const float *restrict QN,            \
    __global float *restrict M, __global float *restrict EA,                         \
    __global float *restrict dT_out, __global float *restrict W_out,                 \
    __global float *restrict S_out,                                                  \
    const int rows, const int cols, const int P,                                     \
    const float cc,                   /* dt/dx */                                    \
    const float kc,                   /* capacity, s/m */                            \
    const float sin_min2,             /* sin(a_min)^2 */                             \
    const float ks_f, const float kd_f,                                              \
    const float rain_dt, const float evap_dt,                                        \
    const float inv_wet, const float am,                                             \
    const float four_dx2              /* 4 dx^2 (m^2) */
#define UPDATE_PASS Tb, dT, W, S, QE, QS, QW, QN, M, EA, dT_out, W_out, S_out, rows, cols, P, \
    cc, kc, sin_min2, ks_f, kd_f, rain_dt, evap_dt, inv_wet, am, four_dx2

/* One vector of the update tile. The sediment a cell sends west and north is
 * what its neighbours there receive from it, and its spq (sediment per unit
 * discharge) is shared with the cells north and west of it: fresh_w / fresh_n
 * compute the western / northern inflows here; otherwise they come from the vector before (*w_so: its sediment
 * sent east, *w_h: its height; one lane over) and from the row above (*n_so:
 * sediment sent south, *n_h: height), and spq of this row from the row above
 * (*n_spq), of the vector after from spq_next unless fresh_e. On return the
 * carries hold this vector's values for the next ones (*n_spq: spq of the
 * row below). */
__attribute__((always_inline))
inline void update_cells(UPDATE_ARGS, const int fresh_w, const int fresh_n, const int fresh_e,
                         floatV *w_so, floatV *w_h, floatV *n_spq, floatV *n_so, floatV *n_h, const floatV spq_next,
                         const int i, const intV exE, const intV exS, const intV exW, const intV exN)
{
    const int iE = i + 1, iS = i + P, iW = i - 1, iN = i - P;
    floatV wi = LD(W, i), si = LD(S, i), dti = LD(dT, i);
    floatV hi = LD(Tb, i) + dti;
    floatV oE = LD(QE, i), oS = LD(QS, i), oW = LD(QW, i), oN = LD(QN, i);
    /* inflow: the neighbour on each side sends through its opposite face */
    floatV iqE = exE ? LD(QW, iE) : ZERO;
    floatV iqS = exS ? LD(QN, iS) : ZERO;
    floatV iqW = exW ? LD(QE, iW) : ZERO;
    floatV iqN = exN ? LD(QS, iN) : ZERO;
    floatV spq_i = fresh_n ? sed_per_q(si, cc, wi) : *n_spq;
    floatV soE = oE * spq_i;
    floatV soS = oS * spq_i;
    floatV soW = oW * spq_i;
    floatV soN = oN * spq_i;
    floatV spq_E = fresh_e ? sed_per_q(LD(S, iE), cc, LD(W, iE)) : EAST_OF(spq_i, spq_next);
    floatV spq_S = sed_per_q(LD(S, iS), cc, LD(W, iS));
    floatV siE = exE ? iqE * spq_E : ZERO;
    floatV siS = exS ? iqS * spq_S : ZERO;
    /* the western neighbour's sediment sent east, the northern one's sent south */
    floatV soE_w = fresh_w ? iqW * sed_per_q(LD(S, iW), cc, LD(W, iW)) : WEST_OF(*w_so, soE);
    floatV soS_n = fresh_n ? iqN * sed_per_q(LD(S, iN), cc, LD(W, iN)) : *n_so;
    floatV siW = exW ? soE_w : ZERO;
    floatV siN = exN ? soS_n : ZERO;
    floatV h_w = fresh_w ? LD(Tb, iW) + LD(dT, iW) : WEST_OF(*w_h, hi);
    floatV h_n = fresh_n ? LD(Tb, iN) + LD(dT, iN) : *n_h;
    floatV hE = exE ? LD(Tb, iE) + LD(dT, iE) : hi;
    floatV hS = exS ? LD(Tb, iS) + LD(dT, iS) : hi;
    floatV hW = exW ? h_w : hi;
    floatV hN = exN ? h_n : hi;
    *w_so = soE; *w_h = hi;
    *n_spq = spq_S; *n_so = soS; *n_h = hi;

    floatV qin_sum = ((iqE + iqS) + iqW) + iqN;
    floatV qout_sum = ((oE + oS) + oW) + oN;
    floatV w1 = MAX(wi + (qin_sum - qout_sum) * cc, ZERO);
    floatV s_in = ((siE + siS) + siW) + siN;
    floatV s_out = ((soE + soS) + soW) + soN;
    floatV s1 = MAX(si + (s_in - s_out), ZERO);

    /* twice the unit discharge through the cell (m^2/s): the sum of its two faces per axis */
    floatV qx2 = (iqW - oW) + (oE - iqE);
    floatV qy2 = (iqN - oN) + (oS - iqS);
    /* sin^2 of the terrain slope, g^2 / (1 + g^2) with g^2 = |dh|^2 / (2 dx)^2 from
     * central differences (one-sided at closed and open edges) */
    floatV dhx = hE - hW, dhy = hS - hN;
    floatV dh2 = dhx * dhx + dhy * dhy;
    floatV sin2 = dh2 / (four_dx2 + dh2);
    floatV cap = (0.5f * kc) * sqrt_v((qx2 * qx2 + qy2 * qy2) * MAX(sin2, F(sin_min2)));

    /* erosion never takes a cell below its lowest neighbour: no pits are dug
     * (a pit would fill with deep water whose flow digs it deeper) */
    floatV hlow = MIN(MIN(hE, hW), MIN(hS, hN));
    floatV emax = MAX(hi - hlow, ZERO);

    floatV w2 = w1 + rain_dt;
    floatV ev = MIN(w2, F(evap_dt));
    floatV w3 = w2 - ev;
    floatV ev_act = w2 - w3;

    /* how far the bed drops: eroded while the water carries less than its capacity,
     * negative (deposited) above it, and where the water is gone, all it carried
     * settles; the sediment gains exactly what the bed lost */
    floatV room = cap - s1;
    floatV drop = room > 0.0f ? MIN(ks_f * room, emax) : kd_f * room;
    drop = w3 <= 0.0f ? -s1 : drop;
    floatV dt1 = dti - drop;
    floatV s2 = MAX(s1 + (dti - dt1), ZERO);

    floatV pres = MIN(w3 * inv_wet, F(1.0f));
    floatV m = LD(M, i);
    ST(m + am * (pres - m), M, i);
    ST(LD(EA, i) + ev_act, EA, i);
    ST(w3, W_out, i);
    ST(s2, S_out, i);
    ST(dt1, dT_out, i);
}

BODY void update_body(UPDATE_ARGS, const int c00, const int r00)
{
    /* carried from the vector before, and per vector from the row above */
    const int nv = TILE_VECTORS;
    floatV w_so = ZERO, w_h = ZERO, n_spq[NV + 1], n_so[NV], n_h[NV];
    n_spq[nv] = ZERO;  /* read (not used) by the last vector of a row */
#define UPDATE_TILE_CELLS(fresh_w, fresh_n, fresh_e) \
    DISPATCH(update_cells, UPDATE_PASS, fresh_w, fresh_n, fresh_e, &w_so, &w_h, &n_spq[v], &n_so[v], &n_h[v], \
             n_spq[v + 1]);
    STORM_TILE(UPDATE_TILE_CELLS)
#undef UPDATE_TILE_CELLS
}

#ifdef X86_AVX512
#pragma clang attribute pop
#endif

__kernel void flux(FLUX_ARGS)
{
    flux_body(FLUX_PASS, get_global_id(0) * (VW * TILE_VECTORS), get_global_id(1) * NR);
}

__kernel void update(UPDATE_ARGS)
{
    update_body(UPDATE_PASS, get_global_id(0) * (VW * TILE_VECTORS), get_global_id(1) * NR);
}

/* ---------------------------------------------------------------------------
 * 3. Thermal weathering, Olsen (2004) multi-neighbour rule on the Moore
 * neighbourhood, in gather form (two passes, no atomics).
 * d_k = h - h_k; T_k = dx tan(talus) (axial) or sqrt(2) dx tan(talus) (diagonal).
 * A cell moves c * max_k(d_k - T_k) in total, to every neighbour with d_k > T_k
 * in proportion d_k / sum d_k. Pass 1 stores s = c * max(d_k - T_k) / sum d_k
 * and r = 1 / (number of neighbours that send to this cell); pass 2 gathers:
 * h' = h - sum (s_i d_ik) r_k + sum (s_k d_ki) r_i.
 * The r share is ours: Olsen's rule updates cells one after another, and in
 * parallel a pit receives from all 8 neighbours at once (4 times too much with
 * c = 0.5: a -1000 m hole becomes a +3000 m tower). Sharing each receiver
 * between its senders bounds what it gets by c times the largest excess; a
 * cell with one sender above it is treated exactly as in Olsen's rule.
 * Neighbours outside a closed or open grid do not exist (scree stays inside).
 * During the storm (bank slumping) material only slides into cells holding
 * more than wet_min metres of water: banks collapse into the channels. Both
 * ends of a transfer test the same stored W. wet_min < 0: everywhere.
 * Order of the neighbours: E, S, W, N, SE, SW, NW, NE.
 * ------------------------------------------------------------------------- */
#define MOORE                                                                    \
    const int off[8] = {1, P, -1, -P, P + 1, P - 1, -P - 1, -P + 1};             \
    const intV ex[8] = {exE, exS, exW, exN, exS & exE, exS & exW, exN & exW, exN & exE};

__kernel void thermal_send(__global const float *restrict Tb, __global const float *restrict dT,
                           __global const float *restrict W,
                           __global float *restrict s_out, __global float *restrict r_out,
                           const int rows, const int cols, const int P,
                           const float t_ax, const float t_dg, const float cfrac, const float wet_min)
{
    CELLS
    MOORE
    floatV hi = LD(Tb, i) + LD(dT, i);
    intV wet_i = LD(W, i) > wet_min;
    floatV dtot = ZERO, emax = ZERO, senders = ZERO;
    for (int k = 0; k < 8; k++) {
        int j = i + off[k];
        floatV d = hi - (LD(Tb, j) + LD(dT, j));
        float t = k < 4 ? t_ax : t_dg;
        intV m = ex[k] & (d > t) & (LD(W, j) > wet_min);
        dtot = m ? dtot + d : dtot;
        emax = m ? MAX(emax, d - t) : emax;
        senders = (ex[k] & (-d > t) & wet_i) ? senders + 1.0f : senders;  /* a higher neighbour sends here */
    }
    ST(dtot > 0.0f ? (cfrac * emax) / MAX(dtot, F(TINY)) : ZERO, s_out, i);
    ST(1.0f / MAX(senders, F(1.0f)), r_out, i);
}

__kernel void thermal_apply(__global const float *restrict Tb, __global const float *restrict dT,
                            __global const float *restrict W,
                            __global const float *restrict s, __global const float *restrict rr,
                            __global float *restrict dT_out,
                            const int rows, const int cols, const int P,
                            const float t_ax, const float t_dg, const float wet_min)
{
    CELLS
    MOORE
    floatV hi = LD(Tb, i) + LD(dT, i);
    floatV si = LD(s, i), ri = LD(rr, i);
    intV wet_i = LD(W, i) > wet_min;
    floatV out = ZERO, in = ZERO;
    for (int k = 0; k < 8; k++) {
        int j = i + off[k];
        floatV hj = LD(Tb, j) + LD(dT, j);
        float t = k < 4 ? t_ax : t_dg;
        floatV d = hi - hj;
        out = (ex[k] & (d > t) & (LD(W, j) > wet_min)) ? out + (si * d) * LD(rr, j) : out;
        floatV e = hj - hi;
        in = (ex[k] & (e > t) & wet_i) ? in + (LD(s, j) * e) * ri : in;
    }
    ST(LD(dT, i) + (in - out), dT_out, i);
}

/* ---------------------------------------------------------------------------
 * Scalar kernels: boundary bookkeeping, halo, diagnostics, output maps.
 * ------------------------------------------------------------------------- */

/* Open grids: the water and sediment each boundary face lets out in this step,
 * accumulated in float64 per face (run before the state buffers swap roles).
 * Faces: [0,rows) east, [rows, rows+cols) south, then west, then north. */
__kernel void boundary_out(__global const float *restrict W, __global const float *restrict S,
                           __global const float *restrict QE, __global const float *restrict QS,
                           __global const float *restrict QW, __global const float *restrict QN,
                           __global double *restrict bnd, const int rows, const int cols, const int P,
                           const float cc)
{
    int f = get_global_id(0);
    int nf = 2 * (rows + cols);
    if (f >= nf) return;
    int r, c;
    if (f < rows) { r = f; c = cols - 1; }
    else if (f < rows + cols) { c = f - rows; r = rows - 1; }
    else if (f < 2 * rows + cols) { r = f - rows - cols; c = 0; }
    else { c = f - 2 * rows - cols; r = 0; }
    int i = AT(r, c);
    float q = f < rows ? QE[i] : f < rows + cols ? QS[i] : f < 2 * rows + cols ? QW[i] : QN[i];
    float spq = (S[i] * cc) * (1.0f / (W[i] > TINY ? W[i] : TINY));  /* as sed_per_q */
    bnd[f] += (double)(q * cc);
    bnd[nf + f] += (double)(q * spq);
}

/* Periodic grids: fill the halo ring of up to four arrays with wrapped values.
 * Work-items [0, rows) do the west and east ghosts of row r, [rows, rows+cols+2)
 * the north and south ghost rows (corners included) straight from the interior. */
inline void wrap1(__global float *a, int k, int rows, int cols, int P)
{
    if (k < rows) {
        a[AT(k, -1)] = a[AT(k, cols - 1)];
        a[AT(k, cols)] = a[AT(k, 0)];
    } else {
        int c = k - rows - 1;  /* -1 .. cols: the ghost rows with their corners */
        int src = c < 0 ? cols - 1 : (c == cols ? 0 : c);
        a[AT(-1, c)] = a[AT(rows - 1, src)];
        a[AT(rows, c)] = a[AT(0, src)];
    }
}

__kernel void halo(__global float *a, __global float *b, __global float *c_, __global float *d,
                   const int n, const int rows, const int cols, const int P)
{
    int k = get_global_id(0);
    if (k >= rows + cols + 2) return;
    wrap1(a, k, rows, cols, P);
    if (n > 1) wrap1(b, k, rows, cols, P);
    if (n > 2) wrap1(c_, k, rows, cols, P);
    if (n > 3) wrap1(d, k, rows, cols, P);
}

/* Diagnostics, one work-item per row, 8 cells at a time: each lane sums
 * its columns (c = lane, lane + 8, ...) in float64, then the lanes are added in
 * a fixed tree order, so the sums do not depend on the device or the
 * work-group size. sums[r] = (sum W, sum dT, sum S, sum EA, sum |dT|), then EA
 * is reset; mx[r] = (max CFL speed from the last flux pass that measured it,
 * min W, min S, count of non-finite values, max W). A cell with any
 * non-finite value is counted and left out of the sums (the stage stops on
 * it). x - x is 0 exactly when x is finite (isfinite is a library call). */
typedef float8 __attribute__((aligned(4))) float8_u;
#define LD8(p, k) (*(__global const float8_u *)((p) + (k)))
#define ST8(v, p, k) (*(__global float8_u *)((p) + (k)) = (v))

inline double hsum8(double8 v)
{
    return ((v.s0 + v.s1) + (v.s2 + v.s3)) + ((v.s4 + v.s5) + (v.s6 + v.s7));
}

inline float hmin8(float8 v)
{
    float4 a = MIN(v.lo, v.hi);
    float2 b = MIN(a.lo, a.hi);
    return MIN(b.lo, b.hi);
}

inline float hmax8(float8 v)
{
    float4 a = MAX(v.lo, v.hi);
    float2 b = MAX(a.lo, a.hi);
    return MAX(b.lo, b.hi);
}

__kernel void diag_rows(__global const float *restrict dT, __global const float *restrict W,
                        __global const float *restrict S, __global const float *restrict QE,
                        __global const float *restrict QS, __global const float *restrict QW,
                        __global const float *restrict QN, __global float *restrict EA,
                        __global const float *restrict wavebuf,
                        __global double *restrict sums, __global float *restrict mx,
                        const int rows, const int cols, const int P)
{
    int r = get_global_id(0);
    if (r >= rows) return;
    const int8 lane = (int8)(0, 1, 2, 3, 4, 5, 6, 7);
    const float8 z8 = (float8)(0.0f);
    double8 sw = (double8)(0.0), sd = sw, ss = sw, se = sw, sa = sw;
    float8 wave = z8, wmax = z8, wmin = (float8)(INFINITY), smin = wmin;
    int8 bad = (int8)(0);
    for (int c = 0; c < cols; c += 8) {  /* rows are padded: lanes past cols read padding */
        int i = AT(r, c);
        float8 w = LD8(W, i), d = LD8(dT, i), s = LD8(S, i), e = LD8(EA, i);
        float8 qe = LD8(QE, i), qs = LD8(QS, i), qw = LD8(QW, i), qn = LD8(QN, i);
        float8 zero_if_finite = (((w - w) + (d - d)) + ((s - s) + (e - e))) +
                                (((qe - qe) + (qs - qs)) + ((qw - qw) + (qn - qn)));
        int8 in = lane + c < cols;
        int8 ok = in & (zero_if_finite == 0.0f);
        bad -= in & ~ok;  /* true is -1 */
        sw += convert_double8(ok ? w : z8);
        sd += convert_double8(ok ? d : z8);
        ss += convert_double8(ok ? s : z8);
        se += convert_double8(ok ? e : z8);
        sa += convert_double8(ok ? (d < 0.0f ? -d : d) : z8);
        ST8(ok ? z8 : e, EA, i);
        wmin = ok ? MIN(wmin, w) : wmin;
        smin = ok ? MIN(smin, s) : smin;
        wmax = ok ? MAX(wmax, w) : wmax;
        wave = ok ? MAX(wave, LD8(wavebuf, i)) : wave;
    }
    sums[5 * r + 0] = hsum8(sw); sums[5 * r + 1] = hsum8(sd); sums[5 * r + 2] = hsum8(ss);
    sums[5 * r + 3] = hsum8(se); sums[5 * r + 4] = hsum8(sa);
    int4 b4 = bad.lo + bad.hi;
    int2 b2 = b4.lo + b4.hi;
    mx[5 * r + 0] = hmax8(wave); mx[5 * r + 1] = hmin8(wmin); mx[5 * r + 2] = hmin8(smin);
    mx[5 * r + 3] = (float)(b2.lo + b2.hi); mx[5 * r + 4] = hmax8(wmax);
}

/* Velocity (m/s) of every cell for the output maps: (vx east, vz south),
 * the mean discharge of the two faces on each axis over the depth. */
__kernel void velocity(__global const float *restrict QE, __global const float *restrict QS,
                       __global const float *restrict QW, __global const float *restrict QN,
                       __global const float *restrict W, __global float *restrict VX,
                       __global float *restrict VZ, const int rows, const int cols, const int P)
{
    int c = get_global_id(0), r = get_global_id(1);
    if (c >= cols || r >= rows) return;
    int i = AT(r, c);
#if BOUNDARY == 2
    int exE = 1, exS = 1, exW = 1, exN = 1;
#else
    int exE = c + 1 < cols, exS = r + 1 < rows, exW = c > 0, exN = r > 0;
#endif
    float iqE = exE ? QW[i + 1] : 0.0f;
    float iqS = exS ? QN[i + P] : 0.0f;
    float iqW = exW ? QE[i - 1] : 0.0f;
    float iqN = exN ? QS[i - P] : 0.0f;
    float qx = 0.5f * ((iqW - QW[i]) + (QE[i] - iqE));
    float qy = 0.5f * ((iqN - QN[i]) + (QS[i] - iqS));
    float h = W[i] > VEL_HMIN ? W[i] : VEL_HMIN;
    VX[i] = qx / h;
    VZ[i] = qy / h;
}
