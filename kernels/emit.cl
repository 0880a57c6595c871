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
 *   on the CPU device. On a GPU a work-item takes one node (LANES 1, below).
 *
 * Numbering (docs/pages/layout.md): internal node i is node i, leaf j is node n-1+j
 * and holds sorted slot j. Parent links are written by the parent. The far
 * end j of node i's range goes where its lower.x will be, and a zero where
 * its lower.y will be: the build's refit (refit.cl, KARRAS_RANGES) reads the
 * one, counts the arrivals at the node in the other, and writes the box over
 * both.
 *
 * KEY_BITS (define): 32 or 64.
 * LANES (define, default 8): 8 for the explicit vectors above (the CPU), 1 for
 * one node per work-item in plain scalar code (a GPU, where each work-item is
 * a SIMT lane already). On an NVIDIA H200 the vector form emitted 2% of the
 * bunny's nodes wrong, in lanes 2, 3, 6 and 7 only, while PoCL's are right:
 * the scalar form is Figure 4 as written, with nothing for a GPU compiler to
 * get wrong in eight-wide vectors it would split anyway.
 * WRITE_LEAVES (define, default 1): 0 leaves the leaf records alone; the
 * build's refit (refit.cl, KARRAS_RANGES) writes them whole with their boxes,
 * which spares a pass over half the node array (about 10% of the emission).
 */
#include "common.h"

#ifndef WRITE_LEAVES
#define WRITE_LEAVES 1
#endif

#ifndef LANES
#define LANES 8
#endif
#if LANES != 8 && LANES != 1
#error "LANES must be 8 or 1"
#endif

#if KEY_BITS == 64
typedef ulong key_t;
#else
typedef uint key_t;
#endif

inline void set_children(__global int *node_words, int node, int a, int b) {
    node_words[8 * node + 3] = a;  /* lower.w */
    node_words[8 * node + 7] = b;  /* upper.w */
}

#if LANES == 1
/* One node per work-item: Karras 2012, Figure 4, on the concatenation
 * K = key . slot compared as the pair (key xor, slot xor), the same prefix
 * comparisons as the vector form (x_j <= below_msb(x_m)). */
typedef struct { key_t k; uint s; } kxor_t;  /* K_i xor K_j: at most 16 bytes */

inline kxor_t xor_with(__global const key_t *keys, int i, int j) {
    kxor_t x;
    x.k = keys[i] ^ keys[j];
    x.s = (uint)i ^ (uint)j;
    return x;
}
inline kxor_t all_ones(void) {
    kxor_t x;
    x.k = ~(key_t)0;
    x.s = ~0u;
    return x;
}
/* 2^msb(x) - 1 of the pair taken as one number (key above slot). */
inline kxor_t below_msb_pair(kxor_t x) {
    if (x.k != 0) {
        key_t k = x.k;
        k |= k >> 1; k |= k >> 2; k |= k >> 4; k |= k >> 8; k |= k >> 16;
#if KEY_BITS == 64
        k |= k >> 32;
#endif
        x.k = k >> 1;
        x.s = ~0u;
    } else {
        uint v = x.s;
        v |= v >> 1; v |= v >> 2; v |= v >> 4; v |= v >> 8; v |= v >> 16;
        x.s = v >> 1;
    }
    return x;
}
inline int pair_le(kxor_t a, kxor_t b) { return a.k < b.k || (a.k == b.k && a.s <= b.s); }
inline int pair_lt(kxor_t a, kxor_t b) { return a.k < b.k || (a.k == b.k && a.s < b.s); }

/* delta(i, j) > delta(i, m), given mask = below_msb(x_m); false outside [0, n). */
inline int shares_more_one(__global const key_t *keys, int n, int i, int j, kxor_t mask) {
    return j >= 0 && j < n && pair_le(xor_with(keys, i, j), mask);
}

