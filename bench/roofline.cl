/* The roofline reference: the bench takes the fastest of three copies, which
 * differ by level of the memory hierarchy: a plain copy, one float4 per
 * work-item; 8 float16 per work-item (fastest from cache); streaming stores
 * that skip the read-for-ownership of the destination (fastest from DRAM). */
__kernel void copy4(__global const float4 *restrict a, __global float4 *restrict b, const int n)
{
    int i = get_global_id(0);
    if (i < n) b[i] = a[i];
}

__kernel void copy16x8(__global const float16 *restrict a, __global float16 *restrict b)
{
    int i = get_global_id(0) * 8;
    for (int k = 0; k < 8; k++)
        b[i + k] = a[i + k];
}

__kernel void copy16_stream(__global const float16 *restrict a, __global float16 *restrict b)
{
    int i = get_global_id(0);
#ifdef __clang__
    __builtin_nontemporal_store(a[i], &b[i]);
#else
    b[i] = a[i];
#endif
}
