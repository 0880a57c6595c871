/* Box queries: the triangles whose boxes overlap each query box
 * (lbvh/queries/overlap.py).
 *
 * A depth-first traversal of the binary nodes (docs/pages/layout.md) enters a node
 * whose box overlaps the query box (closed boxes: touching counts), and at the
 * leaves tests each triangle's own box, the min and max of its three vertices.
 * Every comparison is of float32 values as they are, with no arithmetic, so the
 * answer is exact: a node's box holds its triangles' boxes exactly (the refit
 * takes the same min and max), and pruning never drops an overlapping triangle.
 *
 * Two passes over the same traversal: COUNT=1 writes how many triangles each
 * query box overlaps; COUNT=0 writes their original indices from offsets[i]
 * on (the host's prefix sum of the counts), in ascending order (sort_prims).
 *
 * Defines:
 *   STACK_SIZE=n  stack entries; a push beyond n sets FLAG_OVERFLOW and skips
 *                 that subtree (the host sizes it from the tree's depth).
 *   COUNT=0|1     the pass.
 *   WIDE=1        walk the tree's wide records (kernels/wide.cl: `records`, the
 *                 root's reference (root_x, root_y)), all WIDTH lanes of a
 *                 record compared with the query box at once, instead of its
 *                 binary nodes: the same comparisons of the same floats.
 */
#include "common.h"

#ifndef STACK_SIZE
#define STACK_SIZE 64
#endif
#ifndef WIDE
#define WIDE 0
#endif
#if WIDE
#include "wide_rows.h"
#endif

#define FLAG_OVERFLOW 1

/* prims[first, first + n) in ascending order, in place: a heapsort (Williams
 * 1964), O(n log n) however many triangles a box overlaps. */
inline void sort_prims(__global int *prims, long first, long n) {
    for (long end = n; end > 0; --end) {
        for (long start = end == n ? n / 2 - 1 : 0; start >= 0; --start) {
            long root = start;
            for (;;) {
                long child = 2 * root + 1;
                if (child >= end) break;
                if (child + 1 < end && prims[first + child] < prims[first + child + 1]) ++child;
                if (prims[first + root] >= prims[first + child]) break;
                const int t = prims[first + root];
                prims[first + root] = prims[first + child];
                prims[first + child] = t;
                root = child;
            }
            if (end != n) break;
        }
        const int t = prims[first];
        prims[first] = prims[first + end - 1];
        prims[first + end - 1] = t;
    }
}

inline int boxes_overlap(float3 alo, float3 ahi, float3 blo, float3 bhi) {
    return alo.x <= bhi.x && blo.x <= ahi.x && alo.y <= bhi.y && blo.y <= ahi.y &&
           alo.z <= bhi.z && blo.z <= ahi.z;
}

/* The triangles of slots [s0, s0 + n) whose own boxes overlap the query box:
 * counted in *found, their original indices written from `first` (COUNT=0). */
inline void leaf_overlaps(__global const int *prim_order, __global const float *vertices,
                          __global const uint *slot_faces, int s0, int n, float3 qlo, float3 qhi,
                          long first, __global int *prims, long *found) {
    for (int s = s0; s < s0 + n; ++s) {
        const float3 p0 = load_float3(vertices, slot_faces[3 * s]);
        const float3 p1 = load_float3(vertices, slot_faces[3 * s + 1]);
        const float3 p2 = load_float3(vertices, slot_faces[3 * s + 2]);
        if (boxes_overlap(min3(min3(p0, p1), p2), max3(max3(p0, p1), p2), qlo, qhi)) {
#if !COUNT
            prims[first + *found] = prim_order[s];
#endif
            ++*found;
        }
    }
}

#if WIDE
/* The walk through the tree's wide records (kernels/wide.cl): references (x, y)
 * as kernels/traverse.cl takes them (a leaf's node words, or (record, 0)), from
 * the root's (root_x, root_y); at a record every lane whose box overlaps the
 * query box (all lanes compared at once) is entered: the first followed, the
 * others pushed. */