inline void emit_node(__global const key_t *keys, int n, int i, __global int *node_words,
                      __global int *parent) {
    const kxor_t up = xor_with(keys, i, i + 1);
    const kxor_t down = i == 0 ? all_ones() : xor_with(keys, i, i - 1);
    const int d = pair_lt(up, down) ? 1 : -1;
    /* delta_min = delta(i, i - d); node 0 has no left neighbour: every key shares more. */
    const kxor_t mask_min = i == 0 ? all_ones() : below_msb_pair(d > 0 ? down : up);
    int lmax = 2;
    while (shares_more_one(keys, n, i, i + lmax * d, mask_min)) lmax <<= 1;
    int l = lmax >> 1;  /* the first step of the binary search always succeeds */
    for (int t = lmax >> 2; t >= 1; t >>= 1)
        if (shares_more_one(keys, n, i, i + (l + t) * d, mask_min)) l += t;
    const int j = i + l * d;
    const kxor_t mask_node = below_msb_pair(xor_with(keys, i, j));
    int s = 0, t = l;
    while (t > 1) {
        t = (t + 1) >> 1;
        if (shares_more_one(keys, n, i, i + (s + t) * d, mask_node)) s += t;
    }
    const int gamma = i + s * d + (d < 0 ? -1 : 0);
    const int first = j < i ? j : i, last = j < i ? i : j;
    const int left = first == gamma ? (n - 1) + gamma : gamma;
    const int right = last == gamma + 1 ? n + gamma : gamma + 1;
    set_children(node_words, i, left, right);
    node_words[8 * i] = j;
    node_words[8 * i + 1] = 0;  /* the build's refit counts arrivals here */
    parent[left] = i;
    parent[right] = i;
}

#else  /* LANES == 8 */
/* No value wider than 32 bytes crosses a function boundary, by construction.
 * PoCL 3.0 compiles with -Dinline= (every helper here is an ordinary function
 * that may stay out of line), and on a CPU newer than its LLVM (AMD Zen 4) it
 * compiles for a CPU without AVX-512 while its built-in library is built with
 * it: built-ins are then called out of line, and the two sides pass a 64-byte
 * vector differently (two ymm registers against one zmm), so the lanes arrive
 * as garbage (clang: "AVX vector argument of type 'ulong8' without 'avx512f'
 * enabled changes the ABI"). Lanes of 32-bit values go as int8 and uint8 (32
 * bytes); lanes of 64-bit values are kept as two ulong4 halves (lanes 0-3 in
 * .lo, 4-7 in .hi) and converted half by half; the prefixes (64 or 96 bytes)
 * go through pointers to private memory. On the CPU device this is as fast as
 * the ulong8 form was, and faster than ulong8 inside the functions with
 * 512-bit vectors asked of clang (morton.cl's WIDE_VECTORS: 15% slower here). */

/* Lane masks are 0 or -1. select() and any() are written out because PoCL 3
 * calls both out of line. */
inline int8 blend_int(int8 a, int8 b, int8 m) { return (a & ~m) | (b & m); }
inline uint8 blend_uint(uint8 a, uint8 b, int8 m) { return (a & ~as_uint8(m)) | (b & as_uint8(m)); }
inline ulong4 wide_mask(int4 m) { return as_ulong4(convert_long4(m)); }
inline ulong4 blend_ulong(ulong4 a, ulong4 b, int4 m) {
    const ulong4 w = wide_mask(m);
    return (a & ~w) | (b & w);
}
/* The lane mask of the masks of two ulong4 comparisons (lanes 0-3, 4-7). */
inline int8 lane_mask(long4 lo, long4 hi) { return (int8)(convert_int4(lo), convert_int4(hi)); }
inline int any_lane(int8 m) {
    const int4 h = m.lo | m.hi;
    const int2 q = h.lo | h.hi;
    return (q.x | q.y) != 0;
}

/* K = key . slot per lane, and the operations the searches need on it, in
 * place or into the first argument. gather(p, keys, j): p = K_j.
 * or_all_ones(p, m): all ones where m is set, the largest xor ("no neighbour"). */
#if KEY_BITS == 64
typedef struct { ulong4 lo, hi; uint8 slot; } prefix_t;  /* 96 bits, compared as (key, slot) */
inline void gather(prefix_t *p, __global const key_t *keys, int8 j) {
    p->lo = (ulong4)(keys[j.s0], keys[j.s1], keys[j.s2], keys[j.s3]);
    p->hi = (ulong4)(keys[j.s4], keys[j.s5], keys[j.s6], keys[j.s7]);
    p->slot = as_uint8(j);
}
/* K_i, K_{i+1} and K_{i-1} of a whole aligned group i = i0 .. i0+LANES-1:
 * one vector load. */
