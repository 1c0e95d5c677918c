// Stream-power fluvial erosion, implicit O(n) scheme of Braun and Willett
// (2013), in double precision. One work-item: the solve visits cells in
// "stack" order (every receiver before its donors), which is inherently
// serial; compiled it is O(n) at C speed.
//
// dh/dt = U - K A^m S^n, solved implicitly along each D8 flow path:
//   h_i' = h_r' + delta, delta + F delta^n = h_i - h_r',  F = K dt A^m / d^n
// (F per cell from the host: stream_power.factors), where h_i is the height
// after uplift and h_r' the receiver's new height (already computed:
// receivers come first). delta by Newton (fastscapelib's
// formulation on the height difference); n = 1 has the closed form
// delta = (h_i - h_r') / (1 + F). A cell not above its receiver's new
// height (inside a depression) is not eroded (fastscapelib's rule).
//
// Codes: D8 codes 0..7 (N, NE, E, SE, S, SW, W, NW: worldbake_d8.h);
// any negative code is base level (map edge, no-data, pit): height fixed.

#pragma OPENCL EXTENSION cl_khr_fp64 : enable

#include "worldbake_d8.h"

#define NEWTON_TOL 1e-10
#define NEWTON_MAX 100

// factor[i] = K dt A_i^m / d_i^n, computed on the host (stream_power.factors)
__kernel void stream_power_step(__global double* h, __global const char* code, __global const double* factor,
                                __global int* ndon, __global int* first, __global int* donors,
                                __global int* order, __global int* iterations, int rows, int cols, double n_exp)
{
    if (get_global_id(0) != 0) return;
    int n = rows * cols;
    // donors of each cell, in index order (counting sort on receivers)
    for (int i = 0; i < n; ++i) ndon[i] = 0;
    for (int i = 0; i < n; ++i) {
        char k = code[i];
        if (k >= 0) ndon[i + DR[(int)k] * cols + DC[(int)k]]++;
    }
    int acc = 0;
    for (int i = 0; i < n; ++i) {
        first[i] = acc;
        acc += ndon[i];
        ndon[i] = 0;
    }
    for (int i = 0; i < n; ++i) {
        char k = code[i];
        if (k < 0) continue;
        int r = i + DR[(int)k] * cols + DC[(int)k];
        donors[first[r] + ndon[r]++] = i;
    }
    // stack order: base-level cells in index order, then breadth first up the tree
    int tail = 0;
    for (int i = 0; i < n; ++i)
        if (code[i] < 0) order[tail++] = i;
    for (int head = 0; head < tail; ++head) {
        int c = order[head];
        for (int q = first[c]; q < first[c] + ndon[c]; ++q) order[tail++] = donors[q];
    }
    // the implicit solve, receivers first
    int worst = 0;
    for (int q = 0; q < tail; ++q) {
        int i = order[q];
        char k = code[i];
        if (k < 0) continue;
        int r = i + DR[(int)k] * cols + DC[(int)k];
        double hr = h[r];
        double d0 = h[i] - hr;
        if (d0 <= 0.0) continue;  // in a depression: not eroded
        double f = factor[i];
        double delta;
        if (n_exp == 1.0) {
            delta = d0 / (1.0 + f);
        } else {
            delta = d0;
            int it = 0;
            for (; it < NEWTON_MAX; ++it) {
                double p = pow(delta, n_exp - 1.0);
                double g = delta + f * p * delta - d0;
                double dg = 1.0 + f * n_exp * p;
                double next = delta - g / dg;
                if (next <= 0.0) next = 0.5 * delta;  // stay positive (the root lies in (0, d0])
                double change = fabs(next - delta);
                delta = next;
                if (change <= NEWTON_TOL * d0) break;
            }
            worst = max(worst, it + 1);
        }
        h[i] = hr + delta;
    }
    iterations[0] = worst;
    iterations[1] = tail;
}

// The same implicit solve (n = 1) over multiple flow directions (Quinn et al.
// 1991 / Freeman 1991), as fastscapelib's multiple-receiver eroder: each
// cell sends its drainage area to every neighbour lower on the routing
// surface z in proportion to slope^p times contour length (0.5 dx across an
// axis, 0.354 dx across a diagonal), and erodes toward each of them:
//   h_i' (1 + sum F_j) = h_i + sum F_j h_j',  F_j = K dt A_i^m frac_j / d_j
// over the receivers j still below h_i. The host computes the flow
// fractions frac[8 i + k] (0 where neighbour k is not lower) and
// factor = K dt A^m (0 on hillslopes and base level) with numpy: PoCL's
// double pow would cost those launches more than the serial passes. Two
// serial passes here: the area (`order` = cells by ascending z, walked
// backwards: donors before receivers) and the solve (forwards: receivers
// before donors).

__kernel void mfd_area(__global const int* order, __global const uchar* interior, __global const double* frac,
                       __global double* area, int rows, int cols, double dx)
{
    if (get_global_id(0) != 0) return;
    int n = rows * cols;
    for (int i = 0; i < n; ++i) area[i] = dx * dx;
    for (int q = n - 1; q >= 0; --q) {
        int i = order[q];
        if (!interior[i]) continue;
        double a = area[i];
        for (int k = 0; k < 8; ++k) {
            double f = frac[8 * i + k];
            if (f > 0.0) area[i + DR[k] * cols + DC[k]] += a * f;
        }
    }
}

__kernel void mfd_solve(__global double* h, __global const int* order, __global const double* frac,
                        __global const double* factor, int rows, int cols, double dx)
{
    if (get_global_id(0) != 0) return;
    int n = rows * cols;
    for (int q = 0; q < n; ++q) {
        int i = order[q];
        double fac = factor[i];
        if (fac == 0.0) continue;
        double hi = h[i], sum_f = 0.0, sum_fh = 0.0;
        for (int k = 0; k < 8; ++k) {
            double f = frac[8 * i + k];
            if (f == 0.0) continue;
            double hj = h[i + DR[k] * cols + DC[k]];
            if (hj >= hi) continue;  // not below: no erosion toward it
            double fj = fac * f / ((k & 1) ? dx * M_SQRT2 : dx);
            sum_f += fj;
            sum_fh += fj * hj;
        }
        h[i] = (hi + sum_fh) / (1.0 + sum_f);
    }
}

// The sediment flux: acc_i = src_i + sum over donors j of frac_ji acc_j, the
// same backward pass as mfd_area with each cell's own volume src (m^3: what
// the step eroded there less what it deposited, plus landslide material).
// Base-level cells keep what arrives (it leaves the map).
__kernel void mfd_accumulate(__global const int* order, __global const uchar* interior, __global const double* frac,
                             __global const double* src, __global double* acc, int rows, int cols)
{
    if (get_global_id(0) != 0) return;
    int n = rows * cols;
    for (int i = 0; i < n; ++i) acc[i] = src[i];
    for (int q = n - 1; q >= 0; --q) {
        int i = order[q];
        if (!interior[i]) continue;
        double a = acc[i];
        for (int k = 0; k < 8; ++k) {
            double f = frac[8 * i + k];
            if (f > 0.0) acc[i + DR[k] * cols + DC[k]] += a * f;
        }
    }
}
