/* Stage 5: hierarchy emission, exactly as Karras 2012 ("Maximizing
 * Parallelism in the Construction of BVHs, Octrees, and k-d Trees", HPG),
 * section 4 and Figure 4. Internal node i (0 <= i < n-1) is emitted
 * independently of all others:
 *   d      = sign(delta(i, i+1) - delta(i, i-1))      direction of its range
 *   lmax   : exponential search, then l by binary search, so that the range
 *            is [i, i + l*d] (the keys sharing more than delta(i, i-d) bits)
 *   split  : binary search for the last key sharing more than delta(i, j)
 *            bits with key i (gamma = i + s*d + min(d, 0))
 * delta(i, j) is the length of the common prefix of keys i and j, -1 when j is
 * outside [0, n). Equal keys fall back on the indices (section 4, "duplicate
 * keys"): delta over the concatenation key . index, so the tree is valid
 * whatever the input.
 *
 * Two choices of ours, the same tree bit for bit (tested against the serial
 * Python twin, lbvh/emit.py):
 * - Prefix comparisons without counting bits. With x_j = K_i xor K_j over the
 *   concatenated keys K, delta(i, j) = clz(x_j), so
 *       delta(i, j) > delta(i, m)  <=>  x_j <= 2^msb(x_m) - 1,
 *   a mask computed once per search (below_msb). The direction compares x
 *   directly: x_{i+1} < x_{i-1} <=> delta(i, i+1) > delta(i, i-1), since the
 *   two never share their highest bit for sorted distinct K.
 * - LANES consecutive nodes at once in explicit vectors: each search step is
 *   one vector step for all lanes, the loop ending when every lane is done.
 *   The scalar searches' branches were unpredictable (about half of them
 *   mispredicted) and PoCL does not vectorise a work-item's loop by itself:
 *   the lanes are 25-30% faster with 30-bit keys and 10-15% with 63-bit keys
 *   on the CPU device. A GPU work-item takes one group of LANES nodes.
 *
 * Numbering (docs/layout.md): internal node i is node i, leaf j is node n-1+j
 * and holds sorted slot j. Parent links are written by the parent. The far
 * end j of node i's range goes where its lower.x will be, and a zero where
 * its lower.y will be: the build's refit (refit.cl, KARRAS_RANGES) reads the
 * one, counts the arrivals at the node in the other, and writes the box over
 * both.
 *
 * KEY_BITS (define): 32 or 64.
 * WRITE_LEAVES (define, default 1): 0 leaves the leaf records alone; the
 * build's refit (refit.cl, KARRAS_RANGES) writes them whole with their boxes,
 * which spares a pass over half the node array (about 10% of the emission).
 */
#include "common.h"

#ifndef WRITE_LEAVES
#define WRITE_LEAVES 1
#endif

#define LANES 8

/* Lane masks are 0 or -1. select() and any() are written out because PoCL 3
 * calls both out of line. */
inline int8 blend_int(int8 a, int8 b, int8 m) { return (a & ~m) | (b & m); }
inline uint8 blend_uint(uint8 a, uint8 b, int8 m) { return (a & ~as_uint8(m)) | (b & as_uint8(m)); }
inline ulong8 blend_ulong(ulong8 a, ulong8 b, int8 m) {
    const ulong8 w = as_ulong8(convert_long8(m));
    return (a & ~w) | (b & w);
}
inline int any_lane(int8 m) {
    const int4 h = m.lo | m.hi;
    const int2 q = h.lo | h.hi;
    return (q.x | q.y) != 0;
}

