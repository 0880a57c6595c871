/* Closest points on the mesh: for each query point, the nearest point of the
 * nearest triangle within max_distance (lbvh/queries/closest.py).
 *
 * Traversal: best first over the binary nodes (docs/layout.md). A node is
 * entered only if the squared distance from the point to its box is below the
 * best squared distance found so far; of two children the nearer is visited
 * first and the farther pushed with its box distance, which is compared again
 * when it is popped (a branch-and-bound search, as in Ericson 2005, 6.1).
 *
 * Point-triangle distance (kernels/closest_point.h, which
 * kernels/instance_closest.cl shares): Ericson 2005, Real-Time Collision Detection,
 * section 5.1.5 (ClosestPtPointTriangle): the Voronoi region of the point
 * (three vertices, three edges, the face) is found from six dot products, and
 * the closest point is a vertex, the projection on an edge, or the projection
 * on the plane in barycentric form. Two safeguards make it hold on any
 * triangle: the face's barycentrics are clamped into the triangle, and the
 * answer is the nearer of that point and the nearest point of the three
 * edges as segments (Ericson 5.1.2), so every candidate lies on the triangle
 * and a sliver whose face test cancels still gets its edges' distance; an
 * edge or face whose denominator is not positive (a triangle of zero area, two
 * of its vertices equal) is left to the segments, so nothing divides by zero. The
 * arithmetic is double where the device has it (cl_khr_fp64): float32
 * coordinates and their squares then neither overflow nor underflow, and
 * the cancellation of the region tests stays far below float32's rounding of
 * the answer; without doubles it is float32 (a weaker bound, see
 * lbvh/verification/error_bound.py).
 *
 * Defines:
 *   STACK_SIZE=n  stack entries; a push beyond n sets FLAG_OVERFLOW and skips
 *                 that subtree (the host sizes it from the tree's depth).
 *   NO_FP64=1     float32 arithmetic even where the device has doubles (tests).
 *   POINT_ORDER=1 work-item k answers point order[k] (a permutation); the
 *                 answers stay in the points' own slots.
 */
#include "common.h"

#ifndef STACK_SIZE
#define STACK_SIZE 64
#endif

#define FLAG_OVERFLOW 1

#include "closest_point.h"

#ifndef POINT_ORDER
#define POINT_ORDER 0
#endif

/* Query i: points[3i..]; results: distance, the closest point (3 floats),
 * triangle (original numbering, -1 when nothing is within max_distance),
 * barycentrics u, v of the point on its triangle (q = (1-u-v) p0 + u p1 + v p2
 * with the triangle's own vertex order), flags. */
__kernel void closest_points(__global const float4 *nodes, __global const int *prim_order,
                             __global const float *vertices, __global const uint *slot_faces,
                             const int root, const int num_nodes,
                             __global const float *points, __global const int *order,
                             const float max_distance, const int count, __global float *distance,
                             __global float *closest, __global int *prim, __global float *bary,
                             __global int *flags) {
    const int k = get_global_id(0);
    if (k >= count) return;
#if POINT_ORDER
    const int i = order[k];   /* points in Morton order of their cells (ray_order.cl) */
#else
    const int i = k;
#endif
    const real3 p = to_real3(load_float3(points, i));
    real best2 = (real)max_distance * (real)max_distance;
    int best_slot = -1;
    real best_v = 0, best_w = 0;
    int flag = 0;

    int stack_node[STACK_SIZE];
    real stack_d2[STACK_SIZE];
    int top = 0;
    int node = root;
    real node_d2 = box_distance2(p, nodes[2 * root].xyz, nodes[2 * root + 1].xyz);
    int visits = 0;
    for (;;) {
        if (node >= 0 && node_d2 <= best2 && visits++ < num_nodes) {
            const float4 lo = nodes[2 * node], hi = nodes[2 * node + 1];
            const int a = as_int(lo.w), b = as_int(hi.w);
            if (node_is_leaf(b)) {
                for (int s = a; s < a - b; ++s) {
                    const real3 p0 = to_real3(load_float3(vertices, slot_faces[3 * s]));
                    const real3 p1 = to_real3(load_float3(vertices, slot_faces[3 * s + 1]));
                    const real3 p2 = to_real3(load_float3(vertices, slot_faces[3 * s + 2]));
                    real v, w;
                    closest_on_triangle(p, p0, p1, p2, &v, &w);
                    const real d2 = length2(p - (p0 + v * (p1 - p0) + w * (p2 - p0)));
                    if (d2 < best2 || (best_slot < 0 && d2 <= best2)) {
                        best2 = d2; best_slot = s; best_v = v; best_w = w;
                    }
                }
                node = -1;
            } else {
                const real da = box_distance2(p, nodes[2 * a].xyz, nodes[2 * a + 1].xyz);
                const real db = box_distance2(p, nodes[2 * b].xyz, nodes[2 * b + 1].xyz);
                /* nearer_child (closest_point.h) written out: taking the address of
                 * node, top and flag made this kernel 27% slower on PoCL (Sponza, 1M
                 * points: 1.41 against 1.02 M/s), even forced inline */
                const int nearer = da <= db ? a : b, farther = da <= db ? b : a;
                const real dnear = da <= db ? da : db, dfar = da <= db ? db : da;
                if (dfar <= best2) {
                    if (top < STACK_SIZE) { stack_node[top] = farther; stack_d2[top] = dfar; ++top; }
                    else flag |= FLAG_OVERFLOW;
                }
                node = nearer;
                node_d2 = dnear;
            }
            continue;
        }
        if (top == 0) break;
        --top;
        node = stack_node[top];
        node_d2 = stack_d2[top];
    }

    if (best_slot >= 0) {
        const real3 p0 = to_real3(load_float3(vertices, slot_faces[3 * best_slot]));
        const real3 p1 = to_real3(load_float3(vertices, slot_faces[3 * best_slot + 1]));
        const real3 p2 = to_real3(load_float3(vertices, slot_faces[3 * best_slot + 2]));
        const real3 q = p0 + best_v * (p1 - p0) + best_w * (p2 - p0);
        distance[i] = (float)sqrt(best2);
        closest[3 * i] = (float)q.x;
        closest[3 * i + 1] = (float)q.y;
        closest[3 * i + 2] = (float)q.z;
        prim[i] = prim_order[best_slot];
        bary[2 * i] = (float)best_v;
        bary[2 * i + 1] = (float)best_w;
    } else {
        distance[i] = INFINITY;
        store_float3(closest + 3 * i, (float3)(NAN, NAN, NAN));
        prim[i] = -1;
        bary[2 * i] = 0.0f;
        bary[2 * i + 1] = 0.0f;
    }
    flags[i] = flag;
}