inline void load_group(prefix_t *kc, prefix_t *ku, prefix_t *kd, __global const key_t *keys,
                       int i0, int8 i) {
    const ulong4 lo = *(__global const ulong4 *)(keys + i0);
    const ulong4 hi = *(__global const ulong4 *)(keys + i0 + LANES / 2);
    const key_t next = keys[i0 + LANES], prev = keys[i0 > 0 ? i0 - 1 : 0];
    kc->lo = lo;
    kc->hi = hi;
    kc->slot = as_uint8(i);
    ku->lo = (ulong4)(lo.s1, lo.s2, lo.s3, hi.s0);
    ku->hi = (ulong4)(hi.s1, hi.s2, hi.s3, next);
    ku->slot = as_uint8(i + 1);
    kd->lo = (ulong4)(prev, lo.s0, lo.s1, lo.s2);
    kd->hi = (ulong4)(lo.s3, hi.s0, hi.s1, hi.s2);
    kd->slot = as_uint8(i - 1);
}
inline void xor_keys(prefix_t *p, const prefix_t *a, const prefix_t *b) {
    p->lo = a->lo ^ b->lo;
    p->hi = a->hi ^ b->hi;
    p->slot = a->slot ^ b->slot;
}
inline int8 prefix_le(const prefix_t *a, const prefix_t *b) {
    const int8 s = a->slot <= b->slot;
    return lane_mask((a->lo < b->lo) | ((a->lo == b->lo) & convert_long4(s.lo)),
                     (a->hi < b->hi) | ((a->hi == b->hi) & convert_long4(s.hi)));
}
inline int8 prefix_lt(const prefix_t *a, const prefix_t *b) {
    const int8 s = a->slot < b->slot;
    return lane_mask((a->lo < b->lo) | ((a->lo == b->lo) & convert_long4(s.lo)),
                     (a->hi < b->hi) | ((a->hi == b->hi) & convert_long4(s.hi)));
}
inline void prefix_select(prefix_t *p, const prefix_t *a, const prefix_t *b, int8 m) {
    p->lo = blend_ulong(a->lo, b->lo, m.lo);
    p->hi = blend_ulong(a->hi, b->hi, m.hi);
    p->slot = blend_uint(a->slot, b->slot, m);
}
inline void or_all_ones(prefix_t *p, int8 m) {
    p->lo |= wide_mask(m.lo);
    p->hi |= wide_mask(m.hi);
    p->slot |= as_uint8(m);
}
#else
typedef struct { ulong4 lo, hi; } prefix_t;  /* key << 32 | slot */
inline void concat(prefix_t *p, uint8 k, int8 j) {
    p->lo = (convert_ulong4(k.lo) << 32) | convert_ulong4(as_uint4(j.lo));
    p->hi = (convert_ulong4(k.hi) << 32) | convert_ulong4(as_uint4(j.hi));
}
inline void gather(prefix_t *p, __global const key_t *keys, int8 j) {
    concat(p, (uint8)(keys[j.s0], keys[j.s1], keys[j.s2], keys[j.s3],
                      keys[j.s4], keys[j.s5], keys[j.s6], keys[j.s7]), j);
}
/* K_i, K_{i+1} and K_{i-1} of a whole aligned group i = i0 .. i0+LANES-1:
 * one vector load. */
inline void load_group(prefix_t *kc, prefix_t *ku, prefix_t *kd, __global const key_t *keys,
                       int i0, int8 i) {
    const uint8 k = *(__global const uint8 *)(keys + i0);
    const key_t next = keys[i0 + LANES], prev = keys[i0 > 0 ? i0 - 1 : 0];
    concat(kc, k, i);
    concat(ku, (uint8)(k.s1, k.s2, k.s3, k.s4, k.s5, k.s6, k.s7, next), i + 1);
    concat(kd, (uint8)(prev, k.s0, k.s1, k.s2, k.s3, k.s4, k.s5, k.s6), i - 1);
}
inline void xor_keys(prefix_t *p, const prefix_t *a, const prefix_t *b) {
    p->lo = a->lo ^ b->lo;
    p->hi = a->hi ^ b->hi;
}
inline int8 prefix_le(const prefix_t *a, const prefix_t *b) {
    return lane_mask(a->lo <= b->lo, a->hi <= b->hi);
}
inline int8 prefix_lt(const prefix_t *a, const prefix_t *b) {
    return lane_mask(a->lo < b->lo, a->hi < b->hi);
}
inline void prefix_select(prefix_t *p, const prefix_t *a, const prefix_t *b, int8 m) {
    p->lo = blend_ulong(a->lo, b->lo, m.lo);
    p->hi = blend_ulong(a->hi, b->hi, m.hi);
}
inline void or_all_ones(prefix_t *p, int8 m) {
    p->lo |= wide_mask(m.lo);
    p->hi |= wide_mask(m.hi);
}
#endif