/* K = key . slot per lane, and the operations the searches need on it. */
/* or_all_ones(a, m): all ones where m is set, the largest xor ("no neighbour"). */
#if KEY_BITS == 64
typedef ulong key_t;
typedef ulong8 keys_t;
typedef struct { ulong8 hi; uint8 lo; } prefix_t;  /* 96 bits, compared as (hi, lo) */
inline prefix_t concat(keys_t k, int8 j) { prefix_t p = {k, as_uint8(j)}; return p; }
inline prefix_t xor_keys(prefix_t a, prefix_t b) { prefix_t p = {a.hi ^ b.hi, a.lo ^ b.lo}; return p; }
inline int8 prefix_le(prefix_t a, prefix_t b) {
    return convert_int8((a.hi < b.hi) | ((a.hi == b.hi) & convert_long8(a.lo <= b.lo)));
}
inline int8 prefix_lt(prefix_t a, prefix_t b) {
    return convert_int8((a.hi < b.hi) | ((a.hi == b.hi) & convert_long8(a.lo < b.lo)));
}
inline prefix_t prefix_select(prefix_t a, prefix_t b, int8 m) {
    prefix_t p = {blend_ulong(a.hi, b.hi, m), blend_uint(a.lo, b.lo, m)};
    return p;
}
inline prefix_t or_all_ones(prefix_t a, int8 m) {
    prefix_t p = {a.hi | as_ulong8(convert_long8(m)), a.lo | as_uint8(m)};
    return p;
}
#else
typedef uint key_t;
typedef uint8 keys_t;
typedef ulong8 prefix_t;  /* key << 32 | slot */
inline prefix_t concat(keys_t k, int8 j) { return (convert_ulong8(k) << 32) | convert_ulong8(as_uint8(j)); }
inline prefix_t xor_keys(prefix_t a, prefix_t b) { return a ^ b; }
inline int8 prefix_le(prefix_t a, prefix_t b) { return convert_int8(a <= b); }
inline int8 prefix_lt(prefix_t a, prefix_t b) { return convert_int8(a < b); }
inline prefix_t prefix_select(prefix_t a, prefix_t b, int8 m) { return blend_ulong(a, b, m); }
inline prefix_t or_all_ones(prefix_t a, int8 m) { return a | as_ulong8(convert_long8(m)); }
#endif

/* 2^msb(x) - 1: the xors below it share more leading bits than x does. */
inline ulong8 below_msb64(ulong8 x) {
    x |= x >> 1; x |= x >> 2; x |= x >> 4; x |= x >> 8; x |= x >> 16; x |= x >> 32;
    return x >> 1;
}
#if KEY_BITS == 64
inline uint8 below_msb32(uint8 x) {
    x |= x >> 1; x |= x >> 2; x |= x >> 4; x |= x >> 8; x |= x >> 16;
    return x >> 1;
}
inline prefix_t below_msb(prefix_t x) {
    prefix_t p = {below_msb64(x.hi), blend_uint(below_msb32(x.lo), (uint8)(~0u), convert_int8(x.hi != 0))};
    return p;
}
#else
inline prefix_t below_msb(prefix_t x) { return below_msb64(x); }
#endif

inline keys_t gather(__global const key_t *keys, int8 j) {
    return (keys_t)(keys[j.s0], keys[j.s1], keys[j.s2], keys[j.s3],
                    keys[j.s4], keys[j.s5], keys[j.s6], keys[j.s7]);
}

/* delta(i, j) > delta(i, m) per lane, given mask = below_msb(x_m); false where
 * j is outside [0, n) (delta -1). */
inline int8 shares_more(__global const key_t *keys, int n, prefix_t ki, int8 j, prefix_t mask) {
    const int8 valid = as_uint8(j) < (uint)n;
    const int8 jc = j & valid;
    return valid & prefix_le(xor_keys(ki, concat(gather(keys, jc), jc)), mask);
}

inline void set_children(__global int *node_words, int node, int a, int b) {
    node_words[8 * node + 3] = a;  /* lower.w */
    node_words[8 * node + 7] = b;  /* upper.w */
}

/* Figure 4 of Karras 2012 for internal nodes i0 .. i0+LANES-1 below `limit`
 * (lanes past it redo node limit-1 and write nothing). As in the figure less
 * its repeated evaluations: the first step of the binary search for l always
 * succeeds (the doubling passed lmax/2) and a range of length 1 needs no split
 * search. x * d is written (x ^ back) - back, back = (d < 0 ? -1 : 0). */
