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
 * SCRATCH_BYTES (define): half of sort_buckets' private scratch.
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

/* Where chunk gid's first key of each digit goes: offset[d] = start of
 * digit d in the output + the keys of digit d in the chunks before gid. */
inline void chunk_offsets(uint *offset, __global const uint *counts,
                          __global const uint *digit_totals, int gid, int num_chunks) {
    uint base = 0;
    for (int d = 0; d < RADIX; ++d) {
        offset[d] = base + counts[d * num_chunks + gid];
        base += digit_totals[d];
    }
}

/* The output position of the next key, of digit d. The counter of the
 * current run of equal digits stays in a register (run_pos): coherent meshes
 * give long runs, whose increments would otherwise each wait for the previous
 * store to the same counter. */
inline uint take_position(uint *offset, uint *run_digit, uint *run_pos, uint d) {
    if (d != *run_digit) {
        offset[*run_digit] = *run_pos;
        *run_digit = d;
        *run_pos = offset[d];
    }
    return (*run_pos)++;
}

__kernel void scatter(__global const key_t *keys_in, __global const uint *values_in,
                      __global key_t *keys_out, __global uint *values_out,
                      const int n, const int per_item, const int shift, const int num_chunks,
                      __global const uint *counts, __global const uint *digit_totals) {
    const int gid = get_global_id(0);
    if (gid >= num_chunks) return;
    uint offset[RADIX];
    chunk_offsets(offset, counts, digit_totals, gid, num_chunks);
    uint run_digit = 0, run_pos = offset[0];
    for (int i = chunk_first(gid, per_item, n); i < chunk_last(gid, per_item, n); ++i) {
        const key_t k = keys_in[i];
        const uint pos = take_position(offset, &run_digit, &run_pos, digit_of(k, shift));
        keys_out[pos] = k;
        values_out[pos] = values_in[i];
    }
}

/* CPU path for long keys (lbvh/sort.py decides). One stable scatter by the
 * digit of the highest varying bits (an MSD pass: digit_histogram,
 * scan_counts, scatter_records) leaves the keys sharing that digit in one
 * bucket of about n / 2^RADIX_BITS keys, small enough to stay in cache
 * while LSD passes of LOCAL_BITS-bit digits sort it on the remaining bits
 * where it lies (sort_buckets): one pass over memory instead of one per
 * digit. Every pass is stable, so the result is the stable sort by the whole
 * key (LSD within MSD buckets; Knuth, TAOCP vol. 3, 5.2.5, exercise 10's
 * hybrid).
 *
 * The MSD pass writes each (key, value) pair as one record: half the stores
 * and half the write streams of two arrays (sphere keys: scatter 4.5 -> 2.2
 * ms per 1M keys). sort_buckets reads the records and leaves the sorted pairs
 * in the input arrays, which the MSD pass has consumed. */
#if KEY_BITS == 64
typedef struct {
    ulong key;
    uint value;
} record_t;
inline record_t make_record(ulong k, uint v) {
    record_t r;
    r.key = k;
    r.value = v;
    return r;
}
inline ulong record_key(record_t r) { return r.key; }
inline uint record_value(record_t r) { return r.value; }
#else
/* The key in the high half, the value in the low half. */
typedef ulong record_t;
inline record_t make_record(uint k, uint v) { return ((ulong)k << 32) | v; }
inline uint record_key(record_t r) { return (uint)(r >> 32); }
inline uint record_value(record_t r) { return (uint)r; }
#endif

__kernel void scatter_records(__global const key_t *keys_in, __global const uint *values_in,
                              __global record_t *records, const int n, const int per_item,
                              const int shift, const int num_chunks,
                              __global const uint *counts, __global const uint *digit_totals,
                              __global const key_t *and_or, const int num_partials,
                              const key_t expected) {
    const int gid = get_global_id(0);
    if (gid >= num_chunks || !plan_holds(and_or, num_partials, expected)) return;
    uint offset[RADIX];
    chunk_offsets(offset, counts, digit_totals, gid, num_chunks);
    uint run_digit = 0, run_pos = offset[0];
    for (int i = chunk_first(gid, per_item, n); i < chunk_last(gid, per_item, n); ++i) {
        const key_t k = keys_in[i];
        records[take_position(offset, &run_digit, &run_pos, digit_of(k, shift))] =
            make_record(k, values_in[i]);
    }
}

#if LOCAL_BITS < 3
#error "sort_buckets scans its bins eight at a time: LOCAL_BITS must be at least 3"
#endif
#define LOCAL_RADIX (1 << LOCAL_BITS)
#define LOCAL_MASK (LOCAL_RADIX - 1)
/* Private records of a bucket between passes, two halves of SCRATCH_BYTES
 * (define: 64 KiB on a CPU, in the core's L2; a few bytes where the path does
 * not run, so that no compiler has to find room for it). */
#define SCRATCH_RECORDS (SCRATCH_BYTES / (int)sizeof(record_t))

/* Exclusive prefix sums of the first num8 * 8 bins, eight bins per step: with
 * buckets of a few hundred keys, a scan of 2^LOCAL_BITS bins one by one was a
 * quarter of the pass. */
inline void scan_bins(uint8 *bins, int num8) {
    uint sum = 0;
    for (int d = 0; d < num8; ++d) {
        const uint8 c = bins[d];
        uint8 x = c;
        x += (uint8)(0, x.s0, x.s1, x.s2, x.s3, x.s4, x.s5, x.s6);
        x += (uint8)(0, 0, x.s0, x.s1, x.s2, x.s3, x.s4, x.s5);
        x += (uint8)(0, 0, 0, 0, x.s0, x.s1, x.s2, x.s3);
        bins[d] = x - c + sum;
        sum += x.s7;
    }
}

