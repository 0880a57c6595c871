/* Generalised winding numbers of query points (lbvh/queries/winding.py).
 *
 * w(q) = sum over triangles of the solid angle they subtend at q, over 4 pi
 * (Jacobson, Kavan & Sorkine-Hornung 2013): 1 inside a closed, outward-facing
 * mesh, 0 outside, and a smooth value in between near the holes of an open
 * one. Near triangles are summed exactly, with the solid angle of Van
 * Oosterom & Strackee 1983:
 *   tan(omega / 2) = a . (b x c) / (|a||b||c| + (a.b)|c| + (a.c)|b| + (b.c)|a|)
 * for a, b, c the corners minus q. A node far enough from q is replaced by
 * the Taylor expansion of its triangles' solid angle about its area-weighted
 * centroid p (Barill, Dickson, Schmidt, Levin & Jacobson 2018, "Fast winding
 * numbers for soups and clouds", section 3.2, with the terms up to the second
 * order, ORDER=2, or the first, ORDER=1):
 *   omega ~ N . r / |r|^3 + tr(M) / |r|^3 - 3 r^T M r / |r|^5 + (second order),
 * r = p - q, N = sum of the triangles' vector areas a_t, M = sum of
 * a_t (c_t - p)^T with c_t the centroids; the second-order term is
 * SECOND_ORDER_W's. "Far enough" is |r| > beta * R, R the distance from p to
 * the farthest corner of the node's box (every triangle of the node lies
 * within R of p), and |r|^5 >= A R^3 / (4 pi e), A the node's triangle area:
 * the expansion's error, about A / (4 pi r^2) (R / r)^3, at most e
 * (winding_moments.py NODE_ERROR), so that a node of much area for its radius
 * is opened where its expansion would be poor.
 *
 * Moments, ROWS floats per node (winding_moments.cl makes them):
 *   [0..2] p, [3] R^2, [4..6] N, [7..15] M row by row (M[j][k] = m[7 + 3j + k]),
 *   with ORDER=2 also [16..18] g and [19..36] K (SECOND_ORDER_W); last
 *   ([ROWS - 1]) the far floor A R^3 / (4 pi e).
 * beta2 is beta^2; floor_scale multiplies the floor, NODE_ERROR over the
 * pass's own error target per node (1 for the node error the moments were
 * made for; less for a coarser pass, lbvh/queries/winding.py node_error).
 *
 * With WIDE=1 the walk goes through the tree's wide records (kernels/wide.cl)
 * instead: `moments` then holds, per record, the same ROWS values of each
 * lane's binary node as ROWS rows of WIDTH floats, then CORNER_ROWS rows of the
 * corners of each leaf lane's first triangle (winding_moments.py wide_moments
 * and lane_corners; an empty lane has R^2 and the floor -1, so it is always
 * far, and adds 0), and one record's lanes are tested and expanded in one
 * vector computation; the lanes that are near are summed (leaves) or pushed
 * (records). The near leaves' first triangles are summed in one vector
 * computation too, from the corner rows (solid_angles): with one triangle a
 * leaf, as the default tree's, that read and sum of the corners one triangle
 * at a time through slot_faces was half the walk's time on Sponza (perf), and
 * the rows took it to 1.5x the points per second (bench/README.md). Every node
 * expanded meets the same test as in the binary walk; a node that the binary
 * walk expands but that is not a lane (a record's inner nodes, the root) is
 * expanded through its lanes instead, which is as close or closer.
 *
 * Defines:
 *   STACK_SIZE=n  stack entries; a push beyond n sets FLAG_OVERFLOW and skips
 *                 that subtree (the host sizes it from the tree's depth).
 *   POINT_ORDER=1 work-item k answers point order[k] (a permutation: nearby
 *                 points one after another walk the same records), which
 *                 `points` holds at k (ray_order.cl, gather_points); the
 *                 answers stay in the points' own slots.
 *   ORDER=2|1     the order of the far nodes' expansion (the moments' rows:
 *                 37 or 16); 2 unless told.
 *   WIDE=1        walk the wide records (`nodes` is then the records, the root
 *                 their reference (root, root_y)); WIDTH=4 or 8 lanes.
 *   SCALED=1|2    every difference (a corner or a node's centre minus q) is
 *                 multiplied by `scale`, a power of two that brings the mesh to
 *                 about unit size, and the moments are the scaled mesh's
 *                 (winding_moments.py winding_scale): the triple products
 *                 (size^3) and second-order terms (size^4 times distance^3)
 *                 neither overflow nor underflow float32. 1 (a small mesh,
 *                 scale > 1) subtracts, then scales; 2 (a large one, scale < 1)
 *                 scales each side first, so that corners of opposite signs
 *                 near the float32 limit do not overflow. A scaled difference is
 *                 clamped to +-2^40, where a unit-size node's terms are 0 in
 *                 float32 (its r^2 stays finite). SCALED=0 (meshes of extent
 *                 2^-12 to 2^12) leaves the differences as they are.
 */