inline void emit_lanes(__global const key_t *keys, int n, int i0, int limit,
                       __global int *node_words, __global int *parent) {
    int8 i = i0 + (int8)(0, 1, 2, 3, 4, 5, 6, 7);
    i = blend_int(i, (int8)(limit - 1), i >= limit);
    keys_t kc, ku, kd;  /* keys i, i+1 (<= n-1) and i-1 (slot 0 for i = 0) */
    if (i0 + LANES <= limit && i0 % LANES == 0) {  /* whole aligned group: one load */
        kc = *(__global const keys_t *)(keys + i0);
        const key_t next = keys[i0 + LANES], prev = keys[i0 > 0 ? i0 - 1 : 0];
        ku = (keys_t)(kc.s1, kc.s2, kc.s3, kc.s4, kc.s5, kc.s6, kc.s7, next);
        kd = (keys_t)(prev, kc.s0, kc.s1, kc.s2, kc.s3, kc.s4, kc.s5, kc.s6);
    } else {
        kc = gather(keys, i);
        ku = gather(keys, i + 1);
        kd = gather(keys, (i - 1) & ~(i == 0));  /* slot 0 for node 0: masked below */
    }
    const prefix_t ki = concat(kc, i);
    const prefix_t up = xor_keys(ki, concat(ku, i + 1));
    const prefix_t down = or_all_ones(xor_keys(ki, concat(kd, i - 1)), i == 0);
    const int8 forward = prefix_lt(up, down);  /* d = +1 */
    const int8 back = ~forward;
    /* Node 0 has no left neighbour (delta -1): every key shares more. */
    const prefix_t mask_min = or_all_ones(below_msb(prefix_select(up, down, forward)), i == 0);
    int8 lmax = 2, going = (int8)(-1);
    for (;;) {
        going &= shares_more(keys, n, ki, i + ((lmax ^ back) - back), mask_min);
        if (!any_lane(going)) break;
        lmax = blend_int(lmax, lmax << 1, going);
    }
    int8 l = lmax >> 1;
    for (int8 t = lmax >> 2; any_lane(t >= 1); t >>= 1)
        l += t & (t >= 1) & shares_more(keys, n, ki, i + (((l + t) ^ back) - back), mask_min);
    const int8 j = i + ((l ^ back) - back);
    const prefix_t mask_node = below_msb(xor_keys(ki, concat(gather(keys, j), j)));
    int8 s = 0, t = l, open = l > 1;
    while (any_lane(open)) {
        t = (t + 1) >> 1;
        s += t & open & shares_more(keys, n, ki, i + (((s + t) ^ back) - back), mask_node);
        open &= t > 1;
    }
    const int8 gamma = i + ((s ^ back) - back) + back;
    const int8 first = blend_int(i, j, j < i), last = blend_int(j, i, j < i);
    union { int8 v; int s[LANES]; } node, left, right, far;
    node.v = i;
    far.v = j;
    left.v = blend_int(gamma, (n - 1) + gamma, first == gamma);
    right.v = blend_int(gamma + 1, n + gamma, last == gamma + 1);
    for (int k = 0; k < LANES && i0 + k < limit; ++k) {
        set_children(node_words, node.s[k], left.s[k], right.s[k]);
        node_words[8 * node.s[k]] = far.s[k];
        node_words[8 * node.s[k] + 1] = 0;  /* the build's refit counts arrivals here */
        parent[left.s[k]] = node.s[k];
        parent[right.s[k]] = node.s[k];
    }
}

/* Work-item items cover sorted slots [first, last): it writes those leaves'
 * records (WRITE_LEAVES) and emits the internal nodes of the same numbers
 * (all but n-1). */
__kernel void emit_hierarchy(__global const key_t *sorted_keys, const int n, const int per_item,
                             __global float4 *nodes, __global int *parent) {
    const int gid = get_global_id(0);
    const int first = chunk_first(gid, per_item, n);
    const int last = chunk_last(gid, per_item, n);
    __global int *node_words = (__global int *)nodes;
#if WRITE_LEAVES
    for (int j = first; j < last; ++j) set_children(node_words, (n - 1) + j, j, -1);
#endif
    if (first == 0 && last > 0) parent[0] = -1;
    const int limit = last < n - 1 ? last : n - 1;
    for (int i0 = first; i0 < limit; i0 += LANES)
        emit_lanes(sorted_keys, n, i0, limit, node_words, parent);
}