/* One stable counting pass over the m pairs of the bucket at `start` by the
 * digit (key >> shift) & mask. LOAD(i) declares k and v, the key and value of
 * the source's i-th pair; STORE(p) writes k and v to the destination's p-th.
 * A macro rather than functions: the source and destination are either the
 * records or the key and value arrays. */
#define COUNTING_PASS(LOAD, STORE, shift, mask)                                   \
    do {                                                                          \
        const int pass_shift = (shift);                                           \
        const uint pass_mask = (mask);                                            \
        uint8 bins[LOCAL_RADIX / 8];                                              \
        uint *offset = (uint *)bins;                                              \
        const int num8 = (pass_mask >> 3) + 1;                                    \
        for (int d8 = 0; d8 < num8; ++d8) bins[d8] = 0;                           \
        for (uint i = 0; i < m; ++i) {                                            \
            LOAD(i);                                                              \
            offset[(uint)(k >> pass_shift) & pass_mask]++;                        \
        }                                                                         \
        scan_bins(bins, num8);                                                    \
        for (uint i = 0; i < m; ++i) {                                            \
            LOAD(i);                                                              \
            const uint pos = offset[(uint)(k >> pass_shift) & pass_mask]++;       \
            STORE(pos);                                                           \
        }                                                                         \
    } while (0)

#define LOAD_GLOBAL_RECORD(i)                       \
    const record_t r = records[start + (i)];        \
    const key_t k = record_key(r);                  \
    const uint v = record_value(r)
#define STORE_GLOBAL_RECORD(p) records[start + (p)] = make_record(k, v)
#define LOAD_PAIR(i)                                \
    const key_t k = keys[start + (i)];              \
    const uint v = values[start + (i)]
#define STORE_PAIR(p)                               \
    keys[start + (p)] = k;                          \
    values[start + (p)] = v

/* The two passes of a bucket of m <= SCRATCH_RECORDS records (30-bit keys):
 * both digits counted in one read, both passes between the halves of private
 * scratch, and a sequential copy into the key and value arrays: scattered
 * writes to lines that are not in cache each wait for the line (bucket stage
 * 10-20% faster than the second pass writing the arrays directly). */
inline void two_passes_through_scratch(__global const record_t *records, __global key_t *keys,
                                       __global uint *values, uint m, int shift0, int shift1,
                                       record_t *scratch) {
    uint8 bins0[LOCAL_RADIX / 8], bins1[LOCAL_RADIX / 8];
    uint *offset0 = (uint *)bins0, *offset1 = (uint *)bins1;
    for (int d = 0; d < LOCAL_RADIX / 8; ++d) bins0[d] = bins1[d] = 0;
    for (uint i = 0; i < m; ++i) {
        const key_t k = record_key(records[i]);
        offset0[(uint)(k >> shift0) & LOCAL_MASK]++;
        offset1[(uint)(k >> shift1) & LOCAL_MASK]++;
    }
    scan_bins(bins0, LOCAL_RADIX / 8);
    scan_bins(bins1, LOCAL_RADIX / 8);
    for (uint i = 0; i < m; ++i) {
        const record_t r = records[i];
        scratch[offset0[(uint)(record_key(r) >> shift0) & LOCAL_MASK]++] = r;
    }
    record_t *sorted = scratch + SCRATCH_RECORDS;
    for (uint i = 0; i < m; ++i) {
        const record_t r = scratch[i];
        sorted[offset1[(uint)(record_key(r) >> shift1) & LOCAL_MASK]++] = r;
    }
    for (uint i = 0; i < m; ++i) {
        const record_t r = sorted[i];
        keys[i] = record_key(r);
        values[i] = record_value(r);
    }
}

/* The passes of each bucket, from its records to the key and value arrays.
 * One pass goes straight there; two (30-bit keys) go through private scratch;
 * longer plans, and buckets too large for the scratch, alternate between the
 * records and the arrays and end with a copy where the count is even.
 *
 * Work-item g sorts the buckets that start in its chunk of [0, n). */
__kernel void sort_buckets(__global record_t *records, __global key_t *keys,
                           __global uint *values, const int n, const int per_item,
                           __global const uint *digit_totals, __global const int *local_shifts,
                           const int num_local, __global const key_t *and_or,
                           const int num_partials, const key_t expected) {
    const int gid = get_global_id(0);
    if (!plan_holds(and_or, num_partials, expected)) return;
    const uint lo = (uint)chunk_first(gid, per_item, n);
    const uint hi = (uint)chunk_last(gid, per_item, n);
    record_t scratch[2 * SCRATCH_RECORDS];
    uint start = 0;
    for (int d = 0; d < RADIX && start < hi; ++d) {
        const uint m = digit_totals[d];
        if (start >= lo && m > 0) {
            if (num_local == 1) {
                COUNTING_PASS(LOAD_GLOBAL_RECORD, STORE_PAIR, local_shifts[0], LOCAL_MASK);
            } else if (num_local == 2 && m <= SCRATCH_RECORDS) {
                two_passes_through_scratch(records + start, keys + start, values + start, m,
                                           local_shifts[0], local_shifts[1], scratch);
            } else {
                for (int p = 0; p < num_local; ++p) {
                    if (p % 2 == 0)
                        COUNTING_PASS(LOAD_GLOBAL_RECORD, STORE_PAIR, local_shifts[p], LOCAL_MASK);
                    else
                        COUNTING_PASS(LOAD_PAIR, STORE_GLOBAL_RECORD, local_shifts[p], LOCAL_MASK);
                }
                if (num_local % 2 == 0)   /* a copy: one digit, 0 */
                    COUNTING_PASS(LOAD_GLOBAL_RECORD, STORE_PAIR, 0, 0u);
            }
        }
        start += m;
    }
}
