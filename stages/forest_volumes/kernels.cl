/* The sector splat: every (instance, occupied source voxel) pair carried
 * through the instance's transform and shared among the sector voxels its
 * cube overlaps (splat.py's reference does the same in numpy).
 * Sums are 64-bit fixed point (value x `fixed`, rounded to nearest even)
 * added with integer atomics: integer addition does not depend on the
 * order, so the sums are the same for every work-group size and schedule.
 * float64 with no contraction so the numpy reference gives the same
 * deposits. */
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL EXTENSION cl_khr_int64_base_atomics : enable
#pragma OPENCL FP_CONTRACT OFF

/* One work-item per (instance i, source voxel v), g = i * n_vox + v.
 * pos (n, 3), rot (n, 9) row-major, scale (n); centre (v, 3) in the plant's
 * frame; held (v, 8): density, premultiplied albedo (3), surface, normal (3)
 * of the source voxel. acc: 8 channels of nx * ny * nz voxels (x fastest). */
__kernel void splat(const int n_inst, const int n_vox, __global const double *pos, __global const double *rot,
                    __global const double *scale, __global const double *centre, __global const double *held,
                    const double ox, const double oy, const double oz, const double voxel, const double src_voxel,
                    const double ratio, const int nx, const int ny, const int nz, const double fixed,
                    __global long *acc)
{
    const long g = get_global_id(0);
    if (g >= (long)n_inst * (long)n_vox) return;
    const int i = (int)(g / n_vox), v = (int)(g % n_vox);
    const double S = scale[i];
    __global const double *R = rot + 9 * i;
    const double c0 = centre[3 * v], c1 = centre[3 * v + 1], c2 = centre[3 * v + 2];
    const double o[3] = {ox, oy, oz};
    const double r = fmin(0.5 * S * src_voxel / voxel, 0.5);
    long i0[3];
    double f[3];
    for (int a = 0; a < 3; ++a) {
        const double rc = R[3 * a] * c0 + R[3 * a + 1] * c1 + R[3 * a + 2] * c2;
        const double u = (pos[3 * i + a] + S * rc - o[a]) / voxel;
        const double lo = floor(u - r);
        i0[a] = (long)lo;
        f[a] = fmax(u + r - (lo + 1.0), 0.0) / (2.0 * r);
    }
    __global const double *h = held + 8 * v;
    const double k = S * S * ratio;
    double val[8];
    val[0] = k * h[0];
    val[1] = k * h[1]; val[2] = k * h[2]; val[3] = k * h[3];
    val[4] = k * h[4];
    for (int a = 0; a < 3; ++a)
        val[5 + a] = val[4] * (R[3 * a] * h[5] + R[3 * a + 1] * h[6] + R[3 * a + 2] * h[7]);
    const long count = (long)nx * ny * nz;
    for (int dk = 0; dk < 2; ++dk)
        for (int dj = 0; dj < 2; ++dj)
            for (int di = 0; di < 2; ++di) {
                const long x = i0[0] + di, y = i0[1] + dj, z = i0[2] + dk;
                if (x < 0 || y < 0 || z < 0 || x >= nx || y >= ny || z >= nz) continue;
                const double w = ((di ? f[0] : 1.0 - f[0]) * (dj ? f[1] : 1.0 - f[1])) * (dk ? f[2] : 1.0 - f[2]);
                if (!(w > 0.0)) continue;
                const long at = (z * ny + y) * nx + x;
                for (int q = 0; q < 8; ++q)
                    atom_add(acc + q * count + at, (long)rint(w * val[q] * fixed));
            }
}
