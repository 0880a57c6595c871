/* Box queries: the triangles whose boxes overlap each query box
 * (lbvh/queries/overlap.py).
 *
 * A depth-first traversal of the binary nodes (docs/layout.md) enters a node
 * whose box overlaps the query box (closed boxes: touching counts), and at the
 * leaves tests each triangle's own box, the min and max of its three vertices.
 * Every comparison is of float32 values as they are, with no arithmetic, so the
 * answer is exact: a node's box holds its triangles' boxes exactly (the refit
 * takes the same min and max), and pruning never drops an overlapping triangle.
 *
 * Two passes over the same traversal: COUNT=1 writes how many triangles each
 * query box overlaps; COUNT=0 writes their original indices from offsets[i]
 * on (the host's prefix sum of the counts).
 *
 * Defines:
 *   STACK_SIZE=n  stack entries; a push beyond n sets FLAG_OVERFLOW and skips
 *                 that subtree (the host sizes it from the tree's depth).
 *   COUNT=0|1     the pass.
 */
#include "common.h"

#ifndef STACK_SIZE
#define STACK_SIZE 64
#endif

#define FLAG_OVERFLOW 1

inline int boxes_overlap(float3 alo, float3 ahi, float3 blo, float3 bhi) {
    return alo.x <= bhi.x && blo.x <= ahi.x && alo.y <= bhi.y && blo.y <= ahi.y &&
           alo.z <= bhi.z && blo.z <= ahi.z;
}

__kernel void overlapping(__global const float4 *nodes, __global const int *prim_order,
                          __global const float *vertices, __global const uint *slot_faces,
                          const int root, const int num_nodes, __global const float *lower,
                          __global const float *upper, const int count,
                          __global const long *offsets, __global int *counts_or_prims,
                          __global int *flags) {
    const int i = get_global_id(0);
    if (i >= count) return;
    const float3 qlo = load_float3(lower, i), qhi = load_float3(upper, i);
    long found = 0;
#if !COUNT
    const long first = offsets[i];
#endif
    int flag = 0;
    int stack[STACK_SIZE];
    int top = 0;
    int node = boxes_overlap(nodes[2 * root].xyz, nodes[2 * root + 1].xyz, qlo, qhi) ? root : -1;
    int visits = 0;
    for (;;) {
        if (node >= 0 && visits++ < num_nodes) {
            const float4 lo = nodes[2 * node], hi = nodes[2 * node + 1];
            const int a = as_int(lo.w), b = as_int(hi.w);
            if (node_is_leaf(b)) {
                for (int s = a; s < a - b; ++s) {
                    const float3 p0 = load_float3(vertices, slot_faces[3 * s]);
                    const float3 p1 = load_float3(vertices, slot_faces[3 * s + 1]);
                    const float3 p2 = load_float3(vertices, slot_faces[3 * s + 2]);
                    if (boxes_overlap(min3(min3(p0, p1), p2), max3(max3(p0, p1), p2), qlo, qhi)) {
#if !COUNT
                        counts_or_prims[first + found] = prim_order[s];
#endif
                        ++found;
                    }
                }
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
#if COUNT
    counts_or_prims[i] = (int)found;
#endif
    flags[i] = flag;
}
