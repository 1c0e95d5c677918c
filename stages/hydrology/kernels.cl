// Hydrology kernels. Grids are row-major, row 0 north. Cell kinds:
//   0 interior data cell, 1 edge cell (map border or 8-adjacent to no-data: a
//   Priority-Flood seed and an outlet), 2 no-data.
// D8 codes follow pysheds' neighbour order N, NE, E, SE, S, SW, W, NW (0..7);
// -1 outlet (edge cell), -2 no-data, -3 pit/flat (no strictly lower neighbour).
// Every result is exact: min/max on floats, integer sums. No atomics.

__constant int DR[8] = {-1, -1, 0, 1, 1, 1, 0, -1};
__constant int DC[8] = {0, 1, 1, 1, 0, -1, -1, -1};

#ifndef ACC_T
#define ACC_T uint
#endif

// The epsilon step of Priority-Flood+epsilon, safe in float32 at any height:
// one ulp (the next float up) where |x| >= 1, and x + 2^-23 (rounded) below,
// so the step never produces a denormal that a flush-to-zero device would lose.
inline float step_up(float x)
{
    if (isinf(x)) return x;
    if (fabs(x) >= 1.0f) {
        int i = as_int(x);
        return as_float(x > 0.0f ? i + 1 : i - 1);
    }
    return x + 0x1p-23f;
}

// Depression filling by minimax relaxation, one work-item per tile of T x T
// cells: Gauss-Seidel sweeps in four alternating raster orders inside the
// tile until it is a fixed point of W = max(h, step(min_neighbours W)),
// reading cells of other tiles from Wpub (published at the end of the
// previous pass: Jacobi between tiles, so no data race). The fixed point is
// unique and equals the Priority-Flood result whatever the schedule.
__kernel void fill_tiles(__global const float* h, __global const uchar* kind, __global float* W,
                         __global const float* Wpub, __global const uchar* active, __global uchar* changed,
                         int rows, int cols, int T, int tiles_x, int ntiles, int eps, int max_sweeps)
{
    int t = get_global_id(0);
    if (t >= ntiles) return;
    if (!active[t]) { changed[t] = 0; return; }
    int r0 = (t / tiles_x) * T, c0 = (t % tiles_x) * T;
    int r1 = min(r0 + T, rows), c1 = min(c0 + T, cols);
    int nr = r1 - r0, nc = c1 - c0;
    int any = 0;
    for (int s = 0; s < max_sweeps; ++s) {
        int chg = 0;
        int dir = s & 3;
        for (int ii = 0; ii < nr; ++ii) {
            int r = (dir & 1) ? r1 - 1 - ii : r0 + ii;
            for (int jj = 0; jj < nc; ++jj) {
                int c = (dir & 2) ? c1 - 1 - jj : c0 + jj;
                int idx = r * cols + c;
                if (kind[idx] != 0) continue;
                float hc = h[idx];
                float w = W[idx];
                if (w == hc) continue;
                float m = INFINITY;
                for (int k = 0; k < 8; ++k) {
                    int rr = r + DR[k], cc = c + DC[k];
                    int nidx = rr * cols + cc;
                    int inside = rr >= r0 && rr < r1 && cc >= c0 && cc < c1;
                    float v = inside ? W[nidx] : Wpub[nidx];
                    m = fmin(m, v);
                }
                float nw = fmax(hc, eps ? step_up(m) : m);
                if (nw < w) { W[idx] = nw; chg = 1; }
            }
        }
        if (!chg) break;
        any = 1;
    }
    changed[t] = (uchar)any;
}

// Copy the perimeter of each changed tile from W to Wpub (run after fill_tiles).
__kernel void publish_tiles(__global const float* W, __global float* Wpub, __global const uchar* changed,
                            int rows, int cols, int T, int tiles_x, int ntiles)
{
    int t = get_global_id(0);
    if (t >= ntiles || !changed[t]) return;
    int r0 = (t / tiles_x) * T, c0 = (t % tiles_x) * T;
    int r1 = min(r0 + T, rows), c1 = min(c0 + T, cols);
    for (int c = c0; c < c1; ++c) {
        Wpub[r0 * cols + c] = W[r0 * cols + c];
        Wpub[(r1 - 1) * cols + c] = W[(r1 - 1) * cols + c];
    }
    for (int r = r0; r < r1; ++r) {
        Wpub[r * cols + c0] = W[r * cols + c0];
        Wpub[r * cols + c1 - 1] = W[r * cols + c1 - 1];
    }
}