#include "common.h"

#ifndef STACK_SIZE
#define STACK_SIZE 64
#endif

#ifndef WIDE
#define WIDE 0
#endif

#ifndef ORDER
#define ORDER 2
#endif
#if ORDER == 2
#define ROWS 38
#else
#define ROWS 17
#endif
#define CORNER_ROWS 9
#define RECORD_ROWS (ROWS + CORNER_ROWS)
#define FLOOR_ROW (ROWS - 1)

#define FLAG_OVERFLOW 1

#ifndef SCALED
#define SCALED 0
#endif
#define DIFF_LIMIT 1099511627776.0f   /* 2^40 */
#define CLAMP_DIFF(d) ((d) > DIFF_LIMIT ? DIFF_LIMIT : ((d) < -DIFF_LIMIT ? -DIFF_LIMIT : (d)))
#if SCALED == 1
#define DIFF(a, b) CLAMP_DIFF(((a) - (b)) * scale)
#elif SCALED == 2
#define DIFF(a, b) CLAMP_DIFF((a) * scale - (b) * scale)
#else
#define DIFF(a, b) ((a) - (b))
#endif

/* atan2(y, x) in float32 within 4e-7 of the exact angle (under 2 ulps of pi),
 * inline: PoCL 3 calls its atan2 out of line, and that call was two thirds of
 * the kernel's time on Sponza (perf). atan(t) for t = min/max of |x|, |y| in
 * [0, 1] is t * P(t^2), P (ATAN_P) of degree 7 fitted (minimax, by reweighted least
 * squares in float64) to within 4e-8 of atan on [0, 1], then the octant:
 * pi/2 - a where |y| > |x|, pi - a where x's sign bit is set (atan2(0, -0) =
 * pi, as IEEE's), the sign of y. NaN in stays NaN; (0, 0) gives 0 (or pi);
 * (inf, inf) gives NaN, where atan2 gives pi/4 (a triangle whose corners'
 * distances overflow float32). */
/* P(s) by Horner's rule (Estrin's scheme, a shorter chain, measured no faster in
 * the vector walk: bench/README.md). */
#define ATAN_P(s)                                                                          \
    (((((((-0.004054564982652664f * (s) + 0.021862955763936043f) * (s) -                   \
           0.055912334471940994f) * (s) + 0.0964219868183136f) * (s) -                      \
         0.1390863060951233f) * (s) + 0.19946566224098206f) * (s) -                         \
       0.33329859375953674f) * (s) + 0.9999993443489075f)
inline float atan2_poly(float y, float x) {
    const float ax = abs_bits(x), ay = abs_bits(y);
    const int steep = ay > ax;
    const float t = steep ? ax / ay : (ax == 0.0f ? 0.0f : ay / ax);
    const float s = t * t;
    float a = ATAN_P(s);
    a *= t;
    a = steep ? M_PI_2_F - a : a;
    a = as_int(x) < 0 ? M_PI_F - a : a;
    return as_float(as_uint(a) | (as_uint(y) & 0x80000000u));
}

/* The solid angle of triangle (p0, p1, p2) at q (signed: positive where q sees
 * the triangle's back, its vertices counterclockwise around the outward
 * normal), written out in scalars with the three lengths in one vector sqrt:
 * PoCL 3 called dot and sqrt out of line here (1.19x on Sponza written out;
 * bench/README.md). */