/* 2^msb(x) - 1: the xors below it share more leading bits than x does. */
inline ulong4 below_msb64(ulong4 x) {
    x |= x >> 1; x |= x >> 2; x |= x >> 4; x |= x >> 8; x |= x >> 16; x |= x >> 32;
    return x >> 1;
}
#if KEY_BITS == 64
inline uint8 below_msb32(uint8 x) {
    x |= x >> 1; x |= x >> 2; x |= x >> 4; x |= x >> 8; x |= x >> 16;
    return x >> 1;
}
inline void below_msb(prefix_t *p) {
    p->slot = blend_uint(below_msb32(p->slot), (uint8)(~0u), lane_mask(p->lo != 0, p->hi != 0));
    p->lo = below_msb64(p->lo);
    p->hi = below_msb64(p->hi);
}
#else
inline void below_msb(prefix_t *p) {
    p->lo = below_msb64(p->lo);
    p->hi = below_msb64(p->hi);
}
#endif

/* delta(i, j) > delta(i, m) per lane, given mask = below_msb(x_m); false where
 * j is outside [0, n) (delta -1). */
inline int8 shares_more(__global const key_t *keys, int n, const prefix_t *ki, int8 j,
                        const prefix_t *mask) {
    const int8 valid = as_uint8(j) < (uint)n;
    prefix_t x;
    gather(&x, keys, j & valid);
    xor_keys(&x, ki, &x);
    return valid & prefix_le(&x, mask);
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
    prefix_t ki, up, down;  /* K_i, then its xors with K_{i+1} (i+1 <= n-1) and K_{i-1} */
    if (i0 + LANES <= limit && i0 % LANES == 0) {  /* whole aligned group: one load */
        load_group(&ki, &up, &down, keys, i0, i);
    } else {
        gather(&ki, keys, i);
        gather(&up, keys, i + 1);
        gather(&down, keys, (i - 1) & ~(i == 0));  /* slot 0 for node 0: masked below */
    }
    xor_keys(&up, &ki, &up);
    xor_keys(&down, &ki, &down);
    or_all_ones(&down, i == 0);
    const int8 forward = prefix_lt(&up, &down);  /* d = +1 */
    const int8 back = ~forward;
    /* Node 0 has no left neighbour (delta -1): every key shares more. */
    prefix_t mask_min;
    prefix_select(&mask_min, &up, &down, forward);
    below_msb(&mask_min);
    or_all_ones(&mask_min, i == 0);
    int8 lmax = 2, going = (int8)(-1);
    for (;;) {
        going &= shares_more(keys, n, &ki, i + ((lmax ^ back) - back), &mask_min);
        if (!any_lane(going)) break;
        lmax = blend_int(lmax, lmax << 1, going);
    }
    int8 l = lmax >> 1;
    for (int8 t = lmax >> 2; any_lane(t >= 1); t >>= 1)
        l += t & (t >= 1) & shares_more(keys, n, &ki, i + (((l + t) ^ back) - back), &mask_min);
    const int8 j = i + ((l ^ back) - back);
    prefix_t mask_node;
    gather(&mask_node, keys, j);
    xor_keys(&mask_node, &ki, &mask_node);
    below_msb(&mask_node);
    int8 s = 0, t = l, open = l > 1;
    while (any_lane(open)) {
        t = (t + 1) >> 1;
        s += t & open & shares_more(keys, n, &ki, i + (((s + t) ^ back) - back), &mask_node);
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

#endif  /* LANES */

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
#if LANES == 1
    for (int i = first; i < limit; ++i) emit_node(sorted_keys, n, i, node_words, parent);
#else
    for (int i0 = first; i0 < limit; i0 += LANES)
        emit_lanes(sorted_keys, n, i0, limit, node_words, parent);
#endif
}
