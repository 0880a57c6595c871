/* Closest points on the mesh: for each query point, the nearest point of the
 * nearest triangle within max_distance (lbvh/queries/closest.py).
 *
 * Traversal: best first over the tree's wide records (WIDE=1; kernels/wide.cl),
 * or over its binary nodes (docs/pages/layout.md) where the records would not fit. A
 * node is entered only if the squared distance from the point to its box is no
 * more than the best squared distance found so far; of the children entered
 * the nearest is visited first and the others pushed with their box distances,
 * which are compared again when popped (a branch-and-bound search, as in
 * Ericson 2005, 6.1). A wide record's lanes get their box distances in one
 * vector computation, in `real` as the binary walk's, so both walks prune by
 * the same values (1.21-1.29x faster than the binary walk through the API;
 * bench/README.md).
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
 * of its vertices equal) is left to the segments, so nothing divides by zero.
 * The corners are taken in one order whatever the mesh's (closest_sorted:
 * ascending coordinates), so the point, its distance and the triangle chosen
 * do not depend on the order or winding of the corners. The
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
 *   POINT_ORDER=1 work-item k answers point order[k] (a permutation), which
 *                 `points` holds at k (ray_order.cl, gather_points: read as one
 *                 run, where reading order[k]'s own slot missed the cache once a
 *                 point); the answers stay in the points' own slots.
 *   WIDE=1        walk the wide records (`records`, the root as the reference
 *                 (root_x, root_y)) instead of the binary nodes; WIDTH=4 or 8
 *                 lanes per record (kernels/wide_rows.h).
 */
#include "common.h"

#ifndef STACK_SIZE
#define STACK_SIZE 64
#endif

#define FLAG_OVERFLOW 1

#include "closest_point.h"

#ifndef WIDE
#define WIDE 0
#endif

#if WIDE
#include "wide_rows.h"

/* Squared distances from p to four lanes' boxes (rows of a wide record), as
 * real_box_distance2 computes each; four lanes at a time so that no value
 * wider than 32 bytes (a double8) crosses a function boundary. */
#if defined(cl_khr_fp64) && !defined(NO_FP64)
typedef double4 real4;
#define to_real4(v) convert_double4(v)
#else
typedef float4 real4;
#define to_real4(v) (v)
#endif
inline real4 rmax4(real4 a, real4 b) { return a > b ? a : b; }
inline real4 lanes_distance2(float4 lx, float4 ux, float4 ly, float4 uy, float4 lz, float4 uz,
                             real3 p) {
    const real4 zero = (real4)(0);
    const real4 dx = rmax4(rmax4(to_real4(lx) - (real4)(p.x), (real4)(p.x) - to_real4(ux)), zero);
    const real4 dy = rmax4(rmax4(to_real4(ly) - (real4)(p.y), (real4)(p.y) - to_real4(uy)), zero);
    const real4 dz = rmax4(rmax4(to_real4(lz) - (real4)(p.z), (real4)(p.z) - to_real4(uz)), zero);
    return dx * dx + dy * dy + dz * dz;
}
/* Lane c entered (-1) where its box is not empty and no farther than best2. */
inline int4 lanes_within(real4 d2, float4 lx, float4 ux, real best2) {
    return convert_int4(d2 <= (real4)(best2)) & (lx <= ux);
}
typedef union { real4 h[2]; real s[8]; } real8_lanes;
#endif

/* The triangles of slots [first, end) against the query point p: the nearest so far
 * in (best2, best_slot, best_v, best_w), the first of equal distances kept. A macro,
 * not a function: taking the addresses of those made this kernel slower on PoCL
 * (see the binary walk below). */
#define LEAF_TESTS(first, end)                                                             \
    for (int s = (first); s < (end); ++s) {                                                \
        const real3 p0 = to_real3(load_float3(vertices, slot_faces[3 * s]));              \
        const real3 p1 = to_real3(load_float3(vertices, slot_faces[3 * s + 1]));          \
        const real3 p2 = to_real3(load_float3(vertices, slot_faces[3 * s + 2]));          \
        real v, w;                                                                         \
        const real d2 = closest_sorted(p, p0, p1, p2, &v, &w);                             \
        if (d2 < best2 || (best_slot < 0 && d2 <= best2)) {                                \
            best2 = d2;                                                                    \
            best_slot = s;                                                                 \
            best_v = v;                                                                    \
            best_w = w;                                                                    \
        }                                                                                  \
    }

/* Query i: points[3k..] (the points in order[]'s order, or i = k); results: distance, the closest point (3 floats),
 * triangle (original numbering, -1 when nothing is within max_distance),
 * barycentrics u, v of the point on its triangle (q = (1-u-v) p0 + u p1 + v p2
 * with the triangle's own vertex order), flags. */
