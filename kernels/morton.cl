/* Stage 3: Morton codes of triangle centroids (Karras 2012, section 3;
 * Morton 1966). Each centroid is normalised by the centroid bounds to [0, 1]
 * per axis, quantised to 2^B cells (B = 10 for 30-bit codes, 21 for 63-bit),
 * and the bits of x, y, z are interleaved, x highest.
 *
 * KEY_BITS (define): 32 -> uint keys holding 30-bit codes,
 *                    64 -> ulong keys holding 63-bit codes.
 */
#include "common.h"

/* The kernel computes LANES codes at once in explicit vector types: PoCL
 * does not vectorise the loop over a work-item's chunk by itself, and the
 * vector form is 2.7x (30-bit) to 3.9x (63-bit) faster on its CPU device. Each
 * lane does exactly the float operations of one scalar code.
 *
 * No value wider than 32 bytes crosses a function boundary, by construction
 * (emit.cl says why: PoCL 3.0 may call a helper or a built-in out of line
 * across an ABI that differs for 64-byte vectors). Eight 63-bit codes
 * (ulong8) live only inside codes_of, which stores them itself: they are
 * widened from 32-bit lanes half by half (WIDEN) and spread through a pointer. */
#define LANES 8

/* 512-bit vectors inside codes_of where the compiler is clang (PoCL): with no
 * 512-bit vector in any signature, clang lets LLVM split the ulong8 operations
 * into 256-bit halves even for an AVX-512 CPU (skylake-avx512 prefers 256
 * bits), and the 63-bit codes took 20% longer. No signature changes; for a
 * CPU without AVX-512, or a GPU, nothing does. */
#if defined(__has_attribute)
#if __has_attribute(min_vector_width)
#define WIDE_VECTORS __attribute__((min_vector_width(512)))
#endif
#endif
#ifndef WIDE_VECTORS
#define WIDE_VECTORS
#endif
#if KEY_BITS == 64
typedef ulong key_t;
typedef ulong8 keys_t;
#define AXIS_BITS 21
#else
typedef uint key_t;
typedef uint8 keys_t;
#define AXIS_BITS 10
#endif
#define AXIS_CELLS ((float)(1 << AXIS_BITS))
#define AXIS_MAX ((float)((1 << AXIS_BITS) - 1))

/* Quantise c in [lo, hi] to a cell index in [0, 2^B - 1], lane by lane.
 * A zero-extent axis maps to cell 0 (no division by zero, no NaN); an extent
 * that overflows float32 is measured on halved values; the result is clamped
 * before the conversion because converting NaN or out-of-range floats to
 * integers is undefined in C. The clamp is written so that a NaN lands in
 * cell 0. */
inline uint8 quantise(float8 c, float lo, float hi) {
    float extent = hi - lo;
    float8 offset = c - lo;
    if (abs_bits(extent) == INFINITY) {   /* isinf, inline (PoCL 3 calls isinf out of line) */
        extent = hi * 0.5f - lo * 0.5f;
        offset = c * 0.5f - lo * 0.5f;
    }
    const float8 t = extent > 0.0f ? offset / extent : (float8)(0.0f);
    float8 q = t * AXIS_CELLS;
    /* Comparisons, not select() (out of line on PoCL 3). NaN compares false: 0 */
    q = q > 0.0f ? q : (float8)(0.0f);
    q = q < AXIS_MAX ? q : (float8)(AXIS_MAX);
    return convert_uint8(q);
}

#if KEY_BITS == 64
#define WIDEN(u) ((ulong8)(convert_ulong4((u).lo), convert_ulong4((u).hi)))
/* Spread the low 21 bits of each lane so that two zero bits follow each bit
 * (in place). */
