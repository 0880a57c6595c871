/* Stage 6: bottom-up refit of the node boxes (Karras 2012, section 4,
 * "Bounding box calculation"; Apetrei 2014 does the same walk).
 *
 * One walk per leaf: the leaf's box is the union of its triangles' boxes
 * (stored by bounds.cl); then it climbs
 * towards the root. At each parent an atomic counter tells whether the sibling
 * has already arrived: the first arrival stops, the second (which then knows
 * that both children's boxes are written) computes the parent's box and goes
 * on. min and max are exact and the leaf boxes hold no -0.0 (leaf_box), so
 * the result does not depend on which walk arrives second: it is
 * bit-identical to a serial refit.
 *
 * Memory ordering: see second_arrival() in common.h; the sibling's box is
 * read through a volatile pointer so that no value cached before the atomic
 * is used, on PoCL or on a GPU.
 *
 * A work-item walks `per_item` consecutive leaves (one on a GPU). Leaves are
 * leaf_nodes[k] when use_leaf_list, else leaf_first + k (Karras numbering).
 *
 * KARRAS_RANGES (define, the build's refit): the tree comes straight from
 * emit.cl, whose internal nodes hold the far end of their range of slots in
 * the word where lower.x goes. A node whose whole range lies in this
 * work-item's chunk is reached only by this work-item's walks, which run in
 * slot order, so its counter's outcome is known in advance: the walk from the
 * left child arrives first, the one from the right child second (its left
 * sibling's last leaf came earlier in the chunk). Only nodes that straddle a
 * chunk boundary, a few dozen per chunk, pay for the atomic. On a GPU (one
 * leaf per work-item) every internal node straddles: the plain scheme.
 * The leaf records are written whole here (emit.cl ran with WRITE_LEAVES=0):
 * leaf n-1+k holds slot k alone. The arrival counter of a straddling node is
 * its own lower.y word, which emit.cl zeroed and the second arrival writes
 * the box over: no counter array, no pass to clear one.
 */
#include "common.h"

/* Leaf boxes are gathered in slot order, randomly in memory when the mesh's
 * triangles are not in spatial order: the box PREFETCH_AHEAD slots on is
 * prefetched (1.2-1.5x on a random soup of 1M triangles). OpenCL's prefetch()
 * does nothing on PoCL; CLANG_PREFETCH=1, which the host sets where the
 * compiler is clang (PoCL), uses clang's builtin instead. */

inline void store_box(__global float *node_floats, int node, float3 lo, float3 hi) {
    store_float3(node_floats + 8 * node, lo);
    store_float3(node_floats + 8 * node + 4, hi);
}

inline void load_box_volatile(volatile __global float *node_floats, int node,
                              float3 *lo, float3 *hi) {
    volatile __global float *p = node_floats + 8 * node;
    *lo = (float3)(p[0], p[1], p[2]);
    *hi = (float3)(p[4], p[5], p[6]);
}

#if KARRAS_RANGES
/* Whether internal node p's range of slots, [min(p, j), max(p, j)] with j the
 * far end that emit.cl left in its lower.x word, lies inside the chunk
 * [first, last). Read before p's box is written over it: both walks reaching
 * p read it before the second one writes. */
inline int inside_chunk(__global const int *node_words, int p, int first, int last) {
    const int far = node_words[8 * p];
    return (p < far ? p : far) >= first && (p > far ? p : far) < last;
}
#endif

/* The union of the boxes of slots [slot, slot + count), prefetching the box
 * PREFETCH_AHEAD slots on (last_slot: the highest slot), with +0.0 for -0.0. */
inline void leaf_box(__global const float4 *boxes, __global const int *prim_order, int slot,
                     int count, int last_slot, float3 *lo, float3 *hi) {
    if (slot + PREFETCH_AHEAD <= last_slot)
        PREFETCH_BOX(boxes + 2 * prim_order[slot + PREFETCH_AHEAD]);
    const int t0 = prim_order[slot];
    float3 l = boxes[2 * t0].xyz, h = boxes[2 * t0 + 1].xyz;
    for (int s = 1; s < count; ++s) {
        const int t = prim_order[slot + s];
        l = min3(l, boxes[2 * t].xyz);
        h = max3(h, boxes[2 * t + 1].xyz);
    }
    /* -0.0 + 0.0 = +0.0: min3 and max3 keep whichever of -0 and +0 comes first, so
     * with a signed zero in the leaves a node's box would depend on which child's
     * walk arrived second (the teapot's lower.z flipped sign between builds). */
    *lo = l + (float3)(0.0f);
    *hi = h + (float3)(0.0f);
}

