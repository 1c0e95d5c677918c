/* Counter-based random numbers shared by every kernel that needs them.
 *
 * Included with #include "worldbake_hash.h"; pipeline.opencl.load_program
 * passes this folder with -I, and a stage's cache key hashes the header
 * (pipeline.sources). The numpy twin is worldlib/hashing.py: keep them equal.
 *
 * A kernel that hashes vectors defines HASH_UINT (uint4, uint8, ...) before
 * the include; the default is uint.
 */
#ifndef WORLDBAKE_HASH_H
#define WORLDBAKE_HASH_H

#ifndef HASH_UINT
#define HASH_UINT uint
#endif

/* lowbias32 (Chris Wellons): a full-avalanche 32-bit mixer */
inline __attribute__((always_inline)) HASH_UINT mix32(HASH_UINT h)
{
    h ^= h >> 16;
    h *= 0x7feb352du;
    h ^= h >> 15;
    h *= 0x846ca68bu;
    h ^= h >> 16;
    return h;
}

#endif
