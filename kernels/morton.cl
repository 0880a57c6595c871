/* Stage 3: Morton codes of triangle centroids (Karras 2012, section 3;
 * Morton 1966). Each centroid is normalised by the centroid bounds to [0, 1]
 * per axis, quantised to 2^B cells (B = 10 for 30-bit codes, 21 for 63-bit),
 * and the bits of x, y, z are interleaved, x highest.
 *
 * KEY_BITS (define): 32 -> uint keys holding 30-bit codes,
 *                    64 -> ulong keys holding 63-bit codes.
 */
#include "common.h"

#if KEY_BITS == 64
typedef ulong key_t;
#define AXIS_BITS 21
#else
typedef uint key_t;
#define AXIS_BITS 10
#endif
#define AXIS_CELLS ((float)(1 << AXIS_BITS))
#define AXIS_MAX ((float)((1 << AXIS_BITS) - 1))

/* Quantise c in [lo, hi] to a cell index in [0, 2^B - 1].
 * A zero-extent axis maps to cell 0 (no division by zero, no NaN); an extent
 * that overflows float32 is measured on halved values; the result is clamped
 * before the cast because converting NaN or out-of-range floats to integers is
 * undefined in C. The clamp is written so that a NaN lands in cell 0. */
inline uint quantise(float c, float lo, float hi) {
    float extent = hi - lo;
    float offset = c - lo;
    if (isinf(extent)) {
        extent = hi * 0.5f - lo * 0.5f;
        offset = c * 0.5f - lo * 0.5f;
    }
    float t = extent > 0.0f ? offset / extent : 0.0f;
    float q = t * AXIS_CELLS;
    q = q > 0.0f ? q : 0.0f;  /* NaN compares false: 0 */
    q = q < AXIS_MAX ? q : AXIS_MAX;
    return (uint)q;
}

#if KEY_BITS == 64
/* Spread the low 21 bits of v so that two zero bits follow each bit. */
inline ulong spread_bits(ulong v) {
    v &= 0x1fffffUL;
    v = (v | (v << 32)) & 0x1f00000000ffffUL;
    v = (v | (v << 16)) & 0x1f0000ff0000ffUL;
    v = (v | (v << 8)) & 0x100f00f00f00f00fUL;
    v = (v | (v << 4)) & 0x10c30c30c30c30c3UL;
    v = (v | (v << 2)) & 0x1249249249249249UL;
    return v;
}
#else
/* Spread the low 10 bits of v so that two zero bits follow each bit. */
inline uint spread_bits(uint v) {
    v &= 0x3ffu;
    v = (v | (v << 16)) & 0x030000ffu;
    v = (v | (v << 8)) & 0x0300f00fu;
    v = (v | (v << 4)) & 0x030c30c3u;
    v = (v | (v << 2)) & 0x09249249u;
    return v;
}
#endif

__kernel void morton_codes(__global const float4 *boxes /* lo, hi per triangle */,
                           __global const float4 *centroid_box /* lo, hi */,
                           const int n, const int per_item,
                           __global key_t *keys, __global uint *values) {
    const int gid = get_global_id(0);
    const int first = chunk_first(gid, per_item, n);
    const int last = chunk_last(gid, per_item, n);
    const float4 blo = centroid_box[0], bhi = centroid_box[1];
    for (int t = first; t < last; ++t) {
        float3 c = box_centre(boxes[2 * t].xyz, boxes[2 * t + 1].xyz);
        key_t x = (key_t)quantise(c.x, blo.x, bhi.x);
        key_t y = (key_t)quantise(c.y, blo.y, bhi.y);
        key_t z = (key_t)quantise(c.z, blo.z, bhi.z);
        keys[t] = (spread_bits(x) << 2) | (spread_bits(y) << 1) | spread_bits(z);
        values[t] = (uint)t;
    }
}

/* Number of sorted keys equal to their predecessor, per work-item chunk:
 * the "duplicate codes" that the automatic key width looks at. */
__kernel void count_duplicates(__global const key_t *sorted_keys, const int n,
                               const int per_item, __global uint *partial) {
    const int gid = get_global_id(0);
    const int first = max(chunk_first(gid, per_item, n), 1);
    const int last = chunk_last(gid, per_item, n);
    uint dups = 0;
    for (int i = first; i < last; ++i)
        dups += sorted_keys[i] == sorted_keys[i - 1];
    partial[gid] = dups;
}