inline void wide_overlaps(__global const float *records, __global const int *prim_order,
                          __global const float *vertices, __global const uint *slot_faces,
                          int root_x, int root_y, int num_nodes, float3 qlo, float3 qhi,
                          long first, __global int *prims, long *found, int *flag) {
    __global const int *words = (__global const int *)records;
    const floatw lx = (floatw)(qlo.x), ly = (floatw)(qlo.y), lz = (floatw)(qlo.z);
    const floatw hx = (floatw)(qhi.x), hy = (floatw)(qhi.y), hz = (floatw)(qhi.z);
    int stack_x[STACK_SIZE], stack_y[STACK_SIZE];
    int top = 0, visits = 0, x = root_x, y = root_y;
    for (;;) {
        if (++visits > num_nodes) break;
        if (node_is_leaf(y)) {
            leaf_overlaps(prim_order, vertices, slot_faces, x, -y, qlo, qhi, first, prims, found);
        } else {
            __global const floatw *row = (__global const floatw *)records + 8 * x;
            intw_lanes lanes;
            lanes.v = (row[0] <= hx) & (lx <= row[1]) & (row[2] <= hy) & (ly <= row[3]) &
                      (row[4] <= hz) & (lz <= row[5]);
            __global const int *ref = words + 8 * WIDTH * x + 6 * WIDTH;
            if (enter_lanes(&lanes, ref, stack_x, stack_y, STACK_SIZE, &top, flag,
                            FLAG_OVERFLOW, &x, &y))
                continue;
        }
        if (!pop_lane(stack_x, stack_y, &top, &x, &y)) break;
    }
}
#endif

__kernel void overlapping(__global const float4 *nodes, __global const float *records,
                          __global const int *prim_order,
                          __global const float *vertices, __global const uint *slot_faces,
                          const int root, const int root_x, const int root_y, const int num_nodes,
                          __global const float *lower, __global const float *upper,
                          const int count, __global const long *offsets,
                          __global int *counts_or_prims, __global int *flags) {
    const int i = get_global_id(0);
    if (i >= count) return;
    const float3 qlo = load_float3(lower, i), qhi = load_float3(upper, i);
    long found = 0;
#if COUNT
    const long first = 0;
#else
    const long first = offsets[i];
#endif
    int flag = 0;
    int visits = 0;
    const int in_root = boxes_overlap(nodes[2 * root].xyz, nodes[2 * root + 1].xyz, qlo, qhi);
#if WIDE
    if (in_root)
        wide_overlaps(records, prim_order, vertices, slot_faces, root_x, root_y, num_nodes, qlo,
                      qhi, first, counts_or_prims, &found, &flag);
#else
    int stack[STACK_SIZE];
    int top = 0;
    int node = in_root ? root : -1;
    for (;;) {
        if (node >= 0 && visits++ < num_nodes) {
            const float4 lo = nodes[2 * node], hi = nodes[2 * node + 1];
            const int a = as_int(lo.w), b = as_int(hi.w);
            if (node_is_leaf(b)) {
                leaf_overlaps(prim_order, vertices, slot_faces, a, -b, qlo, qhi, first,
                              counts_or_prims, &found);
                node = -1;
            } else {
                const int in_a = boxes_overlap(nodes[2 * a].xyz, nodes[2 * a + 1].xyz, qlo, qhi);
                const int in_b = boxes_overlap(nodes[2 * b].xyz, nodes[2 * b + 1].xyz, qlo, qhi);
                if (in_a && in_b) {
                    if (top < STACK_SIZE) stack[top++] = b;
                    else flag |= FLAG_OVERFLOW;
                }
                node = in_a ? a : (in_b ? b : -1);
            }
            continue;
        }
        if (top == 0) break;
        node = stack[--top];
    }
#endif
#if COUNT
    counts_or_prims[i] = (int)found;
#else
    sort_prims(counts_or_prims, first, found);
#endif
    flags[i] = flag;
}
