// Flow routing kernels. Grids are row-major, row 0 north. Cell kinds:
//   0 interior data cell, 1 edge cell (map border or 8-adjacent to no-data: a
//   Priority-Flood seed and an outlet), 2 no-data.
// D8 codes follow pysheds' neighbour order N, NE, E, SE, S, SW, W, NW (0..7);
// -1 outlet (edge cell), -2 no-data, -3 pit/flat (no strictly lower neighbour).
// Every result is exact: min/max on floats, integer sums. No atomics.

#include "worldbake_d8.h"

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
// The sweeps run on a private copy of the tile and its one-cell halo (in
// cache on a CPU device): no tile test per neighbour, no cell kinds (a cell
// that may not change, edge or no-data, gets its own W as its height, so the
// w == h test skips it). T = FILL_T, the private arrays' compile-time side.
#ifndef FILL_T
#define FILL_T 64
#endif
#define FILL_P (FILL_T + 2)
__kernel void fill_tiles(__global const float* h, __global const uchar* kind, __global float* W,
                         __global const float* Wpub, __global const uchar* active, __global uchar* changed,
                         int rows, int cols, int T, int tiles_x, int ntiles, int eps, int max_sweeps)
{
    int t = get_global_id(0);
    if (t >= ntiles) return;
    if (!active[t]) { changed[t] = 0; return; }
    float Wp[FILL_P * FILL_P], Hp[FILL_P * FILL_P];
    int r0 = (t / tiles_x) * FILL_T, c0 = (t % tiles_x) * FILL_T;
    int nr = min(FILL_T, rows - r0), nc = min(FILL_T, cols - c0);
    for (int ii = -1; ii <= nr; ++ii)
        for (int jj = -1; jj <= nc; ++jj) {
            int r = r0 + ii, c = c0 + jj, i = (ii + 1) * FILL_P + jj + 1;
            if (r < 0 || r >= rows || c < 0 || c >= cols) { Wp[i] = INFINITY; Hp[i] = INFINITY; continue; }
            int idx = r * cols + c;
            int in_tile = ii >= 0 && ii < nr && jj >= 0 && jj < nc;
            float w = in_tile ? W[idx] : Wpub[idx];
            Wp[i] = w;
            Hp[i] = (in_tile && kind[idx] == 0) ? h[idx] : w;
        }
    int any = 0;
    for (int s = 0; s < max_sweeps; ++s) {
        int chg = 0;
        int dir = s & 3;
        for (int ii = 0; ii < nr; ++ii) {
            int row = ((dir & 1) ? nr - ii : ii + 1) * FILL_P;
            for (int jj = 0; jj < nc; ++jj) {
                int i = row + ((dir & 2) ? nc - jj : jj + 1);
                float hc = Hp[i];
                float w = Wp[i];
                if (w == hc) continue;
                float m = fmin(fmin(fmin(Wp[i - FILL_P], Wp[i - FILL_P + 1]), fmin(Wp[i + 1], Wp[i + FILL_P + 1])),
                               fmin(fmin(Wp[i + FILL_P], Wp[i + FILL_P - 1]), fmin(Wp[i - 1], Wp[i - FILL_P - 1])));
                float nw = fmax(hc, eps ? step_up(m) : m);
                if (nw < w) { Wp[i] = nw; chg = 1; }
            }
        }
        if (!chg) break;
        any = 1;
    }
    if (any)
        for (int ii = 0; ii < nr; ++ii)
            for (int jj = 0; jj < nc; ++jj) W[(r0 + ii) * cols + c0 + jj] = Wp[(ii + 1) * FILL_P + jj + 1];
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
// order) with the largest drop / distance, computed in float32. Written
// without early returns or neighbour loops (indices clamped at the map
// border, where every cell is an edge cell whose code does not look at its
// neighbours) so that the compiler vectorises across work-items.
#define D8_TRY(K, ZN, D) { float s_ = (zc - (ZN)) / (D); int b_ = s_ > best; best = b_ ? s_ : best; bk = b_ ? (K) : bk; }
__kernel void d8(__global const float* z, __global const uchar* kind, __global char* code,
                 int rows, int cols, float dcard, float ddiag)
{
    int c = get_global_id(0), r = get_global_id(1);
    if (r >= rows || c >= cols) return;
    int idx = r * cols + c;
    int up = r > 0 ? -cols : 0, down = r < rows - 1 ? cols : 0;
    int left = c > 0 ? -1 : 0, right = c < cols - 1 ? 1 : 0;
    float zc = z[idx];
    float best = 0.0f;
    int bk = -3;
    D8_TRY(0, z[idx + up], dcard);
    D8_TRY(1, z[idx + up + right], ddiag);
    D8_TRY(2, z[idx + right], dcard);
    D8_TRY(3, z[idx + down + right], ddiag);
    D8_TRY(4, z[idx + down], dcard);
    D8_TRY(5, z[idx + down + left], ddiag);
    D8_TRY(6, z[idx + left], dcard);
    D8_TRY(7, z[idx + up + left], ddiag);
    uchar kd = kind[idx];
    code[idx] = (char)(kd == 0 ? bk : (kd == 1 ? -1 : -2));
}

inline int receiver(int idx, char k, int cols)
{
    return idx + DR[(int)k] * cols + DC[(int)k];
}

// ---- D8 flow accumulation in three exact phases (Barnes 2016's idea) ----
// Tiles of ACC_TILE x ACC_TILE cells, one work-item each, with the tile's
// scratch in private memory (on a CPU device: the work-item's stack, in
// cache), so the only global traffic is the codes, the weights, the result
// and a few numbers per tile perimeter cell ("slots", PMAX per tile). Sums
// are integers (cell counts or fixed-point weights), so the result does not
// depend on any order.

#ifndef ACC_TILE
#define ACC_TILE 64
#endif
#define ACC_CELLS (ACC_TILE * ACC_TILE)
#define PMAX (4 * ACC_TILE)
#define LEAVES (-2)  // in-tile receiver code: the flow leaves the tile

inline int perimeter_count(int nr, int nc)
{
    return (nr <= 2 || nc <= 2) ? nr * nc : 2 * nc + 2 * (nr - 2);
}

// The tile-local index (row * nc + col) of the p-th perimeter cell, each
// cell once: top row, bottom row, then the left and right columns between
// them (tiles of 1 or 2 rows or columns: every cell, in raster order).
inline int perimeter_local(int p, int nr, int nc)
{
    if (nr <= 2 || nc <= 2) return p;
    if (p < nc) return p;
    p -= nc;
    if (p < nc) return (nr - 1) * nc + p;
    p -= nc;
    if (p < nr - 2) return (1 + p) * nc;
    p -= nr - 2;
    return (1 + p) * nc + nc - 1;
}

// The inverse: the perimeter position of tile-local cell (lr, lc), -1 inside.
inline int perimeter_slot(int lr, int lc, int nr, int nc)
{
    if (nr <= 2 || nc <= 2) return lr * nc + lc;
    if (lr == 0) return lc;
    if (lr == nr - 1) return nc + lc;
    if (lc == 0) return 2 * nc + lr - 1;
    if (lc == nc - 1) return 2 * nc + (nr - 2) + lr - 1;
    return -1;
}

inline void tile_geometry(int t, int rows, int cols, int tiles_x, int* r0, int* c0, int* nr, int* nc)
{
    *r0 = (t / tiles_x) * ACC_TILE;
    *c0 = (t % tiles_x) * ACC_TILE;
    *nr = min(ACC_TILE, rows - *r0);
    *nc = min(ACC_TILE, cols - *c0);
}

// A tile's in-tile receivers (local index, -1 where the path ends: outlet,
// no-data or pit, LEAVES where it leaves the tile), in-tile donor counts and
// cell weights (1 per data cell when unit, else w); cell m = nr * nc is a
// dummy receiver (weight 0) for the paths that end or leave.
inline void tile_load(__global const char* code, __global const ACC_T* w, int unit, int r0, int c0, int nr,
                      int nc, int cols, int* rl, uchar* deg, ACC_T* acc)
{
    int m = nr * nc;
    for (int lr = 0; lr < nr; ++lr) {
        __global const char* row = code + (r0 + lr) * cols + c0;
        for (int lc = 0; lc < nc; ++lc) {
            char k = row[lc];
            int kk = k & 7;  // any direction for the table look-up; k < 0 decides below
            int rr = lr + DR[kk], cc = lc + DC[kk];
            int in = (rr >= 0) & (rr < nr) & (cc >= 0) & (cc < nc);
            rl[lr * nc + lc] = k < 0 ? -1 : (in ? rr * nc + cc : LEAVES);
        }
        if (unit)
            for (int lc = 0; lc < nc; ++lc) acc[lr * nc + lc] = (ACC_T)(row[lc] != -2);
        else
            for (int lc = 0; lc < nc; ++lc) acc[lr * nc + lc] = w[(r0 + lr) * cols + c0 + lc];
    }
    acc[m] = 0;
    uchar d2[ACC_CELLS + 1];  // odd cells' counts apart: no store-to-load wait between neighbours
    for (int i = 0; i <= m; ++i) deg[i] = d2[i] = 0;
    int i = 0;
    for (; i + 1 < m; i += 2) {
        int j0 = rl[i], j1 = rl[i + 1];
        deg[j0 >= 0 ? j0 : m]++;
        d2[j1 >= 0 ? j1 : m]++;
    }
    if (i < m) deg[rl[i] >= 0 ? rl[i] : m]++;
    for (int q = 0; q < m; ++q) deg[q] += d2[q];
}

// Accumulate acc downstream inside the tile by Kahn's algorithm, ord its
// queue (the topological order). No branch decides which cell comes next
// (the receiver is queued or not by adding 0 or 1 to the queue's length): on
// a CPU the data-dependent branches of a chain walk mispredicted on about
// every source cell and cost more than the sums. Cell m is a dummy receiver.
inline int tile_accumulate(const int* rl, uchar* deg, ACC_T* acc, ushort* ord, int m)
{
    int n = 0;
    for (int i = 0; i < m; ++i) {  // the sources, without a branch
        ord[n] = (ushort)i;
        n += deg[i] == 0;
    }
    for (int q = 0; q < n; ++q) {  // Kahn's queue: a receiver joins when its last donor is done
        int ci = ord[q];
        int j = rl[ci];
        int jj = j < 0 ? m : j;  // m: a dummy cell
        acc[jj] += acc[ci];
        uchar d = --deg[jj];
        ord[n] = (ushort)jj;
        n += (d == 0) & (j >= 0);
    }
    return n;
}

inline void mark_entry(__global const char* code, int r, int c, int r0, int c0, int nr, int nc, int cols,
                       uchar* deg)
{
    char k = code[r * cols + c];
    if (k < 0) return;
    int rr = r + DR[(int)k] - r0, cc = c + DC[(int)k] - c0;
    if (rr >= 0 && rr < nr && cc >= 0 && cc < nc) deg[rr * nc + cc] = 2;
}

// Mark (deg 2) the tile's cells that receive flow from another tile: the
// receivers, inside the tile, of the ring of cells around it.
inline void mark_entries(__global const char* code, int r0, int c0, int nr, int nc, int rows, int cols,
                         uchar* deg)
{
    for (int c = max(c0 - 1, 0); c <= min(c0 + nc, cols - 1); ++c) {
        if (r0 > 0) mark_entry(code, r0 - 1, c, r0, c0, nr, nc, cols, deg);
        if (r0 + nr < rows) mark_entry(code, r0 + nr, c, r0, c0, nr, nc, cols, deg);
    }
    for (int r = r0; r < r0 + nr; ++r) {
        if (c0 > 0) mark_entry(code, r, c0 - 1, r0, c0, nr, nc, cols, deg);
        if (c0 + nc < cols) mark_entry(code, r, c0 + nc, r0, c0, nr, nc, cols, deg);
    }
}

// Phase 1: local sums inside each tile, written to A; for every perimeter
// slot, the slot of its exit cell (the last cell of its path in the tile, -1
// if the path ends in the tile) and its local sum; inflow zeroed. For
// acc_final, the paths from the entry cells (cells with a donor in another
// tile) cut into segments that share no cell: in slot order, each entry's
// path up to the first cell an earlier segment holds (merge: that cell, -2 if
// the path leaves the tile or ends first, -1 when the slot is no entry).
__kernel void acc_local(__global const char* code, __global const ACC_T* w, __global int* exit_slot,
                        __global ACC_T* local_sum, __global ACC_T* inflow, __global int* merge, __global ACC_T* A,
                        int rows, int cols, int tiles_x, int ntiles, int unit)
{
    int t = get_global_id(0);
    if (t >= ntiles) return;
    int rl[ACC_CELLS];
    uchar deg[ACC_CELLS + 1];
    ACC_T acc[ACC_CELLS + 1];
    ushort ord[ACC_CELLS + 1];
    int r0, c0, nr, nc;
    tile_geometry(t, rows, cols, tiles_x, &r0, &c0, &nr, &nc);
    tile_load(code, w, unit, r0, c0, nr, nc, cols, rl, deg, acc);
    int n = tile_accumulate(rl, deg, acc, ord, nr * nc);  // leaves deg 0 on every cell
    for (int lr = 0; lr < nr; ++lr)
        for (int lc = 0; lc < nc; ++lc) A[(r0 + lr) * cols + c0 + lc] = acc[lr * nc + lc];
    mark_entries(code, r0, c0, nr, nc, rows, cols, deg);
    int base = t * PMAX, np = perimeter_count(nr, nc);
    for (int p = 0; p < np; ++p) {  // segments; deg bit 1: held by a segment
        int ci = perimeter_local(p, nr, nc), mc = -1;
        if (deg[ci] & 2) {
            mc = -2;
            for (;;) {
                if (deg[ci] & 1) {
                    mc = ci;
                    break;
                }
                deg[ci] |= 1;
                ci = rl[ci];
                if (ci < 0) break;
            }
        }
        merge[base + p] = mc;
        inflow[base + p] = 0;
    }
    // exits, receivers before donors (reverse order), in place of rl
    for (int q = n - 1; q >= 0; --q) {
        int ci = ord[q];
        int j = rl[ci];
        int e = rl[j >= 0 ? j : ci];
        rl[ci] = j >= 0 ? e : (j == LEAVES ? ci : -1);
    }
    for (int p = 0; p < np; ++p) ord[perimeter_local(p, nr, nc)] = (ushort)p;  // exits are perimeter cells
    for (int p = 0; p < np; ++p) {
        int li = perimeter_local(p, nr, nc);
        int e = rl[li];
        exit_slot[base + p] = e < 0 ? -1 : base + ord[e];
        local_sum[base + p] = acc[li];
    }
}

// Phase 2 (one work-item): accumulate over the graph of exit slots
// (next(x) = exit slot of the entry cell that x flows into) and write the
// inflow each entry slot receives from other tiles. local_sum is turned
// into global sums at exit slots; entry and gdeg are scratch.
__kernel void acc_global(__global const char* code, __global const int* exit_slot, __global ACC_T* local_sum,
                         __global ACC_T* inflow, __global int* entry, __global int* gdeg,
                         int rows, int cols, int tiles_x, int ntiles)
{
    if (get_global_id(0) != 0) return;
    for (int t = 0; t < ntiles; ++t) {  // entry slot of each exit slot's receiver, in-degrees
        int r0, c0, nr, nc;
        tile_geometry(t, rows, cols, tiles_x, &r0, &c0, &nr, &nc);
        int np = perimeter_count(nr, nc);
        for (int p = 0; p < np; ++p) gdeg[t * PMAX + p] = 0;
    }
    for (int t = 0; t < ntiles; ++t) {
        int r0, c0, nr, nc;
        tile_geometry(t, rows, cols, tiles_x, &r0, &c0, &nr, &nc);
        int np = perimeter_count(nr, nc);
        for (int p = 0; p < np; ++p) {
            int s = t * PMAX + p;
            if (exit_slot[s] != s) continue;
            int li = perimeter_local(p, nr, nc);
            int x = (r0 + li / nc) * cols + c0 + li % nc;
            int y = receiver(x, code[x], cols);
            int yr = y / cols, yc = y - yr * cols;
            int ty = (yr / ACC_TILE) * tiles_x + yc / ACC_TILE;
            int yr0, yc0, ynr, ync;
            tile_geometry(ty, rows, cols, tiles_x, &yr0, &yc0, &ynr, &ync);
            int sy = ty * PMAX + perimeter_slot(yr - yr0, yc - yc0, ynr, ync);
            entry[s] = sy;
            int nx = exit_slot[sy];
            if (nx >= 0) gdeg[nx]++;
        }
    }
    for (int t = 0; t < ntiles; ++t) {
        int r0, c0, nr, nc;
        tile_geometry(t, rows, cols, tiles_x, &r0, &c0, &nr, &nc);
        int np = perimeter_count(nr, nc);
        for (int p = 0; p < np; ++p) {
            int s = t * PMAX + p;
            if (exit_slot[s] != s || gdeg[s] != 0) continue;
            int ci = s;
            for (;;) {
                int sy = entry[ci];
                inflow[sy] += local_sum[ci];
                int nn = exit_slot[sy];
                if (nn < 0) break;
                local_sum[nn] += local_sum[ci];
                if (--gdeg[nn] != 0) break;
                gdeg[nn] = -1;
                ci = nn;
            }
        }
    }
}

// Phase 3: A (the local sums) plus, on every cell, the inflow of the entry
// slots upstream of it in the tile. The segments (acc_local) are walked in
// reverse slot order, so every segment that merges into a segment is done
// before it: a segment's running value is its entry's inflow plus what the
// later segments carried into its cells. Each cell below an entry is
// touched once. Integer adds: exact in any order.
__kernel void acc_final(__global const char* code, __global const ACC_T* inflow, __global const int* merge,
                        __global ACC_T* A, int rows, int cols, int tiles_x, int ntiles)
{
    int t = get_global_id(0);
    if (t >= ntiles) return;
    ACC_T add[ACC_CELLS];
    uchar row_hit[ACC_TILE];
    int r0, c0, nr, nc;
    tile_geometry(t, rows, cols, tiles_x, &r0, &c0, &nr, &nc);
    int base = t * PMAX, np = perimeter_count(nr, nc);
    for (int i = 0; i < nr * nc; ++i) add[i] = 0;
    for (int i = 0; i < nr; ++i) row_hit[i] = 0;
    int goff[8], loff[8];  // the neighbour offsets in the grid and in the tile
    for (int k = 0; k < 8; ++k) {
        goff[k] = DR[k] * cols + DC[k];
        loff[k] = DR[k] * nc + DC[k];
    }
    for (int p = np - 1; p >= 0; --p) {
        int mc = merge[base + p];
        if (mc == -1) continue;
        ACC_T v = inflow[base + p];
        int ci = perimeter_local(p, nr, nc);
        int lr = ci / nc, lc = ci - lr * nc;
        __global const char* cp = code + (r0 + lr) * cols + c0 + lc;
        for (;;) {
            if (ci == mc) {
                add[ci] += v;
                break;
            }
            v += add[ci];
            add[ci] = v;
            row_hit[lr] = 1;
            char k = *cp;
            if (k < 0) break;
            int dr = DR[(int)k], dc = DC[(int)k];
            lr += dr;
            lc += dc;
            if (lr < 0 || lr >= nr || lc < 0 || lc >= nc) break;
            cp += goff[(int)k];
            ci += loff[(int)k];
        }
    }
    for (int lr = 0; lr < nr; ++lr) {
        if (!row_hit[lr]) continue;
        __global ACC_T* a = A + (r0 + lr) * cols + c0;
        for (int lc = 0; lc < nc; ++lc) a[lc] += add[lr * nc + lc];
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

// ---- Complete breaching (Lindsay 2016), serial: one work-item ----
// The same algorithm as reference.breach, step for step: Priority-Flood from
// the edge cells in order of (height, cell index) with a binary heap; when a
// pit is popped, the cells on the path that flooded it are lowered, back
// toward the edge, to one float32 step below the previous one until a cell is
// already low enough. The (height, index) order is total, so the pops and the
// result are those of the Python reference exactly.

inline int heap_less(float ka, int ia, float kb, int ib)
{
    return ka < kb || (ka == kb && ia < ib);
}

inline void heap_push(__global float* hk, __global int* hi, int* size, float k, int i)
{
    int pos = (*size)++;
    while (pos > 0) {
        int parent = (pos - 1) >> 1;
        if (!heap_less(k, i, hk[parent], hi[parent])) break;
        hk[pos] = hk[parent];
        hi[pos] = hi[parent];
        pos = parent;
    }
    hk[pos] = k;
    hi[pos] = i;
}

inline int heap_pop(__global float* hk, __global int* hi, int* size)
{
    int top = hi[0];
    int n = --(*size);
    float k = hk[n];
    int i = hi[n];
    int pos = 0;
    for (;;) {
        int child = 2 * pos + 1;
        if (child >= n) break;
        if (child + 1 < n && heap_less(hk[child + 1], hi[child + 1], hk[child], hi[child])) child++;
        if (!heap_less(hk[child], hi[child], k, i)) break;
        hk[pos] = hk[child];
        hi[pos] = hi[child];
        pos = child;
    }
    if (n > 0) {
        hk[pos] = k;
        hi[pos] = i;
    }
    return top;
}

__kernel void breach_serial(__global float* z, __global const uchar* kind, __global const uchar* pit,
                            __global int* back, __global uchar* done, __global float* hk, __global int* hi,
                            int rows, int cols)
{
    if (get_global_id(0) != 0) return;
    int n = rows * cols, size = 0;
    for (int i = 0; i < n; ++i) {
        back[i] = -1;
        done[i] = kind[i] != 0;
    }
    for (int i = 0; i < n; ++i)
        if (kind[i] == 1) heap_push(hk, hi, &size, z[i], i);
    while (size > 0) {
        int c = heap_pop(hk, hi, &size);
        if (pit[c]) {
            int cc = back[c];
            float target = z[c];
            while (cc >= 0 && z[cc] > target) {
                z[cc] = target;
                cc = back[cc];
                target = nextafter(target, -INFINITY);
            }
        }
        int r = c / cols, col = c - r * cols;
        for (int k = 0; k < 8; ++k) {
            int rr = r + DR[k], c2 = col + DC[k];
            if (rr < 0 || rr >= rows || c2 < 0 || c2 >= cols) continue;
            int j = rr * cols + c2;
            if (done[j]) continue;
            done[j] = 1;
            back[j] = c;
            heap_push(hk, hi, &size, z[j], j);
        }
    }
}

// ---- The depressions' merge tree: union-find sweep, serial (one work-item) ----
// reference.merge_tree_reference step for step on the depression cells
// alone (sparse indices: position in the ascending list of the cells' flat
// indices, so comparing them compares flat indices; every buffer has one
// slot per depression cell, none per map cell): cells in increasing (height,
// index); each joins the components of its already swept 8-neighbours (nbr,
// -1 outside the depressions), which merge pairwise in node order at its
// height. Path compression as in the reference, so the tree is the same
// whatever the machine.

inline int uf_find(__global int* uf, int x)
{
    int root = x;
    while (uf[root] != root) root = uf[root];
    while (uf[x] != root) {
        int next = uf[x];
        uf[x] = root;
        x = next;
    }
    return root;
}

__kernel void merge_sweep(__global const int* order, int ncells, __global const float* h, __global const int* term,
                          __global const int* nbr, __global int* uf, __global int* comp_node, __global int* cell_node,
                          __global int* parent, __global int* child_a, __global int* child_b, __global float* birth,
                          __global int* entry_a, __global int* entry_b, __global int* node_count)
{
    if (get_global_id(0) != 0) return;
    for (int i = 0; i < ncells; ++i) {
        uf[i] = -1;
        cell_node[i] = -1;
    }
    int nodes = 0;
    for (int q = 0; q < ncells; ++q) {
        int c = order[q];
        float hc = h[c];
        int roots[8], low[8], nroots = 0;
        for (int k = 0; k < 8; ++k) {
            int nb = nbr[8 * (long)c + k];
            if (nb < 0 || uf[nb] < 0) continue;
            int root = uf_find(uf, nb);
            int j = 0;
            while (j < nroots && roots[j] != root) ++j;
            if (j == nroots) {
                roots[nroots] = root;
                low[nroots++] = nb;
            } else if (h[nb] < h[low[j]] || (h[nb] == h[low[j]] && nb < low[j])) {
                low[j] = nb;
            }
        }
        uf[c] = c;
        int node;
        if (nroots == 0) {
            node = nodes++;
            parent[node] = -1; child_a[node] = -1; child_b[node] = -1;
            birth[node] = hc; entry_a[node] = -1; entry_b[node] = -1;
        } else {
            for (int a = 1; a < nroots; ++a) {  // insertion sort by node id (stable)
                int rr = roots[a], ll = low[a], key = comp_node[rr], b = a - 1;
                while (b >= 0 && comp_node[roots[b]] > key) {
                    roots[b + 1] = roots[b];
                    low[b + 1] = low[b];
                    --b;
                }
                roots[b + 1] = rr;
                low[b + 1] = ll;
            }
            node = comp_node[roots[0]];
            for (int j = 1; j < nroots; ++j) {
                int other = comp_node[roots[j]];
                int p = nodes++;
                parent[p] = -1; child_a[p] = node; child_b[p] = other; birth[p] = hc;
                int ta = term[low[0]], tb = term[low[j]];  // -1: the path leaves the depressions
                entry_a[p] = ta < 0 ? -1 : cell_node[ta];
                entry_b[p] = tb < 0 ? -1 : cell_node[tb];
                parent[node] = p;
                parent[other] = p;
                node = p;
            }
            for (int j = 0; j < nroots; ++j) uf[roots[j]] = c;
        }
        comp_node[c] = node;
        cell_node[c] = node;
    }
    node_count[0] = nodes;
}

// ---- Plain fill (no epsilon) in three exact phases (Barnes 2016's idea,
// with relaxation inside the tiles instead of a priority queue) ----
// 1. fill_local, one work-item per tile: the fill of the tile alone, its
//    perimeter cells and the map's edge cells as seeds at their own heights
//    (Wloc), each cell labelled by a seed that reaches it at cost Wloc (its
//    label is copied from the neighbour that last lowered it); then every
//    pair of 8-adjacent cells of different labels is an edge of weight
//    max(Wloc, Wloc), kept once per label pair (the lowest) in a small hash,
//    and written per perimeter slot (CSR). Map edge seeds are one node, the
//    ocean, whose edges become the slots' initial levels.
// 2. fill_levels, one work-item: a priority flood over the graph of
//    perimeter slots (tile edges, and 8-adjacent perimeter cells of
//    neighbouring tiles at max(h, h)): level = lowest spill to the ocean.
// 3. fill_combine, one work-item per cell: F = max(Wloc, level(label)) (the
//    host writes numpy's NaN on no-data: a device's NAN may have other bits).
// F equals the Priority-Flood result: a path from a cell to the map edge
// maps to a chain of labels whose edges weigh at most its cost (Wloc <= F,
// F non-increasing along an optimal path), and a label's seed reaches the
// cell at cost Wloc, so every bound is met by a real path.
#define FILL_PMAX (4 * FILL_T)
#ifndef FILL_HCAP
#define FILL_HCAP 4096  // the label-pair hash: a power of two, set by the host
#endif
#define OCEAN 0xFFFF    // the label of the map's edge cells
#define OUTSIDE 0xFFFE  // no-data cells and the halo: no label, no pairs

// min and max of floats that are never NaN here (no-data cells are -inf in
// the private copies and never read otherwise), written out: PoCL 3.0 calls
// its fmin/fmax out of line. Arguments are evaluated twice: pass plain values.
#define FLO(a, b) ((b) < (a) ? (b) : (a))
#define FHI(a, b) ((b) > (a) ? (b) : (a))

// Insert (a, b) (a < b, slots) with weight w keeping the lowest; returns 0 when the table is full.
inline int hash_put(int* hk, float* hw, ushort* used, int* count, int a, int b, float w)
{
    int key = a * FILL_PMAX + b;
    uint pos = ((uint)key * 2654435761u) & (FILL_HCAP - 1);
    for (;;) {
        if (hk[pos] == key) { hw[pos] = FLO(hw[pos], w); return 1; }
        if (hk[pos] < 0) {
            if (4 * (*count + 1) > 3 * FILL_HCAP) return 0;
            hk[pos] = key; hw[pos] = w; used[(*count)++] = (ushort)pos;
            return 1;
        }
        pos = (pos + 1) & (FILL_HCAP - 1);
    }
}

// The lower of a cell's neighbours above and below (column j of a row
// visit) and its label.
#define FILL_COLUMN(J, M, L) { \
    float a_ = Wp[up + (J)], b_ = Wp[dn + (J)]; \
    int k_ = b_ < a_; \
    M = k_ ? b_ : a_; \
    L = k_ ? Lp[dn + (J)] : Lp[up + (J)]; }

// The tile's local fill and labels in the private copy: Gauss-Seidel in
// raster and anti-raster order by turns until a sweep changes nothing. Each
// row keeps the span of columns whose neighbourhood changed since they were
// last evaluated (lo..hi, empty when lo > hi); a visit evaluates its span
// and goes on past it while the cell behind changed. A cell takes the
// lowest of its 8 neighbours (the one behind already updated) and the label
// of that neighbour: any lowest one is a seed reaching it at cost W.
inline void local_fill(float* Wp, const float* Hp, ushort* Lp, int nr, int nc)
{
    uchar lo[FILL_T + 2], hi[FILL_T + 2];
    for (int r = 0; r < nr + 2; ++r) { lo[r] = 1; hi[r] = r >= 1 && r <= nr ? nc : 0; }
    for (int s = 0;; ++s) {
        int chg = 0, back = s & 1;  // raster and anti-raster order
        int step = back ? -1 : 1;
        for (int ii = 0; ii < nr; ++ii) {
            int pr = back ? nr - ii : ii + 1;
            int a = lo[pr], b = hi[pr];
            if (a > b) continue;
            lo[pr] = FILL_P; hi[pr] = 0;
            int row = pr * FILL_P, up = row - FILL_P, dn = row + FILL_P;
            int j = back ? b : a, last = back ? a : b;
            float pw = Wp[row + j - step], m0, m1, m2;
            ushort pl = Lp[row + j - step], l0, l1, l2;
            FILL_COLUMN(j - step, m0, l0)
            FILL_COLUMN(j, m1, l1)
            int clo = FILL_P, chi = 0, upd = 0;
            for (; j >= 1 && j <= nc && (upd || (back ? j >= last : j <= last)); j += step) {
                int i = row + j;
                FILL_COLUMN(j + step, m2, l2)
                float m = m0, nx = Wp[i + step];
                ushort l = l0;
                int k = m1 < m; m = k ? m1 : m; l = k ? l1 : l;
                k = m2 < m; m = k ? m2 : m; l = k ? l2 : l;
                k = nx < m; m = k ? nx : m; l = k ? Lp[i + step] : l;
                k = pw < m; m = k ? pw : m; l = k ? pl : l;
                float w = Wp[i], nw = FHI(Hp[i], m);
                upd = nw < w;
                pw = upd ? nw : w;
                pl = upd ? l : Lp[i];
                Wp[i] = pw;
                Lp[i] = pl;
                clo = upd && j < clo ? j : clo;
                chi = upd && j > chi ? j : chi;
                m0 = m1; l0 = l1; m1 = m2; l1 = l2;
            }
            if (chi) {
                int nlo = clo > 1 ? clo - 1 : 1, nhi = chi < nc ? chi + 1 : nc;
                for (int r = pr - 1; r <= pr + 1; ++r) {
                    lo[r] = nlo < lo[r] ? nlo : lo[r];
                    hi[r] = nhi > hi[r] ? nhi : hi[r];
                }
                chg = 1;
            }
        }
        if (!chg) break;
    }
}

// The label pair of cell i (label a, height wi) and cell j, as an initial
// level (a pair with the ocean) or a hash entry.
#define FILL_PAIR(j) { \
    ushort b_ = Lp[j]; \
    if (b_ != a && b_ != OUTSIDE) { \
        float wj_ = Wp[j], w_ = FHI(wi, wj_); \
        if (a == OCEAN || b_ == OCEAN) { \
            int s_ = base + (a == OCEAN ? b_ : a); \
            float i_ = init[s_]; \
            init[s_] = FLO(i_, w_); \
        } else { \
            int lo_ = a < b_ ? a : b_, hi_ = a < b_ ? b_ : a, key_ = lo_ * FILL_PMAX + hi_; \
            if (!full && !(key_ == last && w_ >= last_w)) { \
                full = !hash_put(hk, hw, used, &count, lo_, hi_, w_); \
                last = key_; \
                last_w = w_; \
            } \
        } \
    } }

// The perimeter slots' edges to other tiles: every 8-neighbour q of the
// slot's cell outside the tile, on the map; the map's edge cells there are
// the ocean (an initial level max(h, h)), interior cells are perimeter slots
// of their tile (an edge of weight max(h, h)), no-data cells nothing. Written
// here, in tile order, so that fill_levels reads only arrays indexed by node.
// A tile has at most 6 (nr + nc) - 4 < 3 * FILL_PMAX of them (CSR xoff, xn, xw).
inline void fill_cross(__global const float* h, __global const uchar* kind, const float* Hp, __global float* init,
                       __global int* xoff, __global int* xn, __global float* xw, int t, int r0, int c0, int nr,
                       int nc, int rows, int cols, int tiles_x)
{
    int base = t * FILL_PMAX, ob = t * (FILL_PMAX + 1), xb = t * 3 * FILL_PMAX, e = 0;
    int np = (nr <= 2 || nc <= 2) ? nr * nc : 2 * nc + 2 * (nr - 2);
    for (int p = 0; p < FILL_PMAX; ++p) {
        xoff[ob + p] = e;
        if (p >= np) continue;
        int loc = perimeter_local(p, nr, nc), lr = loc / nc, lc = loc - lr * nc;
        int r = r0 + lr, c = c0 + lc;
        if (kind[r * cols + c] != 0) continue;
        float hx = Hp[(lr + 1) * FILL_P + lc + 1], v = init[base + p];
        for (int k = 0; k < 8; ++k) {
            int rr = r + DR[k], cc = c + DC[k];
            if (rr < 0 || rr >= rows || cc < 0 || cc >= cols) continue;
            if (rr >= r0 && rr < r0 + nr && cc >= c0 && cc < c0 + nc) continue;
            int q = rr * cols + cc;
            uchar kq = kind[q];
            if (kq == 2) continue;
            float hq = h[q], w = FHI(hx, hq);
            if (kq == 1) { v = FLO(v, w); continue; }
            int tr = rr / FILL_T, tc = cc / FILL_T, qr0 = tr * FILL_T, qc0 = tc * FILL_T;
            int qnr = min(FILL_T, rows - qr0), qnc = min(FILL_T, cols - qc0);
            xn[xb + e] = (tr * tiles_x + tc) * FILL_PMAX + perimeter_slot(rr - qr0, cc - qc0, qnr, qnc);
            xw[xb + e] = w;
            ++e;
        }
        init[base + p] = v;
    }
    xoff[ob + FILL_PMAX] = e;
}

__kernel void fill_local(__global const float* h, __global const uchar* kind, __global float* Wloc,
                         __global int* label, __global int* off, __global ushort* adj_n, __global float* adj_w,
                         __global float* init, __global int* xoff, __global int* xn, __global float* xw,
                         __global uchar* overflow, int rows, int cols, int tiles_x, int ntiles)
{
    int t = get_global_id(0);
    if (t >= ntiles) return;
    float Wp[FILL_P * FILL_P], Hp[FILL_P * FILL_P];
    ushort Lp[FILL_P * FILL_P];
    int hk[FILL_HCAP];
    float hw[FILL_HCAP];
    ushort used[3 * FILL_HCAP / 4 + 1];  // the hash's filled slots, in insertion order
    int r0 = (t / tiles_x) * FILL_T, c0 = (t % tiles_x) * FILL_T;
    int nr = min(FILL_T, rows - r0), nc = min(FILL_T, cols - c0);
    int base = t * FILL_PMAX;
    for (int jj = 0; jj < nc + 2; ++jj)  // the halo (the cells are all set below)
        for (int i = jj; i <= jj + (nr + 1) * FILL_P; i += (nr + 1) * FILL_P) { Wp[i] = Hp[i] = INFINITY; Lp[i] = OUTSIDE; }
    for (int ii = 1; ii <= nr; ++ii)
        for (int i = ii * FILL_P; i <= ii * FILL_P + nc + 1; i += nc + 1) { Wp[i] = Hp[i] = INFINITY; Lp[i] = OUTSIDE; }
    for (int ii = 0; ii < nr; ++ii)
        for (int jj = 0; jj < nc; ++jj) {
            int idx = (r0 + ii) * cols + c0 + jj, i = (ii + 1) * FILL_P + jj + 1;
            uchar k = kind[idx];
            float hc = h[idx];
            int slot = perimeter_slot(ii, jj, nr, nc);
            if (k == 2) { Wp[i] = Hp[i] = -INFINITY; Lp[i] = OUTSIDE; continue; }  // never a neighbour of a non-seed
            Hp[i] = hc;
            int seed = k == 1 || slot >= 0;
            Wp[i] = seed ? hc : INFINITY;
            // not reached yet; a non-seed gets a seed's label when first lowered
            Lp[i] = k == 1 || slot < 0 ? OCEAN : (ushort)slot;
        }
    local_fill(Wp, Hp, Lp, nr, nc);
    for (int p = 0; p < FILL_PMAX; ++p) init[base + p] = INFINITY;
    fill_cross(h, kind, Hp, init, xoff, xn, xw, t, r0, c0, nr, nc, rows, cols, tiles_x);
    for (int i = 0; i < FILL_HCAP; ++i) hk[i] = -1;
    int count = 0, full = 0;
    int last = -1;  // cells along a label boundary repeat the pair: skip the hash
    float last_w = INFINITY;
    for (int ii = 0; ii < nr; ++ii) {
        for (int jj = 0; jj < nc; ++jj) {  // branch-free: vectorised
            int i = (ii + 1) * FILL_P + jj + 1, idx = (r0 + ii) * cols + c0 + jj;
            ushort a = Lp[i];
            Wloc[idx] = Wp[i];
            label[idx] = a >= OUTSIDE ? -1 : base + a;
        }
        for (int jj = 0; jj < nc; ++jj) {
            int i = (ii + 1) * FILL_P + jj + 1;
            ushort a = Lp[i];
            float wi = Wp[i];
            if (a == OUTSIDE) continue;
            if (((Lp[i + 1] ^ a) | (Lp[i + FILL_P - 1] ^ a) | (Lp[i + FILL_P] ^ a) | (Lp[i + FILL_P + 1] ^ a)) == 0) continue;
            // the neighbours E, SW, S, SE: each adjacent pair once
            FILL_PAIR(i + 1) FILL_PAIR(i + FILL_P - 1) FILL_PAIR(i + FILL_P) FILL_PAIR(i + FILL_P + 1)
        }
    }
    overflow[t] = (uchar)full;
    // CSR per slot, both directions; Lp reused as the cursor
    int ob = t * (FILL_PMAX + 1);
    for (int p = 0; p <= FILL_PMAX; ++p) off[ob + p] = 0;
    for (int u = 0; u < count; ++u) {
        int key = hk[used[u]];
        off[ob + key / FILL_PMAX + 1]++;
        off[ob + key % FILL_PMAX + 1]++;
    }
    for (int p = 0; p < FILL_PMAX; ++p) { off[ob + p + 1] += off[ob + p]; Lp[p] = 0; }
    int ab = t * 2 * FILL_HCAP;
    for (int u = 0; u < count; ++u) {
        int q = used[u], a = hk[q] / FILL_PMAX, b = hk[q] % FILL_PMAX;
        int ea = ab + off[ob + a] + Lp[a]++, eb = ab + off[ob + b] + Lp[b]++;
        adj_n[ea] = (ushort)b; adj_w[ea] = hw[q];
        adj_n[eb] = (ushort)a; adj_w[eb] = hw[q];
    }
}

// fill_levels' heap: 4-ary (half the depth of a binary one), ordered on the
// key alone: the levels are the unique minimax values whatever order equal
// keys leave in.
inline void fheap_push(__global float* hk, __global int* hi, int* size, float k, int i)
{
    int pos = (*size)++;
    while (pos > 0) {
        int parent = (pos - 1) >> 2;
        float kp = hk[parent];
        if (!(k < kp)) break;
        hk[pos] = kp;
        hi[pos] = hi[parent];
        pos = parent;
    }
    hk[pos] = k;
    hi[pos] = i;
}

inline int fheap_pop(__global float* hk, __global int* hi, int* size)
{
    int top = hi[0];
    int n = --(*size);
    float k = hk[n];
    int i = hi[n];
    int pos = 0;
    for (;;) {
        int first = 4 * pos + 1;
        if (first >= n) break;
        int child = first;
        float kc = hk[first];
        int end = first + 4 < n ? first + 4 : n;
        for (int c = first + 1; c < end; ++c) {
            float kk = hk[c];
            int lower = kk < kc;
            child = lower ? c : child;
            kc = lower ? kk : kc;
        }
        if (!(kc < k)) break;
        hk[pos] = kc;
        hi[pos] = hi[child];
        pos = child;
    }
    hk[pos] = k;
    hi[pos] = i;
    return top;
}

// The flood over the perimeter slots from their initial levels (edges to the
// ocean), through the tile edges (off, adj_n, adj_w) and the edges to other
// tiles (xoff, xn, xw). Slots that are no node keep an infinite level.
__kernel void fill_levels(__global const int* off, __global const ushort* adj_n, __global const float* adj_w,
                          __global const int* xoff, __global const int* xn, __global const float* xw,
                          __global const float* init, __global float* level, __global float* hk, __global int* hi,
                          int ntiles)
{
    if (get_global_id(0) != 0) return;
    int size = 0;
    for (int u = 0; u < ntiles * FILL_PMAX; ++u) {
        float v = init[u];
        level[u] = v;
        if (v < INFINITY) fheap_push(hk, hi, &size, v, u);
    }
    while (size > 0) {
        float key = hk[0];
        int u = fheap_pop(hk, hi, &size);
        if (key > level[u]) continue;  // stale entry
        int t = u / FILL_PMAX, p = u - t * FILL_PMAX;
        int ob = t * (FILL_PMAX + 1), ab = t * 2 * FILL_HCAP, xb = t * 3 * FILL_PMAX;
        for (int e = off[ob + p]; e < off[ob + p + 1]; ++e) {
            int v = t * FILL_PMAX + adj_n[ab + e];
            float we = adj_w[ab + e], cand = FHI(key, we);
            if (cand < level[v]) { level[v] = cand; fheap_push(hk, hi, &size, cand, v); }
        }
        for (int e = xoff[ob + p]; e < xoff[ob + p + 1]; ++e) {
            int v = xn[xb + e];
            float we = xw[xb + e], cand = FHI(key, we);
            if (cand < level[v]) { level[v] = cand; fheap_push(hk, hi, &size, cand, v); }
        }
    }
}

// In place on fill_local's Wloc (edge cells: h, no-data: -inf, both with
// no label): the level of the cell's label where that is higher.
__kernel void fill_combine(__global float* F, __global const int* label, __global const float* level, int n)
{
    int i = get_global_id(0);
    if (i >= n) return;
    int lab = label[i];
    if (lab >= 0) {
        float w = F[i], l = level[lab];
        if (l > w) F[i] = l;
    }
}