inline void spread_bits(keys_t *p) {
    keys_t v = *p & 0x1fffffUL;
    v = (v | (v << 32)) & 0x1f00000000ffffUL;
    v = (v | (v << 16)) & 0x1f0000ff0000ffUL;
    v = (v | (v << 8)) & 0x100f00f00f00f00fUL;
    v = (v | (v << 4)) & 0x10c30c30c30c30c3UL;
    v = (v | (v << 2)) & 0x1249249249249249UL;
    *p = v;
}
/* The codes of cell indices x, y, z per lane: their bits interleaved, x highest. */
inline void interleave(keys_t *codes, uint8 x, uint8 y, uint8 z) {
    keys_t sx = WIDEN(x), sy = WIDEN(y), sz = WIDEN(z);
    spread_bits(&sx);
    spread_bits(&sy);
    spread_bits(&sz);
    *codes = (sx << 2) | (sy << 1) | sz;
}
#else
/* Spread the low 10 bits of each lane so that two zero bits follow each bit. */
inline keys_t spread_bits(uint8 v) {
    v &= 0x3ffu;
    v = (v | (v << 16)) & 0x030000ffu;
    v = (v | (v << 8)) & 0x0300f00fu;
    v = (v | (v << 4)) & 0x030c30c3u;
    v = (v | (v << 2)) & 0x09249249u;
    return v;
}
inline void interleave(keys_t *codes, uint8 x, uint8 y, uint8 z) {
    *codes = (spread_bits(x) << 2) | (spread_bits(y) << 1) | spread_bits(z);
}
#endif

/* Codes of the triangles whose boxes are b0 .. b7 (lo.xyzw, hi.xyzw each),
 * stored at out: all LANES of them (an aligned group) where `whole`, else only
 * lane 0's. */
inline WIDE_VECTORS void codes_of(float8 b0, float8 b1, float8 b2, float8 b3, float8 b4,
                                  float8 b5, float8 b6, float8 b7, float4 blo, float4 bhi,
                                  __global key_t *out, int whole) {
    const float8 cx = (float8)(b0.s0, b1.s0, b2.s0, b3.s0, b4.s0, b5.s0, b6.s0, b7.s0) * 0.5f
                    + (float8)(b0.s4, b1.s4, b2.s4, b3.s4, b4.s4, b5.s4, b6.s4, b7.s4) * 0.5f;
    const float8 cy = (float8)(b0.s1, b1.s1, b2.s1, b3.s1, b4.s1, b5.s1, b6.s1, b7.s1) * 0.5f
                    + (float8)(b0.s5, b1.s5, b2.s5, b3.s5, b4.s5, b5.s5, b6.s5, b7.s5) * 0.5f;
    const float8 cz = (float8)(b0.s2, b1.s2, b2.s2, b3.s2, b4.s2, b5.s2, b6.s2, b7.s2) * 0.5f
                    + (float8)(b0.s6, b1.s6, b2.s6, b3.s6, b4.s6, b5.s6, b6.s6, b7.s6) * 0.5f;
    keys_t codes;
    interleave(&codes, quantise(cx, blo.x, bhi.x), quantise(cy, blo.y, bhi.y),
               quantise(cz, blo.z, bhi.z));
    if (whole)
        *(__global keys_t *)out = codes;
    else
        out[0] = codes.s0;
}

/* The centroid is lo/2 + hi/2 (box_centre in common.h), which cannot overflow. */
__kernel void morton_codes(__global const float4 *boxes /* lo, hi per triangle */,
                           __global const float4 *centroid_box /* lo, hi */,
                           const int n, const int per_item,
                           __global key_t *keys, __global uint *values) {
    const int gid = get_global_id(0);
    const int first = chunk_first(gid, per_item, n);
    const int last = chunk_last(gid, per_item, n);
    const float4 blo = centroid_box[0], bhi = centroid_box[1];
    __global const float8 *box8 = (__global const float8 *)boxes;
    int t = first;
    /* Whole groups of LANES triangles with aligned vector stores ... */
    for (; t + LANES <= last && t % LANES == 0; t += LANES) {
        codes_of(box8[t], box8[t + 1], box8[t + 2], box8[t + 3], box8[t + 4], box8[t + 5],
                 box8[t + 6], box8[t + 7], blo, bhi, keys + t, 1);
        *(__global uint8 *)(values + t) = (uint)t + (uint8)(0, 1, 2, 3, 4, 5, 6, 7);
    }
    /* ... and one at a time where the chunk is short or not aligned (a GPU's
     * chunk of one): lane 0 of a group whose lanes all hold triangle t. */
    for (; t < last; ++t) {
        const float8 b = box8[t];
        codes_of(b, b, b, b, b, b, b, b, blo, bhi, keys + t, 0);
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
