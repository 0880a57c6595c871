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
 * keys"): delta over the concatenation key . index, i.e. KEY_BITS + clz(i ^ j),
 * so the tree is valid whatever the input.
 *
 * Numbering (docs/layout.md): internal node i is node i, leaf j is node n-1+j
 * and holds sorted slot j. Parent links are written by the parent. The far
 * end j of node i's range goes where its lower.x will be: the build's refit
 * reads it (refit.cl, KARRAS_RANGES) and writes the box over it.
 *
 * KEY_BITS (define): 32 or 64. CLZ_BUILTIN (define): see clz_key below.
 */
#include "common.h"

#if KEY_BITS == 64
typedef ulong key_t;
#else
typedef uint key_t;
#endif

/* Count of leading zeros. PoCL 3 calls OpenCL's clz out of line, a call and a
 * stack frame about ten times per node: a quarter of this kernel's time.
 * CLZ_BUILTIN=1 uses clang's builtin instead (one instruction); the host sets
 * it only where a build with it succeeds (lbvh/emit.py). min and max are
 * written out for the same reason. */
#if CLZ_BUILTIN
inline int clz_index(uint x) { return x ? __builtin_clz(x) : 32; }
#if KEY_BITS == 64
inline int clz_key(key_t x) { return x ? __builtin_clzl(x) : 64; }
#else
inline int clz_key(key_t x) { return clz_index(x); }
#endif
#else
inline int clz_index(uint x) { return (int)clz(x); }
inline int clz_key(key_t x) { return (int)clz(x); }
#endif
inline int imin(int a, int b) { return a < b ? a : b; }
inline int imax(int a, int b) { return a > b ? a : b; }

inline int common_prefix(__global const key_t *keys, int n, key_t ki, int i, int j) {
    if ((uint)j >= (uint)n) return -1;  /* j < 0 or j >= n */
    const key_t kj = keys[j];
    if (ki != kj) return clz_key(ki ^ kj);
    return KEY_BITS + clz_index((uint)(i ^ j));
}

inline void set_children(__global int *node_words, int node, int a, int b) {
    node_words[8 * node + 3] = a;  /* lower.w */
    node_words[8 * node + 7] = b;  /* upper.w */
}

/* Figure 4 of Karras 2012, with the prefix lengths the figure computes twice
 * not evaluated again (same tree, about a quarter fewer instructions):
 * delta_min is one of the two neighbours' prefixes; the first step of the
 * binary search for l always succeeds (the doubling passed lmax/2); a range
 * of length 1 needs no split search (its split is 0). */
inline void emit_internal(__global const key_t *keys, int n, int i,
                          __global int *node_words, __global int *parent) {
    const key_t ki = keys[i];
    const int up = common_prefix(keys, n, ki, i, i + 1);
    const int down = common_prefix(keys, n, ki, i, i - 1);
    /* Direction of the range: towards the neighbour sharing the longer prefix
     * (the two are never equal for distinct keys.index). */
    const int d = up > down ? 1 : -1;
    const int delta_min = d > 0 ? down : up;
    /* Upper bound on the range length by doubling, then the exact length. */
    int lmax = 2;
    while (common_prefix(keys, n, ki, i, i + lmax * d) > delta_min) lmax *= 2;
    int l = lmax / 2;
    for (int t = lmax / 4; t >= 1; t /= 2)
        if (common_prefix(keys, n, ki, i, i + (l + t) * d) > delta_min) l += t;
    const int j = i + l * d;
    /* Split: the highest position where the range's common prefix grows. */
    int s = 0;
    if (l > 1) {
        const int delta_node = common_prefix(keys, n, ki, i, j);
        int t = l;
        do {
            t = (t + 1) / 2;
            if (common_prefix(keys, n, ki, i, i + (s + t) * d) > delta_node) s += t;
        } while (t > 1);
    }
    const int gamma = i + s * d + imin(d, 0);
    const int left = imin(i, j) == gamma ? (n - 1) + gamma : gamma;
    const int right = imax(i, j) == gamma + 1 ? (n - 1) + gamma + 1 : gamma + 1;
    set_children(node_words, i, left, right);
    node_words[8 * i] = j;
    parent[left] = i;
    parent[right] = i;
}

/* Work-item items cover sorted slots j: it writes leaf j's record and, for
 * j < n-1, emits internal node j. */
__kernel void emit_hierarchy(__global const key_t *sorted_keys, const int n, const int per_item,
                             __global float4 *nodes, __global int *parent) {
    const int gid = get_global_id(0);
    const int first = chunk_first(gid, per_item, n);
    const int last = chunk_last(gid, per_item, n);
    __global int *node_words = (__global int *)nodes;
    for (int j = first; j < last; ++j) {
        set_children(node_words, (n - 1) + j, j, -1);
        if (j == 0) parent[0] = -1;
        if (j < n - 1) emit_internal(sorted_keys, n, j, node_words, parent);
    }
}