/* The walk from `node` (box lo, hi) towards the root, as far as this walk is
 * the second to arrive at each parent. */
inline void climb(__global float *node_floats, __global const int *node_words,
                  __global const int *parent, __global int *arrivals, int first, int last,
                  int node, float3 lo, float3 hi) {
    for (;;) {
        const int p = parent[node];
        if (p < 0) break;
        const int left = node_words[8 * p + 3];
#if KARRAS_RANGES
        if (inside_chunk(node_words, p, first, last)) {
            if (left == node) break;
        } else if (!second_arrival((__global int *)node_floats, 8 * p + 1)) {
            break;  /* the counter is p's lower.y word, zeroed by emit.cl */
        }
#else
        if (!second_arrival(arrivals, p)) break;
#endif
        const int sibling = left == node ? node_words[8 * p + 7] : left;
        float3 slo, shi;
        load_box_volatile(node_floats, sibling, &slo, &shi);
        lo = min3(lo, slo);
        hi = max3(hi, shi);
        store_box(node_floats, p, lo, hi);
        node = p;
    }
}

__kernel void refit(__global const float4 *boxes /* lo, hi per triangle (bounds.cl) */,
                    __global const int *prim_order, __global float4 *nodes,
                    __global const int *parent, __global int *arrivals,
                    __global const int *leaf_nodes, const int use_leaf_list,
                    const int leaf_first, const int num_leaves, const int per_item) {
    const int gid = get_global_id(0);
    const int first = chunk_first(gid, per_item, num_leaves);
    const int last = chunk_last(gid, per_item, num_leaves);
    __global float *node_floats = (__global float *)nodes;
    __global const int *node_words = (__global const int *)nodes;
#if KARRAS_RANGES
    /* Each leaf's box, then its walk, leaf after leaf: the box stays in
     * registers for the walk and the sibling boxes the walk reads were
     * mostly written a few leaves before, still in cache. Atomics are rare
     * here (nodes straddling a chunk boundary), so they do not stall the
     * prefetched gathers much. */
    for (int k = first; k < last; ++k) {
        int node = leaf_first + k;  /* leaf k holds slot k alone (emit.cl, WRITE_LEAVES=0) */
        float3 lo, hi;
        leaf_box(boxes, prim_order, k, 1, leaf_first, &lo, &hi);
        nodes[2 * node] = (float4)(lo, as_float(k));
        nodes[2 * node + 1] = (float4)(hi, as_float(-1));
        climb(node_floats, node_words, parent, arrivals, first, last, node, lo, hi);
    }
#else
    /* Leaf boxes first, for the whole chunk: the gathers are independent of
     * each other, so the core overlaps their cache misses; in the walks below,
     * every atomic is a full barrier that would stall each gather in turn. */
    for (int k = first; k < last; ++k) {
        const int node = use_leaf_list ? leaf_nodes[k] : leaf_first + k;
        float3 lo, hi;
        leaf_box(boxes, prim_order, node_words[8 * node + 3], -node_words[8 * node + 7],
                 leaf_first, &lo, &hi);
        store_box(node_floats, node, lo, hi);
    }
    for (int k = first; k < last; ++k) {
        const int node = use_leaf_list ? leaf_nodes[k] : leaf_first + k;
        float3 lo, hi;
        load_box_volatile(node_floats, node, &lo, &hi);
        climb(node_floats, node_words, parent, arrivals, first, last, node, lo, hi);
    }
#endif
}

/* The arrival counters start at zero (a kernel: PoCL's buffer fill is slower). */
__kernel void clear_arrivals(__global int *arrivals, const int count, const int per_item) {
    const int gid = get_global_id(0);
    const int last = chunk_last(gid, per_item, count);
    for (int i = chunk_first(gid, per_item, count); i < last; ++i) arrivals[i] = 0;
}
