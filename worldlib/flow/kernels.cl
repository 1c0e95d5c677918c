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
// cell weights (1 per data cell when unit, else w).
inline void tile_load(__global const char* code, __global const ACC_T* w, int unit, int r0, int c0, int nr,
                      int nc, int cols, int* rl, uchar* deg, ACC_T* acc)
{
    for (int i = 0; i < nr * nc; ++i) deg[i] = 0;
    for (int lr = 0; lr < nr; ++lr)
        for (int lc = 0; lc < nc; ++lc) {
            int idx = (r0 + lr) * cols + c0 + lc;
            char k = code[idx];
            int j = -1;
            if (k >= 0) {
                int rr = lr + DR[(int)k], cc = lc + DC[(int)k];
                j = (rr >= 0 && rr < nr && cc >= 0 && cc < nc) ? rr * nc + cc : LEAVES;
            }
            rl[lr * nc + lc] = j;
            acc[lr * nc + lc] = unit ? (ACC_T)(k != -2) : w[idx];
            if (j >= 0) deg[j]++;
        }
}

// Accumulate acc downstream inside the tile (Kahn's order by walking
// chains from cells without in-tile donors); ord gets the topological order.
inline int tile_accumulate(const int* rl, uchar* deg, ACC_T* acc, ushort* ord, int m)
{
    int n = 0;
    for (int i = 0; i < m; ++i) {
        if (deg[i] != 0) continue;
        int ci = i;
        for (;;) {
            ord[n++] = (ushort)ci;
            int j = rl[ci];
            if (j < 0) break;
            acc[j] += acc[ci];
            if (--deg[j] != 0) break;
            deg[j] = 255;  // visited: never a start cell again
            ci = j;
        }
    }
    return n;
}

// Phase 1: local sums inside each tile; for every perimeter slot, the slot
// of its exit cell (the last cell of its path in the tile, -1 if the path
// ends in the tile) and its local sum.
__kernel void acc_local(__global const char* code, __global const ACC_T* w, __global int* exit_slot,
                        __global ACC_T* local_sum, int rows, int cols, int tiles_x, int ntiles, int unit)
{
    int t = get_global_id(0);
    if (t >= ntiles) return;
    int rl[ACC_CELLS];
    uchar deg[ACC_CELLS];
    ACC_T acc[ACC_CELLS];
    ushort ord[ACC_CELLS];
    int r0, c0, nr, nc;
    tile_geometry(t, rows, cols, tiles_x, &r0, &c0, &nr, &nc);
    tile_load(code, w, unit, r0, c0, nr, nc, cols, rl, deg, acc);
    int n = tile_accumulate(rl, deg, acc, ord, nr * nc);
    // exits, receivers before donors (reverse order), in place of rl
    for (int q = n - 1; q >= 0; --q) {
        int ci = ord[q];
        int j = rl[ci];
        rl[ci] = j >= 0 ? rl[j] : (j == LEAVES ? ci : -1);
    }
    int base = t * PMAX, np = perimeter_count(nr, nc);
    for (int p = 0; p < np; ++p) {
        int li = perimeter_local(p, nr, nc);
        int e = rl[li];
        exit_slot[base + p] = e < 0 ? -1 : base + perimeter_slot(e / nc, e % nc, nr, nc);
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

// Phase 3: final accumulation = local accumulation of (weight + inflow).
__kernel void acc_final(__global const char* code, __global const ACC_T* w, __global const ACC_T* inflow,
                        __global ACC_T* A, int rows, int cols, int tiles_x, int ntiles, int unit)
{
    int t = get_global_id(0);
    if (t >= ntiles) return;
    int rl[ACC_CELLS];
    uchar deg[ACC_CELLS];
    ACC_T acc[ACC_CELLS];
    ushort ord[ACC_CELLS];
    int r0, c0, nr, nc;
    tile_geometry(t, rows, cols, tiles_x, &r0, &c0, &nr, &nc);
    tile_load(code, w, unit, r0, c0, nr, nc, cols, rl, deg, acc);
    int base = t * PMAX, np = perimeter_count(nr, nc);
    for (int p = 0; p < np; ++p) acc[perimeter_local(p, nr, nc)] += inflow[base + p];
    tile_accumulate(rl, deg, acc, ord, nr * nc);
    for (int lr = 0; lr < nr; ++lr)
        for (int lc = 0; lc < nc; ++lc) A[(r0 + lr) * cols + c0 + lc] = acc[lr * nc + lc];
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
// reference.merge_tree_reference step for step: cells in increasing (height,
// index); each joins the components of its already swept 8-neighbours (it is
// an interior cell, so every neighbour is on the map), which merge pairwise
// in node order at its height. Path compression as in the reference, so the
// tree is the same whatever the machine.

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

__kernel void merge_sweep(__global const int* cells, int ncells, __global const float* h, __global const int* term,
                          __global int* uf, __global int* comp_node, __global int* cell_node,
                          __global int* parent, __global int* child_a, __global int* child_b, __global float* birth,
                          __global int* entry_a, __global int* entry_b, __global int* node_count, int n, int cols)
{
    if (get_global_id(0) != 0) return;
    for (int i = 0; i < n; ++i) {
        uf[i] = -1;
        cell_node[i] = -1;
    }
    int nodes = 0;
    for (int q = 0; q < ncells; ++q) {
        int c = cells[q];
        float hc = h[c];
        int roots[8], low[8], nroots = 0;
        for (int k = 0; k < 8; ++k) {
            int nb = c + DR[k] * cols + DC[k];
            if (uf[nb] < 0) continue;
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
                entry_a[p] = cell_node[term[low[0]]];
                entry_b[p] = cell_node[term[low[j]]];
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
