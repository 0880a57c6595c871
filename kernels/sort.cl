/* Stage 4: stable LSD radix sort of (key, value) pairs.
 *
 * One pass per RADIX_BITS-bit digit, least significant first (Knuth, TAOCP
 * vol. 3, 5.2.5; the counting/scan/scatter split of Merrill & Grimshaw 2011).
 * The keys are cut into G contiguous chunks, one per work-item:
 *   1. digit_histogram: each chunk counts its digits -> counts[d * G + g]
 *   2. scan_counts:     one work-item per digit d scans counts[d * G + 0..G)
 *                       (exclusive) and writes the digit's total
 *   3. scatter:         each chunk walks its keys in order and writes each to
 *                       base(d) + counts[d * G + g] + rank within the chunk;
 *                       walking in order keeps the sort stable.
 * Large contiguous chunks suit a CPU device (PoCL); on a GPU the same kernels
 * run with many small chunks. Passes whose digit is the same in every key are
 * skipped by the host, which reads the AND and OR of all keys (key_bits).
 *
 * On a CPU, with many keys and more varying bits than one digit holds, the
 * host runs one such pass over the highest varying bits only and then
 * sort_buckets (below) instead of the remaining passes.
 *
 * KEY_BITS (define): 32 or 64. RADIX_BITS (define): digit width, e.g. 8.
 * LOCAL_BITS (define): digit width of sort_buckets' in-cache passes.
 */
#include "common.h"

#if KEY_BITS == 64
typedef ulong key_t;
#else
typedef uint key_t;
#endif
#define RADIX (1 << RADIX_BITS)
#define DIGIT_MASK (RADIX - 1)

inline uint digit_of(key_t key, int shift) { return (uint)(key >> shift) & DIGIT_MASK; }

/* AND and OR of the keys of each chunk: bits where AND != OR vary. Both go
 * to one array (ANDs, then ORs) that the host reads back in one command. */
__kernel void key_bits(__global const key_t *keys, const int n, const int per_item,
                       __global key_t *and_or) {
    const int gid = get_global_id(0);
    const int first = chunk_first(gid, per_item, n);
    const int last = chunk_last(gid, per_item, n);
    key_t a = ~(key_t)0, o = 0;
    for (int i = first; i < last; ++i) {
        a &= keys[i];
        o |= keys[i];
    }
    and_or[gid] = a;
    and_or[get_global_size(0) + gid] = o;
}

/* Speculative plan (lbvh/sort.py): the host may queue the passes for the
 * varying bits it expects before it has read the real ones. The passes then
 * do nothing unless the bits that vary (from key_bits' partial ANDs and ORs,
 * num_partials of each) are exactly `expected`; num_partials = 0: no check. */
inline int plan_holds(__global const key_t *and_or, int num_partials, key_t expected) {
    key_t a = ~(key_t)0, o = 0;
    for (int g = 0; g < num_partials; ++g) {
        a &= and_or[g];
        o |= and_or[num_partials + g];
    }
    return num_partials == 0 || (a ^ o) == expected;
}

__kernel void digit_histogram(__global const key_t *keys, const int n, const int per_item,
                              const int shift, const int num_chunks, __global uint *counts,
                              __global const key_t *and_or, const int num_partials,
                              const key_t expected) {
    const int gid = get_global_id(0);
    if (gid >= num_chunks || !plan_holds(and_or, num_partials, expected)) return;
    const int first = chunk_first(gid, per_item, n);
    const int last = chunk_last(gid, per_item, n);
    /* Four histograms, one per key index mod 4: runs of equal digits
     * (coherent meshes) would otherwise chain every increment on the
     * previous one. */
    uint hist[4][RADIX];
    for (int d = 0; d < RADIX; ++d) hist[0][d] = hist[1][d] = hist[2][d] = hist[3][d] = 0;
    int i = first;
    for (; i + 3 < last; i += 4) {
        hist[0][digit_of(keys[i], shift)]++;
        hist[1][digit_of(keys[i + 1], shift)]++;
        hist[2][digit_of(keys[i + 2], shift)]++;
        hist[3][digit_of(keys[i + 3], shift)]++;
    }
    for (; i < last; ++i) hist[0][digit_of(keys[i], shift)]++;
    for (int d = 0; d < RADIX; ++d)
        counts[d * num_chunks + gid] = (hist[0][d] + hist[1][d]) + (hist[2][d] + hist[3][d]);
}

__kernel void scan_counts(__global uint *counts, const int num_chunks,
                          __global uint *digit_totals) {
    const int d = get_global_id(0);
    if (d >= RADIX) return;
    __global uint *row = counts + d * num_chunks;
    uint sum = 0;
    for (int g = 0; g < num_chunks; ++g) {
        uint c = row[g];
        row[g] = sum;
        sum += c;
    }
    digit_totals[d] = sum;
}

