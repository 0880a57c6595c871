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
 * and holds sorted slot j. Parent links are written by the parent.
 *
 * KEY_BITS (define): 32 or 64.
 */
#include "common.h"

#if KEY_BITS == 64
typedef ulong key_t;
#else
typedef uint key_t;
#endif

inline int common_prefix(__global const key_t *keys, int n, int i, int j) {
    if (j < 0 || j >= n) return -1;
    key_t ki = keys[i], kj = keys[j];
    if (ki != kj) return (int)clz(ki ^ kj);
    return KEY_BITS + (int)clz((uint)(i ^ j));
}

inline void set_children(__global int *node_words, int node, int a, int b) {
    node_words[8 * node + 3] = a;  /* lower.w */
    node_words[8 * node + 7] = b;  /* upper.w */
}

inline void emit_internal(__global const key_t *keys, int n, int i,
                          __global int *node_words, __global int *parent) {
    /* Direction of the range from the neighbouring prefixes. */
    const int d = common_prefix(keys, n, i, i + 1) - common_prefix(keys, n, i, i - 1) >= 0 ? 1 : -1;
    const int delta_min = common_prefix(keys, n, i, i - d);
    /* Upper bound on the range length by doubling, then the exact length. */
    int lmax = 2;
    while (common_prefix(keys, n, i, i + lmax * d) > delta_min) lmax *= 2;
    int l = 0;
    for (int t = lmax / 2; t >= 1; t /= 2)
        if (common_prefix(keys, n, i, i + (l + t) * d) > delta_min) l += t;
    const int j = i + l * d;
    /* Split: the highest position where the range's common prefix grows. */
    const int delta_node = common_prefix(keys, n, i, j);
    int s = 0;
    int t = l;
    do {
        t = (t + 1) / 2;
        if (common_prefix(keys, n, i, i + (s + t) * d) > delta_node) s += t;
    } while (t > 1);
    const int gamma = i + s * d + min(d, 0);
    const int left = min(i, j) == gamma ? (n - 1) + gamma : gamma;
    const int right = max(i, j) == gamma + 1 ? (n - 1) + gamma + 1 : gamma + 1;
    set_children(node_words, i, left, right);
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