inline float dot3(float3 u, float3 v) { return u.x * v.x + u.y * v.y + u.z * v.z; }
inline float solid_angle(float3 q, float3 p0, float3 p1, float3 p2, float scale) {
    const float3 a = DIFF(p0, q), b = DIFF(p1, q), c = DIFF(p2, q);
    const float4 l = sqrt4((float4)(dot3(a, a), dot3(b, b), dot3(c, c), 0.0f));
    const float la = l.x, lb = l.y, lc = l.z;
    const float num = a.x * (b.y * c.z - b.z * c.y) + a.y * (b.z * c.x - b.x * c.z) +
                      a.z * (b.x * c.y - b.y * c.x);
    const float den = la * lb * lc + dot3(a, b) * lc + dot3(a, c) * lb + dot3(b, c) * la;
    return 2.0f * atan2_poly(num, den);
}

/* The second-order term of a far node's expansion (ORDER=2; Barill et al. 2018,
 * section 3.2): 1/2 H_ijk d_j d_k f_i(p), f(x) = (x - q) / |x - q|^3, for
 * H_ijk = sum_t a_t,i S_t,jk, S_t the mean of (x - p)(x - p)^T over triangle t:
 *   g . r / |r|^5 + sum_i r_i (K_i . rr) / |r|^7,  rr = (x^2, y^2, z^2, xy, xz, yz),
 * m[16..18] = g = -3/2 (2 u + t) (u_k = H_iik, t_i = H_ijj) and m[19 + 6 i ..] = K_i,
 * 15/2 H_i.. over those pairs with the mixed ones doubled (winding.py, node_moments).
 * inv5 = 1/|r|^5, inv = 1/|r|; works on float or floatw rows alike. */
#define SECOND_ORDER_W(m, x, y, z, inv5, inv)                                              \
    (((m)[16] * (x) + (m)[17] * (y) + (m)[18] * (z)) * (inv5) +                           \
     ((x) * ((m)[19] * (x) * (x) + (m)[20] * (y) * (y) + (m)[21] * (z) * (z) +              \
             (m)[22] * (x) * (y) + (m)[23] * (x) * (z) + (m)[24] * (y) * (z)) +             \
      (y) * ((m)[25] * (x) * (x) + (m)[26] * (y) * (y) + (m)[27] * (z) * (z) +              \
             (m)[28] * (x) * (y) + (m)[29] * (x) * (z) + (m)[30] * (y) * (z)) +             \
      (z) * ((m)[31] * (x) * (x) + (m)[32] * (y) * (y) + (m)[33] * (z) * (z) +              \
             (m)[34] * (x) * (y) + (m)[35] * (x) * (z) + (m)[36] * (y) * (z))) *            \
         (inv5) * (inv) * (inv))

/* The exact solid angles of the triangles of slots [first, end), added to w. */
#define LEAF_SUM(first, end)                                                               \
    for (int s = (first); s < (end); ++s)                                                  \
        w += solid_angle(q, load_float3(vertices, slot_faces[3 * s]),                      \
                         load_float3(vertices, slot_faces[3 * s + 1]),                     \
                         load_float3(vertices, slot_faces[3 * s + 2]), scale);

#if WIDE
#include "wide_rows.h"

/* The sum of the lanes of v. */
inline float lanes_sum(floatw v) {
#if WIDTH == 8
    const float4 h = v.lo + v.hi;
#else
    const float4 h = v;
#endif
    const float2 d = h.lo + h.hi;
    return d.x + d.y;
}

/* atan2_poly lane by lane, by the same operations, with masks for its choices
 * (PoCL 3 calls select() out of line). */