// D8 steepest descent, one work-item per cell: the first neighbour (pysheds
// order) with the largest drop / distance, computed in float32.
__kernel void d8(__global const float* z, __global const uchar* kind, __global char* code,
                 int rows, int cols, float dcard, float ddiag)
{
    int c = get_global_id(0), r = get_global_id(1);
    if (r >= rows || c >= cols) return;
    int idx = r * cols + c;
    uchar kd = kind[idx];
    if (kd != 0) { code[idx] = kd == 1 ? (char)-1 : (char)-2; return; }
    float zc = z[idx];
    float best = 0.0f;
    int bk = -3;
    for (int k = 0; k < 8; ++k) {
        float s = (zc - z[(r + DR[k]) * cols + c + DC[k]]) / ((k & 1) ? ddiag : dcard);
        if (s > best) { best = s; bk = k; }
    }
    code[idx] = (char)bk;
}

inline int receiver(int idx, char k, int cols)
{
    return idx + DR[(int)k] * cols + DC[(int)k];
}

// ---- D8 flow accumulation in three exact phases (Barnes 2016's idea) ----
// Tiles of T x T cells, one work-item each. Sums are integers (cell counts or
// fixed-point weights), so the result does not depend on any order.

// Phase 1: local accumulation inside the tile (in-tile donors only), the
// tile's topological order, and for every cell the exit cell (last cell in
// the tile on its flow path, -1 if the path ends in the tile).
__kernel void acc_local(__global const char* code, __global const ACC_T* w, __global ACC_T* L,
                        __global int* exitof, __global int* ord, __global uchar* deg,
                        int rows, int cols, int T, int tiles_x, int ntiles, int unit)
{
    int t = get_global_id(0);
    if (t >= ntiles) return;
    int r0 = (t / tiles_x) * T, c0 = (t % tiles_x) * T;
    int r1 = min(r0 + T, rows), c1 = min(c0 + T, cols);
    for (int r = r0; r < r1; ++r)
        for (int c = c0; c < c1; ++c) {
            int idx = r * cols + c;
            deg[idx] = 0;
            L[idx] = unit ? (ACC_T)(code[idx] != -2) : w[idx];
        }
    for (int r = r0; r < r1; ++r)
        for (int c = c0; c < c1; ++c) {
            int idx = r * cols + c;
            char k = code[idx];
            if (k < 0) continue;
            int rr = r + DR[(int)k], cc = c + DC[(int)k];
            if (rr >= r0 && rr < r1 && cc >= c0 && cc < c1) deg[rr * cols + cc]++;
        }
    int base = t * T * T, n = 0;
    for (int r = r0; r < r1; ++r)
        for (int c = c0; c < c1; ++c) {
            int idx = r * cols + c;
            if (deg[idx] != 0) continue;
            int cr = r, cc = c, ci = idx;
            for (;;) {
                ord[base + n++] = ci;
                char k = code[ci];
                if (k < 0) break;
                int rr = cr + DR[(int)k], c2 = cc + DC[(int)k];
                if (!(rr >= r0 && rr < r1 && c2 >= c0 && c2 < c1)) break;
                int ri = rr * cols + c2;
                L[ri] += L[ci];
                if (--deg[ri] != 0) break;
                deg[ri] = 255;  /* visited marker: never a start cell again */
                cr = rr; cc = c2; ci = ri;
            }
        }
    for (int i = n - 1; i >= 0; --i) {
        int ci = ord[base + i];
        char k = code[ci];
        if (k < 0) { exitof[ci] = -1; continue; }
        int cr = ci / cols, cc = ci - cr * cols;
        int rr = cr + DR[(int)k], c2 = cc + DC[(int)k];
        exitof[ci] = (rr >= r0 && rr < r1 && c2 >= c0 && c2 < c1) ? exitof[rr * cols + c2] : ci;
    }
}

// Phase 2 (one work-item): accumulate over the graph of exit cells
// (next(x) = exit of the cell x flows into) and write the inflow I(e) that
// each entry cell e receives from other tiles. L holds the local sums; it is
// overwritten at exit cells by their global sums. gdeg is scratch.
inline int perimeter_count(int nr, int nc)
{
    return (nr <= 2 || nc <= 2) ? nr * nc : 2 * nc + 2 * (nr - 2);
}

// The p-th perimeter cell of a tile, each cell once: top row, bottom row,
// then the left and right columns between them (tiles of 1 or 2 rows or
// columns: every cell, in raster order).
inline int perimeter_cell(int p, int r0, int c0, int nr, int nc, int cols)
{
    if (nr <= 2 || nc <= 2) return (r0 + p / nc) * cols + c0 + p % nc;
    if (p < nc) return r0 * cols + c0 + p;
    p -= nc;
    if (p < nc) return (r0 + nr - 1) * cols + c0 + p;
    p -= nc;
    if (p < nr - 2) return (r0 + 1 + p) * cols + c0;
    p -= nr - 2;
    return (r0 + 1 + p) * cols + c0 + nc - 1;
}

