/* Closest points on triangles: what kernels/closest.cl (one mesh) and
 * kernels/instance_closest.cl (a scene of placed meshes) share.
 *
 * `real` is double where the device has it (cl_khr_fp64) and NO_FP64 is not
 * defined, else float; the point-box distance, the segment and the
 * point-triangle closest point of Ericson 2005, Real-Time Collision Detection,
 * 5.1.2 and 5.1.5 (ClosestPtPointTriangle) with the safeguards that
 * kernels/closest.cl's header describes.
 */
#ifndef LBVH_CLOSEST_POINT_H
#define LBVH_CLOSEST_POINT_H
#include "common.h"

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
inline real real_box_distance2(real3 p, real3 lo, real3 hi) {
    const real3 zero = (real3)(0, 0, 0);
    const real3 d = rmax3(rmax3(lo - p, p - hi), zero);
    return d.x * d.x + d.y * d.y + d.z * d.z;
}

/* The same for a float32 box (a node's). */
inline real box_distance2(real3 p, float3 lo, float3 hi) {
    return real_box_distance2(p, to_real3(lo), to_real3(hi));
}

inline real length2(real3 v) { return v.x * v.x + v.y * v.y + v.z * v.z; }
/* dot, written out: PoCL 3 calls the builtin out of line (1.05-1.08x here). */
inline real dot3r(real3 u, real3 v) { return u.x * v.x + u.y * v.y + u.z * v.z; }

inline real clamp01(real t) { return t < 0 ? 0 : (t > 1 ? 1 : t); }

/* Closest point on segment [a, b] to p: parameter t in [0, 1] (Ericson 5.1.2). */
inline real segment_t(real3 p, real3 a, real3 b) {
    const real3 ab = b - a;
    const real len2 = dot3r(ab, ab);
    return len2 > 0 ? clamp01(dot3r(p - a, ab) / len2) : 0;
}

/* The closest point of triangle (a, b, c) to p as barycentrics (v, w):
 * q = a + v (b - a) + w (c - a) = (1 - v - w) a + v b + w c. */
inline void closest_on_triangle(real3 p, real3 a, real3 b, real3 c, real *out_v, real *out_w) {
    const real3 ab = b - a, ac = c - a, ap = p - a;
    const real d1 = dot3r(ab, ap), d2 = dot3r(ac, ap);
    if (d1 <= 0 && d2 <= 0) { *out_v = 0; *out_w = 0; return; }                    /* vertex a */
    const real3 bp = p - b;
    const real d3 = dot3r(ab, bp), d4 = dot3r(ac, bp);
    if (d3 >= 0 && d4 <= d3) { *out_v = 1; *out_w = 0; return; }                   /* vertex b */
    const real vc = d1 * d4 - d3 * d2;
    if (vc <= 0 && d1 >= 0 && d3 <= 0 && d1 - d3 > 0) {                            /* edge ab */
        *out_v = d1 / (d1 - d3); *out_w = 0; return;
    }
    const real3 cp = p - c;
    const real d5 = dot3r(ab, cp), d6 = dot3r(ac, cp);
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

/* The corners of a triangle in one order, whatever order the mesh lists them
 * in: ascending by x, then y, then z (three compare-exchanges, in place). The
 * walks test a triangle and make its closest point from its corners in this
 * order, so the point, its distance and the triangle chosen do not depend on
 * the order of the corners or the winding (the arithmetic is the same, operation
 * for operation); bary_of_sorted gives the barycentrics back in the mesh's order. */
inline int corner_before(real3 a, real3 b) {
    return a.x < b.x || (a.x == b.x && (a.y < b.y || (a.y == b.y && a.z < b.z)));
}
inline void sort_corners(real3 *a, real3 *b, real3 *c) {
    real3 s;
    if (corner_before(*b, *a)) { s = *a; *a = *b; *b = s; }
    if (corner_before(*c, *b)) { s = *b; *b = *c; *c = s; }
    if (corner_before(*b, *a)) { s = *a; *a = *b; *b = s; }
}

/* Which of the sorted corners s0, s1, s2 corner x is, among those not taken yet
 * (bits of *taken): a corner repeated in the triangle takes one weight each. */
inline int sorted_slot(real3 x, real3 s0, real3 s1, int *taken) {
    int j = 2;
    if (!(*taken & 1) && x.x == s0.x && x.y == s0.y && x.z == s0.z) j = 0;
    else if (!(*taken & 2) && x.x == s1.x && x.y == s1.y && x.z == s1.z) j = 1;
    *taken |= 1 << j;
    return j;
}

/* The closest point q of triangle (p0, p1, p2) to p, as closest_on_triangle on the
 * sorted corners, and its squared distance; (v, w) are the sorted corners'. */
inline real closest_sorted(real3 p, real3 p0, real3 p1, real3 p2, real *v, real *w) {
    sort_corners(&p0, &p1, &p2);
    closest_on_triangle(p, p0, p1, p2, v, w);
    return length2(p - (p0 + *v * (p1 - p0) + *w * (p2 - p0)));
}

/* The closest point from the sorted corners' (v, w) (closest_sorted), and the
 * barycentrics of corners p1 and p2 in the mesh's order in *u1, *u2. */
inline real3 point_of_sorted(real3 p0, real3 p1, real3 p2, real v, real w, real *u1, real *u2) {
    real3 s0 = p0, s1 = p1, s2 = p2;
    sort_corners(&s0, &s1, &s2);
    /* the sorted corners' weights; rounding may take 1 - v - w below 0 where
     * v + w is 1 */
    const real u = 1 - v - w, weight[3] = {u > 0 ? u : 0, v, w};
    int taken = 0;
    (void)sorted_slot(p0, s0, s1, &taken);
    *u1 = weight[sorted_slot(p1, s0, s1, &taken)];
    *u2 = weight[sorted_slot(p2, s0, s1, &taken)];
    return s0 + v * (s1 - s0) + w * (s2 - s0);
}

/* One step of the best-first walks: of children a and b with squared box distances
 * da and db, the nearer is next (*node, *node_d2) and the farther, if within best2,
 * is pushed with its distance; a push beyond STACK_SIZE sets FLAG_OVERFLOW in *flag
 * (the including file defines both). */
inline void nearer_child(int a, int b, real da, real db, real best2, int *stack_node,
                         real *stack_d2, int *top, int *flag, int *node, real *node_d2) {
    const int nearer = da <= db ? a : b, farther = da <= db ? b : a;
    const real dnear = da <= db ? da : db, dfar = da <= db ? db : da;
    if (dfar <= best2) {
        if (*top < STACK_SIZE) { stack_node[*top] = farther; stack_d2[*top] = dfar; ++*top; }
        else *flag |= FLAG_OVERFLOW;
    }
    *node = nearer;
    *node_d2 = dnear;
}

#endif