inline floatw atan2_polyw(floatw y, floatw x) {
    const intw magnitude = (intw)(0x7fffffff);
    const floatw ax = as_floatw(as_intw(x) & magnitude), ay = as_floatw(as_intw(y) & magnitude);
    const intw steep = ay > ax;
    const floatw num = as_floatw((as_intw(ax) & steep) | (as_intw(ay) & ~steep));
    const floatw den = as_floatw((as_intw(ay) & steep) | (as_intw(ax) & ~steep));
    const floatw t = as_floatw(as_intw(num / den) & (den != (floatw)(0.0f)));
    const floatw s = t * t;
    floatw a = ATAN_P(s);
    a *= t;
    a = as_floatw((as_intw((floatw)(M_PI_2_F) - a) & steep) | (as_intw(a) & ~steep));
    const intw negative = as_intw(x) < (intw)(0);
    a = as_floatw((as_intw((floatw)(M_PI_F) - a) & negative) | (as_intw(a) & ~negative));
    return as_floatw(as_intw(a) | (as_intw(y) & (intw)(0x80000000)));
}

/* solid_angle lane by lane, of the triangles whose corners are the rows
 * c[0..8] (a record's CORNER_ROWS); forced inline (PoCL 3 kept it out of
 * line, and its float8 result went through memory). */
__attribute__((always_inline)) inline floatw solid_angles(float3 q, __global const floatw *c,
                                                          float scale) {
    const floatw ax = DIFF(c[0], (floatw)(q.x)), ay = DIFF(c[1], (floatw)(q.y)),
                 az = DIFF(c[2], (floatw)(q.z));
    const floatw bx = DIFF(c[3], (floatw)(q.x)), by = DIFF(c[4], (floatw)(q.y)),
                 bz = DIFF(c[5], (floatw)(q.z));
    const floatw cx = DIFF(c[6], (floatw)(q.x)), cy = DIFF(c[7], (floatw)(q.y)),
                 cz = DIFF(c[8], (floatw)(q.z));
    const floatw la = SQRTW(ax * ax + ay * ay + az * az);
    const floatw lb = SQRTW(bx * bx + by * by + bz * bz);
    const floatw lc = SQRTW(cx * cx + cy * cy + cz * cz);
    const floatw num = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) +
                       az * (bx * cy - by * cx);
    const floatw den = la * lb * lc + (ax * bx + ay * by + az * bz) * lc +
                       (ax * cx + ay * cy + az * cz) * lb + (bx * cx + by * cy + bz * cz) * la;
    return (floatw)(2.0f) * atan2_polyw(num, den);
}
#endif