__kernel void scatter(__global const key_t *keys_in, __global const uint *values_in,
                      __global key_t *keys_out, __global uint *values_out,
                      const int n, const int per_item, const int shift, const int num_chunks,
                      __global const uint *counts, __global const uint *digit_totals,
                      __global const key_t *and_or, const int num_partials, const key_t expected) {
    const int gid = get_global_id(0);
    if (gid >= num_chunks || !plan_holds(and_or, num_partials, expected)) return;
    const int first = chunk_first(gid, per_item, n);
    const int last = chunk_last(gid, per_item, n);
    uint offset[RADIX];
    uint base = 0;
    for (int d = 0; d < RADIX; ++d) {
        offset[d] = base + counts[d * num_chunks + gid];
        base += digit_totals[d];
    }
    /* The counter of the current run of equal digits stays in a register:
     * coherent meshes give long runs, whose increments would otherwise each
     * wait for the previous store to the same counter. */
    uint run_digit = 0, pos = offset[0];
    for (int i = first; i < last; ++i) {
        const key_t k = keys_in[i];
        const uint d = digit_of(k, shift);
        if (d != run_digit) {
            offset[run_digit] = pos;
            run_digit = d;
            pos = offset[d];
        }
        keys_out[pos] = k;
        values_out[pos] = values_in[i];
        ++pos;
    }
}

/* CPU path for long keys (lbvh/sort.py decides). After one stable scatter by
 * the digit of the highest varying bits (the kernels above, an MSD pass), the
 * keys sharing that digit form a bucket of about n / 2^RADIX_BITS keys, small
 * enough to stay in cache while LSD passes of LOCAL_BITS-bit digits sort it on
 * the remaining bits where it lies: one pass over memory instead of one per
 * digit. Every pass is stable, so the result is the stable sort by the whole
 * key (LSD within MSD buckets; Knuth, TAOCP vol. 3, 5.2.5, exercise 10's
 * hybrid). Passes alternate between the two buffers inside the bucket's
 * range, so every bucket ends in the same buffer: a after an even number of
 * passes, b after an odd one.
 *
 * Work-item g sorts the buckets that start in its chunk of [0, n). */
#if LOCAL_BITS < 3
#error "sort_buckets scans its bins eight at a time: LOCAL_BITS must be at least 3"
#endif
#define LOCAL_RADIX (1 << LOCAL_BITS)
#define LOCAL_MASK (LOCAL_RADIX - 1)

inline void bucket_pass(__global const key_t *src_keys, __global const uint *src_values,
                        __global key_t *dst_keys, __global uint *dst_values,
                        uint start, uint end, int shift) {
    uint8 bins[LOCAL_RADIX / 8];
    uint *offset = (uint *)bins;
    for (int d = 0; d < LOCAL_RADIX / 8; ++d) bins[d] = 0;
    for (uint i = start; i < end; ++i) offset[(uint)(src_keys[i] >> shift) & LOCAL_MASK]++;
    /* Exclusive prefix sums from `start`, eight bins per step: with buckets of
     * a few hundred keys, a scan of 2^LOCAL_BITS bins one by one was a quarter
     * of the pass. */
    uint sum = start;
    for (int d = 0; d < LOCAL_RADIX / 8; ++d) {
        const uint8 c = bins[d];
        uint8 x = c;
        x += (uint8)(0, x.s0, x.s1, x.s2, x.s3, x.s4, x.s5, x.s6);
        x += (uint8)(0, 0, x.s0, x.s1, x.s2, x.s3, x.s4, x.s5);
        x += (uint8)(0, 0, 0, 0, x.s0, x.s1, x.s2, x.s3);
        bins[d] = x - c + sum;
        sum += x.s7;
    }
    for (uint i = start; i < end; ++i) {
        const key_t k = src_keys[i];
        const uint pos = offset[(uint)(k >> shift) & LOCAL_MASK]++;
        dst_keys[pos] = k;
        dst_values[pos] = src_values[i];
    }
}

__kernel void sort_buckets(__global key_t *keys_a, __global uint *values_a,
                           __global key_t *keys_b, __global uint *values_b,
                           const int n, const int per_item, __global const uint *digit_totals,
                           __global const int *local_shifts, const int num_local,
                           __global const key_t *and_or, const int num_partials,
                           const key_t expected) {
    const int gid = get_global_id(0);
    if (!plan_holds(and_or, num_partials, expected)) return;
    const uint lo = (uint)chunk_first(gid, per_item, n);
    const uint hi = (uint)chunk_last(gid, per_item, n);
    uint start = 0;
    for (int d = 0; d < RADIX && start < hi; ++d) {
        const uint end = start + digit_totals[d];
        if (start >= lo && end > start) {
            for (int p = 0; p < num_local; ++p) {
                if (p % 2 == 0)
                    bucket_pass(keys_a, values_a, keys_b, values_b, start, end, local_shifts[p]);
                else
                    bucket_pass(keys_b, values_b, keys_a, values_a, start, end, local_shifts[p]);
            }
        }
        start = end;
    }
}
