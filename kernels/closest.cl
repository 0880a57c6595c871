/* Closest points on the mesh: for each query point, the nearest point of the
 * nearest triangle within max_distance (lbvh/queries/closest.py).
 *
 * Traversal: best first over the binary nodes (docs/layout.md). A node is
 * entered only if the squared distance from the point to its box is below the
 * best squared distance found so far; of two children the nearer is visited
 * first and the farther pushed with its box distance, which is compared again
 * when it is popped (a branch-and-bound search, as in Ericson 2005, 6.1).
 *
 * Point-triangle distance: Ericson 2005, Real-Time Collision Detection,
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

#ifndef POINT_ORDER
#define POINT_ORDER 0
#endif

#if defined(cl_khr_fp64) && !defined(NO_FP64)
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
typedef double real;
typedef double3 real3;
#define to_real3(v) convert_double3(v)
#define REAL_INF ((double)INFINITY)
#else
typedef float real;
typedef float3 real3;
#define to_real3(v) (v)
#define REAL_INF INFINITY
#endif

inline real3 rmax3(real3 a, real3 b) {
    return (real3)(a.x > b.x ? a.x : b.x, a.y > b.y ? a.y : b.y, a.z > b.z ? a.z : b.z);
}

/* Squared distance from p to the box [lo, hi]: 0 inside. */
inline real box_distance2(real3 p, float3 lo, float3 hi) {
    const real3 zero = (real3)(0, 0, 0);
    const real3 d = rmax3(rmax3(to_real3(lo) - p, p - to_real3(hi)), zero);
    return d.x * d.x + d.y * d.y + d.z * d.z;
}

inline real length2(real3 v) { return v.x * v.x + v.y * v.y + v.z * v.z; }

inline real clamp01(real t) { return t < 0 ? 0 : (t > 1 ? 1 : t); }

/* Closest point on segment [a, b] to p: parameter t in [0, 1] (Ericson 5.1.2). */
inline real segment_t(real3 p, real3 a, real3 b) {
    const real3 ab = b - a;
    const real len2 = dot(ab, ab);
    return len2 > 0 ? clamp01(dot(p - a, ab) / len2) : 0;
}

/* The closest point of triangle (a, b, c) to p as barycentrics (v, w):
 * q = a + v (b - a) + w (c - a) = (1 - v - w) a + v b + w c. */
inline void closest_on_triangle(real3 p, real3 a, real3 b, real3 c, real *out_v, real *out_w) {
    const real3 ab = b - a, ac = c - a, ap = p - a;
    const real d1 = dot(ab, ap), d2 = dot(ac, ap);
    if (d1 <= 0 && d2 <= 0) { *out_v = 0; *out_w = 0; return; }                    /* vertex a */
    const real3 bp = p - b;
    const real d3 = dot(ab, bp), d4 = dot(ac, bp);
    if (d3 >= 0 && d4 <= d3) { *out_v = 1; *out_w = 0; return; }                   /* vertex b */
    const real vc = d1 * d4 - d3 * d2;
    if (vc <= 0 && d1 >= 0 && d3 <= 0 && d1 - d3 > 0) {                            /* edge ab */
        *out_v = d1 / (d1 - d3); *out_w = 0; return;
    }
    const real3 cp = p - c;
    const real d5 = dot(ab, cp), d6 = dot(ac, cp);
    if (d6 >= 0 && d5 <= d6) { *out_v = 0; *out_w = 1; return; }                   /* vertex c */
    const real vb = d5 * d2 - d1 * d6;
    if (vb <= 0 && d2 >= 0 && d6 <= 0 && d2 - d6 > 0) {                            /* edge ac */
        *out_v = 0; *out_w = d2 / (d2 - d6); return;
    }
    const real va = d3 * d6 - d5 * d4;
    if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0 && (d4 - d3) + (d5 - d6) > 0) { /* bc */
        const real w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        *out_v = 1 - w; *out_w = w; return;
    }
    /* the face; then the safeguards of the header */
    const real denom = va + vb + vc;
    real v = denom > 0 ? clamp01(vb / denom) : 0, w = denom > 0 ? clamp01(vc / denom) : 0;
    if (v + w > 1) { const real s = v + w; v /= s; w /= s; }
    real best = denom > 0 ? length2(p - (a + v * ab + w * ac)) : REAL_INF;
    const real tab = segment_t(p, a, b), tac = segment_t(p, a, c), tbc = segment_t(p, b, c);
    const real dab = length2(p - (a + tab * ab)), dac = length2(p - (a + tac * ac));
    const real dbc = length2(p - (b + tbc * (c - b)));
    if (dab < best) { best = dab; v = tab; w = 0; }
    if (dac < best) { best = dac; v = 0; w = tac; }
    if (dbc < best) { v = 1 - tbc; w = tbc; }
    *out_v = v; *out_w = w;
}

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
