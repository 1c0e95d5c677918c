// Rounding the landslide's cones (hillslope.py round_cones; its numpy
// reference is round_cones_reference): one Jacobi sweep of the Godunov
// upwind update of |grad u| = Sc, u <= its input, on the axis stencil and on
// the diagonal one (spacing sqrt 2), the lower of the two. Ping-pong buffers:
// every cell reads only the previous sweep, so the result does not depend on
// the order the device runs the cells in. No contraction into fma: the
// numbers are numpy's.
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL FP_CONTRACT OFF

static double eikonal_arm(double a, double b, double s)
{
    if (isinf(a) && isinf(b)) return INFINITY;  // no neighbour on either side of this stencil
    double d = fabs(a - b);
    if (d >= s) return fmin(a, b) + s;
    return 0.5 * (a + b + sqrt(2.0 * s * s - d * d));
}

// u and out are padded: (rows + 2) x (cols + 2), the border +inf (no neighbour there), so no cell needs a bounds check
__kernel void round_cones(__global const double* u, __global double* out, __global const double* rise,
                          int rows, int cols)
{
    int c = get_global_id(0), r = get_global_id(1);
    if (r >= rows || c >= cols) return;
    int w = cols + 2, i = (r + 1) * w + c + 1;
    double s = rise[r * cols + c];  // Sc dx of this cell
    double axis = eikonal_arm(fmin(u[i - 1], u[i + 1]), fmin(u[i - w], u[i + w]), s);
    double diag = eikonal_arm(fmin(u[i - w - 1], u[i + w + 1]), fmin(u[i - w + 1], u[i + w - 1]),
                              s * 1.4142135623730951);
    out[i] = fmin(u[i], fmin(axis, diag));
}
