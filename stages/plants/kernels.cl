// Plant geometry kernels: data-parallel vertex generation for branch tubes,
// leaf instances and grass blades. The numpy twins are in reference.py;
// the layouts (VERT, RING, LEAF, TMPL, BLADE) are documented there.
// Deterministic: each work-item writes its own rows, no atomics.

#define VERT 14
#define RING 20
#define LEAF 17
#define TMPL 9
#define BLADE 14

inline float3 ld3(__global const float *p) { return (float3)(p[0], p[1], p[2]); }
inline void st3(__global float *p, float3 v) { p[0] = v.x; p[1] = v.y; p[2] = v.z; }
inline float3 safe_normalize(float3 v) {
    float n = sqrt(dot(v, v));
    return n > 0.0f ? v / n : v;
}

// One work-item per ring; it writes sides + 1 vertices (the seam repeats k = 0 at u = 1).
__kernel void tube_rings(const int n_rings,
                         __global const float *ring,
                         __global const int *sides,
                         __global const int *offset,
                         __global float *out)
{
    int r = get_global_id(0);
    if (r >= n_rings) return;
    __global const float *R = ring + (size_t)r * RING;
    float3 c = ld3(R), N = ld3(R + 3), B = ld3(R + 6), T = ld3(R + 9);
    float radius = R[12], slope = R[13], v = R[14], bw = R[15], phase = R[16];
    float3 pivot = ld3(R + 17);
    int s = sides[r];
    for (int k = 0; k <= s; ++k) {
        float th = 2.0f * M_PI_F * (float)k / (float)s;
        float cs = cos(th), sn = sin(th);
        if (k == s) { cs = 1.0f; sn = 0.0f; }
        float3 d = cs * N + sn * B;
        __global float *o = out + (size_t)(offset[r] + k) * VERT;
        st3(o, c + radius * d);
        st3(o + 3, safe_normalize(d + slope * T));
        o[6] = (float)k / (float)s;
        o[7] = v;
        o[8] = bw;
        o[9] = 0.0f;
        o[10] = phase;
        st3(o + 11, pivot);
    }
}

// One work-item per (leaf, template vertex).
__kernel void leaf_instances(const int n_leaves, const int n_tmpl,
                             __global const float *leaf,
                             __global const float *tmpl,
                             __global float *out)
{
    int gid = get_global_id(0);
    if (gid >= n_leaves * n_tmpl) return;
    int li = gid / n_tmpl, ti = gid - li * n_tmpl;
    __global const float *Lf = leaf + (size_t)li * LEAF;
    __global const float *Tp = tmpl + (size_t)ti * TMPL;
    float3 pos = ld3(Lf), H = ld3(Lf + 3), Lv = ld3(Lf + 6), U = ld3(Lf + 9);
    float sc = Lf[12], curl = Lf[14];
    float x = Tp[0], y = Tp[1], z = Tp[2];
    __global float *o = out + (size_t)gid * VERT;
    st3(o, pos + sc * (x * Lv + y * H + (z - curl * y * y) * U));
    st3(o + 3, safe_normalize(Tp[3] * Lv + (Tp[4] + 2.0f * curl * y * Tp[5]) * H + Tp[5] * U));
    o[6] = Tp[6];
    o[7] = Tp[7];
    o[8] = Lf[15];
    o[9] = Tp[8];
    o[10] = Lf[16];
    st3(o + 11, pos);
}

// One work-item per (blade, row): rows j < n write two vertices, row n the tip.
// rows holds each blade's n + 1 curve parameters (curvature-adapted, grass.py).
__kernel void grass_blades(const int n_blades, const int n, const float taper,
                           __global const float *blade,
                           __global const float *rows,
                           __global float *out)
{
    int gid = get_global_id(0);
    if (gid >= n_blades * (n + 1)) return;
    int bi = gid / (n + 1), j = gid - bi * (n + 1);
    __global const float *Bd = blade + (size_t)bi * BLADE;
    float3 b = ld3(Bd), h = ld3(Bd + 3), t = ld3(Bd + 6), s = ld3(Bd + 9);
    float w = Bd[12], phase = Bd[13];
    float v = rows[(size_t)bi * (n + 1) + j];   // curve parameter of this row
    float3 a = b + v * (h - b);          // De Casteljau
    float3 q = h + v * (t - h);
    float3 c = a + v * (q - a);
    float3 nrm = safe_normalize(cross(s, q - a));
    float hw = 0.5f * w * (1.0f - (v > 0.0f ? exp2(taper * log2(v)) : 0.0f));
    __global float *o = out + ((size_t)bi * (2 * n + 1) + 2 * j) * VERT;
    int cnt = j < n ? 2 : 1;
    for (int e = 0; e < cnt; ++e) {
        __global float *oe = o + e * VERT;
        float3 p = j < n ? (e == 0 ? c - hw * s : c + hw * s) : c;
        st3(oe, p);
        st3(oe + 3, nrm);
        oe[6] = j < n ? (float)e : 0.5f;
        oe[7] = v;
        oe[8] = v * v;
        oe[9] = v;
        oe[10] = phase;
        st3(oe + 11, b);
    }
}

// The roofline reference: a plain copy, to compare achieved bandwidth.
__kernel void copy_floats(const int n, __global const float *src, __global float *dst)
{
    int i = get_global_id(0);
    if (i < n) dst[i] = src[i];
}