__kernel void acc_global(__global const char* code, __global const int* exitof, __global ACC_T* L,
                         __global ACC_T* inflow, __global int* gdeg,
                         int rows, int cols, int T, int tiles_x, int ntiles)
{
    if (get_global_id(0) != 0) return;
    for (int pass = 0; pass < 3; ++pass) {
        for (int t = 0; t < ntiles; ++t) {
            int r0 = (t / tiles_x) * T, c0 = (t % tiles_x) * T;
            int nr = min(r0 + T, rows) - r0, nc = min(c0 + T, cols) - c0;
            int np = perimeter_count(nr, nc);
            for (int p = 0; p < np; ++p) {
                int x = perimeter_cell(p, r0, c0, nr, nc, cols);
                char k = code[x];
                if (k < 0 || exitof[x] != x) continue;
                if (pass == 0) { gdeg[x] = 0; continue; }
                int nx = exitof[receiver(x, k, cols)];
                if (pass == 1) { if (nx >= 0) gdeg[nx]++; continue; }
                if (gdeg[x] != 0) continue;
                int ci = x;
                for (;;) {
                    int ec = receiver(ci, code[ci], cols);
                    inflow[ec] += L[ci];
                    int nn = exitof[ec];
                    if (nn < 0) break;
                    L[nn] += L[ci];
                    if (--gdeg[nn] != 0) break;
                    gdeg[nn] = -1;
                    ci = nn;
                }
            }
        }
    }
}

// Phase 3: final accumulation = local accumulation of w + inflow along the
// order found in phase 1.
__kernel void acc_final(__global const char* code, __global const ACC_T* w, __global const ACC_T* inflow,
                        __global ACC_T* A, __global const int* ord,
                        int rows, int cols, int T, int tiles_x, int ntiles, int unit)
{
    int t = get_global_id(0);
    if (t >= ntiles) return;
    int r0 = (t / tiles_x) * T, c0 = (t % tiles_x) * T;
    int r1 = min(r0 + T, rows), c1 = min(c0 + T, cols);
    for (int r = r0; r < r1; ++r)
        for (int c = c0; c < c1; ++c) {
            int idx = r * cols + c;
            A[idx] = (unit ? (ACC_T)(code[idx] != -2) : w[idx]) + inflow[idx];
        }
    int base = t * T * T, n = (r1 - r0) * (c1 - c0);
    for (int i = 0; i < n; ++i) {
        int ci = ord[base + i];
        char k = code[ci];
        if (k < 0) continue;
        int cr = ci / cols, cc = ci - cr * cols;
        int rr = cr + DR[(int)k], c2 = cc + DC[(int)k];
        if (rr >= r0 && rr < r1 && c2 >= c0 && c2 < c1) A[rr * cols + c2] += A[ci];
    }
}

// Wetness index ln(a / tan b) and moisture, one work-item per cell.
// a = specific catchment area (m^2 per m of contour = accumulation / dx),
// tan b = steepest D8 drop / distance on the terrain, at least tan_min.
// moisture = 1 - (1 - m_twi)(1 - m_water)(1 - m_ext), m_twi the wetness
// index mapped linearly from [twi_dry, twi_wet] to [0, 1].
__kernel void wetness(__global const float* h, __global const uchar* kind, __global const float* acc,
                      __global const float* water, __global const float* ext,
                      __global float* twi, __global float* moist,
                      int rows, int cols, float dx, float dcard, float ddiag, float tan_min,
                      float twi_dry, float twi_wet)
{
    int c = get_global_id(0), r = get_global_id(1);
    if (r >= rows || c >= cols) return;
    int idx = r * cols + c;
    if (kind[idx] == 2) { twi[idx] = NAN; moist[idx] = NAN; return; }
    float hc = h[idx];
    float best = 0.0f;
    for (int k = 0; k < 8; ++k) {
        int rr = r + DR[k], cc = c + DC[k];
        if (rr < 0 || rr >= rows || cc < 0 || cc >= cols) continue;
        float hn = h[rr * cols + cc];
        if (isnan(hn)) continue;
        float s = (hc - hn) / ((k & 1) ? ddiag : dcard);
        if (s > best) best = s;
    }
    float tb = fmax(best, tan_min);
    float t = log((acc[idx] / dx) / tb);
    twi[idx] = t;
    float m = clamp((t - twi_dry) / (twi_wet - twi_dry), 0.0f, 1.0f);
    float mo = 1.0f - (1.0f - m) * (1.0f - water[idx]) * (1.0f - ext[idx]);
    moist[idx] = mo;
}
