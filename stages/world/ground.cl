// The ground albedo of a band of texel rows of one UDIM tile, one work item per texel: the splat
// weights bilinear between cell centres (clamped at the edges), each ground
// type's colour times its periodic detail table at the texel, summed. The
// taps are separable, so the host computes them per texel column and per
// texel row exactly as the numpy reference does (ground.tile_albedo); the
// kernel only gathers and blends. The splat is a window of the world's (the taps are relative to it).

#define MAX_TYPES 8

__kernel void tile_albedo(__global const float *restrict splat, const int cols, const int types,
                          __global const float *restrict tables, const int period,
                          __global const float *restrict colours, const int texels, const int rows,
                          __global const int *restrict col_taps,   // per texel column: c0, c1, detail column
                          __global const float *restrict col_frac, // per texel column: the share of c1
                          __global const int *restrict row_taps,   // per texel row: r0, r1, detail row
                          __global const float *restrict row_frac, // per texel row: the share of r1
                          __global float *restrict out)
{
    const int i = get_global_id(0), j = get_global_id(1);  // texel column (east), row (0 = the band's north edge)
    if (i >= texels || j >= rows)
        return;
    const int c0 = col_taps[3 * i], c1 = col_taps[3 * i + 1], di = col_taps[3 * i + 2];
    const int r0 = row_taps[3 * j], r1 = row_taps[3 * j + 1], dj = row_taps[3 * j + 2];
    const float fc = col_frac[i], fr = row_frac[j];
    __global const float *s00 = splat + ((long)r0 * cols + c0) * types, *s10 = splat + ((long)r1 * cols + c0) * types;
    __global const float *s01 = splat + ((long)r0 * cols + c1) * types, *s11 = splat + ((long)r1 * cols + c1) * types;
    float rgb[3] = {0.0f, 0.0f, 0.0f};
    for (int k = 0; k < types && k < MAX_TYPES; ++k) {
        const float a = s00[k] * (1.0f - fr) + s10[k] * fr;  // along the rows first, as the reference
        const float b = s01[k] * (1.0f - fr) + s11[k] * fr;
        const float w = a * (1.0f - fc) + b * fc;
        const float blend = tables[((long)k * period + dj) * period + di] * w;
        for (int c = 0; c < 3; ++c)
            rgb[c] += colours[k * 3 + c] * blend;
    }
    __global float *o = out + ((long)j * texels + i) * 3;
    for (int c = 0; c < 3; ++c)
        o[c] = clamp(rgb[c], 0.0f, 1.0f);
}