__kernel void winding_numbers(__global const float4 *nodes, __global const float *moments,
                              __global const float *vertices, __global const uint *slot_faces,
                              const int root, const int root_y, const int num_nodes,
                              __global const float *points, __global const int *order,
                              const int count, const float beta2, const float floor_scale,
                              const float scale,
                              __global float *winding, __global int *flags) {
    const int k = get_global_id(0);
    if (k >= count) return;
    const int i = point_index(order, k);
    const float3 q = load_float3(points, k);
    float w = 0.0f;
#if WIDE
    floatw wv = (floatw)(0.0f);   /* the lanes' vector sums, added up once at the end */
#endif
    int flag = 0;
    int stack[STACK_SIZE];
    int top = 0, visits = 0;
#if WIDE
    __global const int *words = (__global const int *)nodes;
    __global const floatw *rows = (__global const floatw *)moments;
    if (node_is_leaf(root_y)) {     /* a root leaf: no records */
        LEAF_SUM(root, root - root_y);
    } else {
        int record = root;
        for (;;) {
            if (visits++ < num_nodes) {
                __global const floatw *m = rows + RECORD_ROWS * record;
                const floatw rx = DIFF(m[0], (floatw)(q.x)), ry = DIFF(m[1], (floatw)(q.y)),
                             rz = DIFF(m[2], (floatw)(q.z));
                const floatw r2 = rx * rx + ry * ry + rz * rz;
                const floatw r1 = SQRTW(r2);
                const intw far = (r2 > (floatw)(beta2) * m[3]) &
                                 (r2 * r2 * r1 >= (floatw)(floor_scale) * m[FLOOR_ROW]);
                const intw y_row = ((__global const intw *)words)[8 * record + 7];
                /* far (and not an empty lane): expanded; near: a leaf's first triangle
                 * summed from the corner rows, lane by lane, and the rest of it one by
                 * one; a record pushed. Each part only where a lane needs it: a record
                 * near the point often has no far lane (1.10x on Sponza, bench/README.md). */
                const intw far_lanes = far & (m[3] >= (floatw)(0.0f));
                const intw near_leaves = ~far & (y_row < (intw)(0));
                if (lane_bits(far_lanes) != 0u) {
                    /* the far lanes' expansions (Barill et al. 2018), as the binary walk's */
                    const floatw inv = (floatw)(1.0f) / r1;
                    const floatw inv3 = inv * inv * inv;
                    const floatw mrx = m[7] * rx + m[8] * ry + m[9] * rz;
                    const floatw mry = m[10] * rx + m[11] * ry + m[12] * rz;
                    const floatw mrz = m[13] * rx + m[14] * ry + m[15] * rz;
                    const floatw term =
                        (m[4] * rx + m[5] * ry + m[6] * rz) * inv3 + (m[7] + m[11] + m[15]) * inv3 -
                        (floatw)(3.0f) * (rx * mrx + ry * mry + rz * mrz) * inv3 * inv * inv
#if ORDER == 2
                        + SECOND_ORDER_W(m, rx, ry, rz, inv3 * inv * inv, inv)
#endif
                        ;
                    /* term where far, +0 elsewhere: a mask, not select(), which PoCL 3
                     * calls out of line */
                    wv += as_floatw(as_intw(term) & far_lanes);
                }
                if (lane_bits(near_leaves) != 0u)
                    wv += as_floatw(as_intw(solid_angles(q, m + ROWS, scale)) & near_leaves);
                __global const int *ref = words + 8 * WIDTH * record + 6 * WIDTH;
                for (uint bits = lane_bits(~far & (y_row < (intw)(-1) | y_row >= (intw)(0)));
                     bits != 0u; bits &= bits - 1u) {
                    const int c = lowest_lane(bits);
                    const int x = ref[c], y = ref[WIDTH + c];
                    if (node_is_leaf(y)) {
                        LEAF_SUM(x + 1, x - y);
                    } else if (top < STACK_SIZE) {
                        stack[top++] = x;
                    } else {
                        flag |= FLAG_OVERFLOW;
                    }
                }
            }
            if (top == 0) break;
            record = stack[--top];
        }
    }
#else
    int node = root;
    for (;;) {
        if (node >= 0 && visits++ < num_nodes) {
            __global const float *m = moments + ROWS * node;
            const float3 r = DIFF((float3)(m[0], m[1], m[2]), q);
            const float r2 = dot(r, r);
            const int a = as_int(nodes[2 * node].w), b = as_int(nodes[2 * node + 1].w);
            const float r1 = sqrt1(r2);
            if (r2 > beta2 * m[3] && r2 * r2 * r1 >= floor_scale * m[FLOOR_ROW]) {
                /* far: the expansion (Barill et al. 2018) */
                const float inv = 1.0f / r1;
                const float inv3 = inv * inv * inv;
                const float3 n = (float3)(m[4], m[5], m[6]);
                const float3 mr = (float3)(m[7] * r.x + m[8] * r.y + m[9] * r.z,
                                           m[10] * r.x + m[11] * r.y + m[12] * r.z,
                                           m[13] * r.x + m[14] * r.y + m[15] * r.z);
                w += dot(n, r) * inv3 + (m[7] + m[11] + m[15]) * inv3 -
                     3.0f * dot(r, mr) * inv3 * inv * inv
#if ORDER == 2
                     + SECOND_ORDER_W(m, r.x, r.y, r.z, inv3 * inv * inv, inv)
#endif
                     ;
                node = -1;
            } else if (node_is_leaf(b)) {
                LEAF_SUM(a, a - b);
                node = -1;
            } else {
                if (top < STACK_SIZE) stack[top++] = b;
                else flag |= FLAG_OVERFLOW;
                node = a;
            }
            continue;
        }
        if (top == 0) break;
        node = stack[--top];
    }
#endif
#if WIDE
    w += lanes_sum(wv);
#endif
    winding[i] = w * (0.25f * M_1_PI_F);
    flags[i] = flag;
}