__kernel void closest_points(__global const float4 *nodes, __global const float *records,
                             __global const int *prim_order,
                             __global const float *vertices, __global const uint *slot_faces,
                             const int root, const int root_x, const int root_y,
                             const int num_nodes,
                             __global const float *points, __global const int *order,
                             const float max_distance, const int count, __global float *distance,
                             __global float *closest, __global int *prim, __global float *bary,
                             __global int *flags) {
    const int k = get_global_id(0);
    if (k >= count) return;
    const int i = point_index(order, k);
    const real3 p = to_real3(load_float3(points, k));
    real best2 = (real)max_distance * (real)max_distance;
    int best_slot = -1;
    real best_v = 0, best_w = 0;
    int flag = 0;

#if WIDE
    __global const int *record_words = (__global const int *)records;
    __global const float4 *quads = (__global const float4 *)records;
    int stack_x[STACK_SIZE], stack_y[STACK_SIZE];
    real stack_d2[STACK_SIZE];
    int top = 0;
    int x = root_x, y = root_y;
    int visits = 0;
    int go = box_distance2(p, nodes[2 * root].xyz, nodes[2 * root + 1].xyz) <= best2;
    while (go && visits++ < num_nodes) {
        int have = 0;
        if (node_is_leaf(y)) {
            LEAF_TESTS(x, x - y);
        } else {
            /* rows 0-5 of record x as float4 quarters: row r, lanes 4h..4h+3 */
            __global const float4 *q = quads + 2 * WIDTH * x;
            real8_lanes d2;
            d2.h[0] = lanes_distance2(q[0], q[WIDTH / 4], q[2 * WIDTH / 4], q[3 * WIDTH / 4],
                                      q[4 * WIDTH / 4], q[5 * WIDTH / 4], p);
#if WIDTH == 8
            d2.h[1] = lanes_distance2(q[1], q[3], q[5], q[7], q[9], q[11], p);
            const intw in = (intw)(lanes_within(d2.h[0], q[0], q[2], best2),
                                   lanes_within(d2.h[1], q[1], q[3], best2));
#else
            const intw in = lanes_within(d2.h[0], q[0], q[1], best2);
#endif
            /* the lanes entered, nearest first by insertion (equal: the earlier lane) */
            int lane[WIDTH];
            int n = 0;
            for (uint m = lane_bits(in); m != 0u; m &= m - 1u) {
                const int c = lowest_lane(m);
                const real e = d2.s[c];
                int k = n++;
                for (; k > 0 && d2.s[lane[k - 1]] > e; --k) lane[k] = lane[k - 1];
                lane[k] = c;
            }
            if (n > 0) {
                __global const int *ref = record_words + 8 * WIDTH * x + 6 * WIDTH;
                for (int k = n - 1; k > 0; --k) {
                    if (top < STACK_SIZE) {
                        stack_x[top] = ref[lane[k]];
                        stack_y[top] = ref[WIDTH + lane[k]];
                        stack_d2[top] = d2.s[lane[k]];
                        ++top;
                    } else {
                        flag |= FLAG_OVERFLOW;
                    }
                }
                x = ref[lane[0]];
                y = ref[WIDTH + lane[0]];
                have = 1;
            }
        }
        if (!have) {
            /* pop, dropping boxes farther than the best so far */
            while (top > 0 && stack_d2[top - 1] > best2) --top;
            if (top == 0) break;
            --top;
            x = stack_x[top];
            y = stack_y[top];
        }
    }
#else
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
                LEAF_TESTS(a, a - b);
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

#endif

    if (best_slot >= 0) {
        const real3 p0 = to_real3(load_float3(vertices, slot_faces[3 * best_slot]));
        const real3 p1 = to_real3(load_float3(vertices, slot_faces[3 * best_slot + 1]));
        const real3 p2 = to_real3(load_float3(vertices, slot_faces[3 * best_slot + 2]));
        real u1, u2;
        const real3 q = point_of_sorted(p0, p1, p2, best_v, best_w, &u1, &u2);
        distance[i] = (float)sqrt(best2);
        closest[3 * i] = (float)q.x;
        closest[3 * i + 1] = (float)q.y;
        closest[3 * i + 2] = (float)q.z;
        prim[i] = prim_order[best_slot];
        bary[2 * i] = (float)u1;
        bary[2 * i + 1] = (float)u2;
    } else {
        distance[i] = INFINITY;
        store_float3(closest + 3 * i, (float3)(NAN, NAN, NAN));
        prim[i] = -1;
        bary[2 * i] = 0.0f;
        bary[2 * i + 1] = 0.0f;
    }
    flags[i] = flag;
}
