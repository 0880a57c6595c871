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
 * a_t (c_t - p)^T with c_t the centroids; FAR_TERM evaluates it, the
 * second-order terms with it. "Far enough" is |r| > beta * R, R the distance from p to
 * the farthest corner of the node's box (every triangle of the node lies
 * within R of p), and |r|^5 >= A R^3 / (4 pi e), A the node's triangle area:
 * the expansion's error, about A / (4 pi r^2) (R / r)^3, at most e
 * (winding_moments.py NODE_ERROR), so that a node of much area for its radius
 * is opened where its expansion would be poor.
 *
 * Moments, ROWS floats per node (winding_moments.cl makes them):
 *   [0..2] p, [3] R^2, [4..6] N, [7] tr M, [8..13] -3 M's symmetric pairs, with
 *   ORDER=2 also [14..16] g and [17..26] the cubic's coefficients (FAR_TERM);
 *   last ([ROWS - 1]) the far floor A R^3 / (4 pi e).
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
 * computation too, from the corner rows (SOLID_ANGLES): with one triangle a
 * leaf, as the default tree's, that read and sum of the corners one triangle
 * at a time through slot_faces was half the walk's time on Sponza (perf), and
 * the rows took it to 1.5x the points per second (bench/README.md). Every node
 * expanded meets the same test as in the binary walk; a node that the binary
 * walk expands but that is not a lane (a record's inner nodes, the root) is
 * expanded through its lanes instead, which is as close or closer. A second
 * kernel, winding_packets (below), walks the same records for 16 points a
 * work-item, the vectors then the points (a CPU's choice).
 *
 * Defines:
 *   STACK_SIZE=n  stack entries; a push beyond n sets FLAG_OVERFLOW and skips
 *                 that subtree (the host sizes it from the tree's depth).
 *   POINT_ORDER=1 work-item k answers point order[k] (a permutation: nearby
 *                 points one after another walk the same records), which
 *                 `points` holds at k (ray_order.cl, gather_points); the
 *                 answers stay in the points' own slots.
 *   ORDER=2|1     the order of the far nodes' expansion (the moments' rows:
 *                 28 or 15); 2 unless told.
 *   WIDE=1        walk the wide records (`nodes` is then the records, the root
 *                 their reference (root, root_y)); WIDTH=4 or 8 lanes.
 *   CLANG_PREFETCH=1  winding_packets asks a record it pushes into the cache
 *                 with clang's builtin (the host: where the compiler is clang).
 *
 * Scale: every length the walk sees is the mesh's times `scale`, a power of
 * two that brings the mesh to unit size (winding_moments.py winding_scale):
 * the points (scaled, and clamped to 2^40 of the mesh, on the host:
 * winding.py unit_points), the nodes' centres and the corner rows (scaled
 * where the moments are made), the vertices read from the mesh (scaled here,
 * VDIFF). So the triple products (size^3) and second-order terms (size^4
 * times distance^3) neither overflow nor underflow float32, and the same mesh
 * and points at any other power-of-two scale give the walk the same floats:
 * the same winding numbers, bit for bit (tests/queries/test_invariance.py).
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
#define ROWS 28
#else
#define ROWS 15
#endif
#define CORNER_ROWS 9
#define RECORD_ROWS (ROWS + CORNER_ROWS)
#define FLOOR_ROW (ROWS - 1)

#define FLAG_OVERFLOW 1

/* Points, node centres and corner rows are all at the mesh's unit size (see
 * the header: `scale`); a vertex read from the mesh is scaled here, by a power
 * of two (exact). */
#define DIFF(a, b) ((a) - (b))
#define VDIFF(v, b) ((v) * scale - (b))

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
 * bench/README.md). p0, p1, p2 are the mesh's vertices (scaled here), q a
 * point at unit size. The corners are read from the least on (common.h
 * least_corner), and the denominator is grouped symmetric in the last two
 * (b, c): the same floats for any corner the mesh lists first, the numerator
 * and so the angle negated exactly for the winding reversed; a triangle with
 * two corners at one point adds 0. A point on the triangle's plane (a numerator
 * of 0, either sign) gets 0, where atan2 would give +-2 pi by the zero's sign,
 * which rounding sets, not the geometry: a point on a closed surface then has
 * the mean of the two sides' winding numbers, 1/2, in every corner order. */
inline float dot3(float3 u, float3 v) { return u.x * v.x + u.y * v.y + u.z * v.z; }
inline float solid_angle(float3 q, float3 p0, float3 p1, float3 p2, float scale) {
    const int first = least_corner(p0, p1, p2);
    if (first < 0) return 0.0f;
    const float3 s0 = first == 0 ? p0 : (first == 1 ? p1 : p2);
    const float3 s1 = first == 0 ? p1 : (first == 1 ? p2 : p0);
    const float3 s2 = first == 0 ? p2 : (first == 1 ? p0 : p1);
    const float3 a = VDIFF(s0, q), b = VDIFF(s1, q), c = VDIFF(s2, q);
    const float4 l = sqrt4((float4)(dot3(a, a), dot3(b, b), dot3(c, c), 0.0f));
    const float la = l.x, lb = l.y, lc = l.z;
    const float num = a.x * (b.y * c.z - b.z * c.y) + a.y * (b.z * c.x - b.x * c.z) +
                      a.z * (b.x * c.y - b.y * c.x);
    const float den = (la * (lb * lc) + dot3(b, c) * la) + (dot3(a, b) * lc + dot3(a, c) * lb);
    return num == 0.0f ? 0.0f : 2.0f * atan2_poly(num, den);
}

/* A far node's expansion (Barill et al. 2018, section 3.2) at r = p - q, with
 * its terms grouped by the power of |r| they are divided by:
 *   inv3 (N.r + tr M + inv2 (g.r - 3 r^T M r + inv2 C(r))),
 * inv3 = 1/|r|^3, inv2 = 1/|r|^2, -3 r^T M r by its 6 monomials (m[8..13]) and
 * C(r), the second order's cubic, by its 10 (m[17..26]; m[14..16] = g): each
 * coefficient one row of the moments, ready to multiply (winding_moments.py
 * node_moments; summed there in float64, where the terms of one monomial were
 * added up here for every point: 1.1x on Sponza's inside tests,
 * bench/README.md). M(j) is row j of the node's moments (a float, or a vector
 * of lanes); r's components, r2 = |r|^2, r1 = |r| (the far test's) and the
 * result are of type T (float or a vector of points or lanes). One grouping
 * for every walk, with fewer operations than the terms one by one. */
#define FAR_TERM(T, M, x, y, z, r2, r1, out)                                               \
    T out;                                                                                 \
    do {                                                                                   \
        const T xx_ = (x) * (x), yy_ = (y) * (y), zz_ = (z) * (z);                         \
        const T inv3_ = (T)(1.0f) / ((r2) * (r1));                                         \
        const T inv2_ = inv3_ * (r1);                                                      \
        const T xy_ = (x) * (y), xz_ = (x) * (z), yz_ = (y) * (z);                         \
        const T quad_ = M(8) * xx_ + M(9) * yy_ + M(10) * zz_ + M(11) * xy_ + M(12) * xz_ +  \
                        M(13) * yz_;                                                       \
        out = inv3_ * (M(4) * (x) + M(5) * (y) + M(6) * (z) + M(7) +                       \
                       inv2_ * (quad_ + SECOND_TERM(M, x, y, z, xx_, yy_, zz_, xy_, inv2_))); \
    } while (0)
#if ORDER == 2
#define SECOND_TERM(M, x, y, z, xx, yy, zz, xy, inv2)                                      \
    (M(14) * (x) + M(15) * (y) + M(16) * (z) +                                             \
     (inv2) * (M(17) * (xx) * (x) + M(18) * (yy) * (y) + M(19) * (zz) * (z) +              \
               M(20) * (xx) * (y) + M(21) * (xx) * (z) + M(22) * (yy) * (x) +              \
               M(23) * (yy) * (z) + M(24) * (zz) * (x) + M(25) * (zz) * (y) +              \
               M(26) * (xy) * (z)))
#else
#define SECOND_TERM(M, x, y, z, xx, yy, zz, xy, inv2) 0.0f
#endif

/* atan2_poly lane by lane, by the same operations, with masks for its choices
 * (PoCL 3 calls select() out of line), into `out`: over vectors of type T
 * (integer vectors IT, AS_T / AS_IT their reinterpretations). A macro, not a
 * function: no vector of more than 32 bytes may cross a call on PoCL 3, and
 * clang warns of one even where the call is inlined. */
#define ATAN2_LANES(T, IT, AS_T, AS_IT, y, x, out)                                         \
    T out;                                                                                 \
    do {                                                                                   \
        const IT atan_abs_ = (IT)(0x7fffffff);                                             \
        const T atan_ax_ = AS_T(AS_IT(x) & atan_abs_);                                     \
        const T atan_ay_ = AS_T(AS_IT(y) & atan_abs_);                                     \
        const IT atan_steep_ = atan_ay_ > atan_ax_;                                        \
        const T atan_num_ =                                                                \
            AS_T((AS_IT(atan_ax_) & atan_steep_) | (AS_IT(atan_ay_) & ~atan_steep_));      \
        const T atan_den_ =                                                                \
            AS_T((AS_IT(atan_ay_) & atan_steep_) | (AS_IT(atan_ax_) & ~atan_steep_));      \
        const T atan_t_ = AS_T(AS_IT(atan_num_ / atan_den_) & (atan_den_ != (T)(0.0f)));   \
        const T atan_s_ = atan_t_ * atan_t_;                                               \
        T atan_a_ = ATAN_P(atan_s_);                                                       \
        atan_a_ *= atan_t_;                                                                \
        atan_a_ = AS_T((AS_IT((T)(M_PI_2_F) - atan_a_) & atan_steep_) |                    \
                       (AS_IT(atan_a_) & ~atan_steep_));                                   \
        const IT atan_negative_ = AS_IT(x) < (IT)(0);                                      \
        atan_a_ = AS_T((AS_IT((T)(M_PI_F) - atan_a_) & atan_negative_) |                   \
                       (AS_IT(atan_a_) & ~atan_negative_));                                \
        out = AS_T(AS_IT(atan_a_) | (AS_IT(y) & (IT)(0x80000000)));                        \
    } while (0)

/* solid_angle lane by lane, of the triangles whose corners minus q are a, b, c
 * (components of type T, integer vectors IT), into `out`: the same operations,
 * the corners already in solid_angle's order (the corner rows are stored so:
 * winding_moments.py lane_corners). */
#define SOLID_ANGLES(T, IT, AS_T, AS_IT, SQRT, ax, ay, az, bx, by, bz, cx, cy, cz, out)   \
    T out;                                                                                 \
    do {                                                                                   \
        const T la2_ = ax * ax + ay * ay + az * az;                                        \
        const T lb2_ = bx * bx + by * by + bz * bz;                                        \
        const T lc2_ = cx * cx + cy * cy + cz * cz;                                        \
        const T la_ = SQRT(la2_), lb_ = SQRT(lb2_), lc_ = SQRT(lc2_);                      \
        const T num_ = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) +               \
                       az * (bx * cy - by * cx);                                           \
        const T den_ = (la_ * (lb_ * lc_) + (bx * cx + by * cy + bz * cz) * la_) +           \
                       ((ax * bx + ay * by + az * bz) * lc_ + (ax * cx + ay * cy + az * cz) * lb_); \
        ATAN2_LANES(T, IT, AS_T, AS_IT, num_, den_, half_);                                \
        out = AS_T(AS_IT((T)(2.0f) * half_) & (num_ != (T)(0.0f)));                        \
    } while (0)

/* The exact solid angles of the triangles of slots [first, end), added to w. */
#define LEAF_SUM(first, end)                                                               \
    for (int s = (first); s < (end); ++s)                                                  \
        w += solid_angle(q, load_float3(vertices, slot_faces[3 * s]),                      \
                         load_float3(vertices, slot_faces[3 * s + 1]),                     \
                         load_float3(vertices, slot_faces[3 * s + 2]), scale);

/* The arguments of both kernels (lbvh/queries/winding.py passes the same). */
#define WINDING_ARGS                                                                       \
    __global const float4 *nodes, __global const float *moments,                           \
        __global const float *vertices, __global const uint *slot_faces, const int root,   \
        const int root_y, const int num_nodes, __global const float *points,               \
        __global const int *order, const int count, const float beta2,                     \
        const float floor_scale, const float scale, __global float *winding,               \
        __global int *flags

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

inline floatw atan2_polyw(floatw y, floatw x) {
    ATAN2_LANES(floatw, intw, as_floatw, as_intw, y, x, a);
    return a;
}

/* A record's moment row j, all lanes (the per-point walk) or lane c (`ml`, the
 * packets' walk). */
#define ROW_W(j) m[j]
#define ROW_L(j) ml[(j) * WIDTH]

/* The packets' walk (winding_packets): PACKET = 16 points a work-item, one
 * float16 a coordinate. */
#define PACKET 16
typedef float16 floatp;
typedef int16 intp;
typedef union { floatp v; float s[PACKET]; } floatp_lanes;
/* The helpers of float16 and int16 values are macros, not functions: no vector
 * of more than 32 bytes may cross a call on PoCL 3 (kernels compiled for a
 * target without AVX-512 pass it differently), and clang warns of one even
 * where the call is inlined. */
#if INLINE_SQRT
/* common.h's inline square root, 16 lanes (of a variable: v is read 16 times) */
#define SQRTP(v)                                                                           \
    ((float16)(__builtin_sqrtf((v).s0), __builtin_sqrtf((v).s1), __builtin_sqrtf((v).s2),    \
               __builtin_sqrtf((v).s3), __builtin_sqrtf((v).s4), __builtin_sqrtf((v).s5),    \
               __builtin_sqrtf((v).s6), __builtin_sqrtf((v).s7), __builtin_sqrtf((v).s8),    \
               __builtin_sqrtf((v).s9), __builtin_sqrtf((v).sa), __builtin_sqrtf((v).sb),    \
               __builtin_sqrtf((v).sc), __builtin_sqrtf((v).sd), __builtin_sqrtf((v).se),    \
               __builtin_sqrtf((v).sf)))
#else
/* by halves: common.h's sqrt8 (the OpenCL builtin there) takes 32 bytes, not 64 */
#define SQRTP(v) ((float16)(sqrt8((v).lo), sqrt8((v).hi)))
#endif
#define as_floatp as_float16
#define as_intp as_int16

/* The least (LESS <) or the largest (>) lane of v into `out`, by comparisons
 * (fmin and fmax PoCL 3 calls out of line). */
#define LANES_EXTREME(v, LESS, out)                                                        \
    float out;                                                                             \
    do {                                                                                   \
        const float8 a8_ = (v).lo LESS (v).hi ? (v).lo : (v).hi;                           \
        const float4 a4_ = a8_.lo LESS a8_.hi ? a8_.lo : a8_.hi;                           \
        const float2 a2_ = a4_.lo LESS a4_.hi ? a4_.lo : a4_.hi;                           \
        out = a2_.x LESS a2_.y ? a2_.x : a2_.y;                                            \
    } while (0)

/* A packet's lanes as 16 bits (of a comparison's lanes, 0 or -1), and back. */
#define PACKET_BITS_OF(v, out)                                                             \
    uint out;                                                                              \
    do {                                                                                   \
        const intp b16_ = (v) & (intp)(1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024, 2048,   \
                                       4096, 8192, 16384, 32768);                          \
        const int8 b8_ = b16_.lo | b16_.hi;                                                \
        const int4 b4_ = b8_.lo | b8_.hi;                                                  \
        const int2 b2_ = b4_.lo | b4_.hi;                                                  \
        out = (uint)(b2_.x | b2_.y);                                                       \
    } while (0)
#define PACKET_MASK(bits)                                                                  \
    (((intp)((int)(bits)) & (intp)(1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024, 2048, 4096, \
                                   8192, 16384, 32768)) != (intp)(0))

/* The exact solid angles at the packet's points of the triangle with corners
 * (scalars) p0, p1, p2, added to w where `mask` (a comparison's lanes) is set. */
#define PACKET_TRIANGLE(p0x, p0y, p0z, p1x, p1y, p1z, p2x, p2y, p2z, mask)                 \
    do {                                                                                   \
        const floatp ax = DIFF((floatp)(p0x), qx), ay = DIFF((floatp)(p0y), qy),           \
                     az = DIFF((floatp)(p0z), qz);                                         \
        const floatp bx = DIFF((floatp)(p1x), qx), by = DIFF((floatp)(p1y), qy),           \
                     bz = DIFF((floatp)(p1z), qz);                                         \
        const floatp cx = DIFF((floatp)(p2x), qx), cy = DIFF((floatp)(p2y), qy),           \
                     cz = DIFF((floatp)(p2z), qz);                                         \
        SOLID_ANGLES(floatp, intp, as_floatp, as_intp, SQRTP, ax, ay, az, bx, by, bz, cx, cy, \
                     cz, sa);                                                              \
        w += as_floatp(as_intp(sa) & (mask));                                              \
    } while (0)
/* ... of the triangles of slots [first, end) */
#define PACKET_LEAF(first, end, mask)                                                      \
    for (int s = (first); s < (end); ++s) {                                                \
        const float3 c0 = load_float3(vertices, slot_faces[3 * s]);                        \
        const float3 c1 = load_float3(vertices, slot_faces[3 * s + 1]);                    \
        const float3 c2 = load_float3(vertices, slot_faces[3 * s + 2]);                    \
        const int least = least_corner(c0, c1, c2);  /* solid_angle's order */             \
        if (least < 0) continue;                                                           \
        const float3 s0 = least == 0 ? c0 : (least == 1 ? c1 : c2);                        \
        const float3 s1 = least == 0 ? c1 : (least == 1 ? c2 : c0);                        \
        const float3 s2 = least == 0 ? c2 : (least == 1 ? c0 : c1);                        \
        const float3 u0 = s0 * scale, u1 = s1 * scale, u2 = s2 * scale;                   \
        PACKET_TRIANGLE(u0.x, u0.y, u0.z, u1.x, u1.y, u1.z, u2.x, u2.y, u2.z, mask);       \
    }
#endif

__kernel void winding_numbers(WINDING_ARGS) {
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
                    /* the far lanes' expansions (Barill et al. 2018), as the binary walk's;
                     * the term where far, +0 elsewhere: a mask, not select(), which PoCL 3
                     * calls out of line */
                    FAR_TERM(floatw, ROW_W, rx, ry, rz, r2, r1, term);
                    wv += as_floatw(as_intw(term) & far_lanes);
                }
                if (lane_bits(near_leaves) != 0u) {
                    /* the corner rows: each lane's first triangle */
                    __global const floatw *c = m + ROWS;
                    const floatw qx = (floatw)(q.x), qy = (floatw)(q.y), qz = (floatw)(q.z);
                    const floatw ax = DIFF(c[0], qx), ay = DIFF(c[1], qy), az = DIFF(c[2], qz);
                    const floatw bx = DIFF(c[3], qx), by = DIFF(c[4], qy), bz = DIFF(c[5], qz);
                    const floatw cx = DIFF(c[6], qx), cy = DIFF(c[7], qy), cz = DIFF(c[8], qz);
                    SOLID_ANGLES(floatw, intw, as_floatw, as_intw, SQRTW, ax, ay, az, bx, by, bz,
                                 cx, cy, cz, sa);
                    wv += as_floatw(as_intw(sa) & near_leaves);
                }
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
#define ROW_B(j) m[j]
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
                FAR_TERM(float, ROW_B, r.x, r.y, r.z, r2, r1, term);
                w += term;
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

#if WIDE
/* The same sums for PACKET points at once, a work-item a packet (the host's
 * choice on a CPU, lbvh/queries/winding.py use_packets; with the points in
 * their Morton order, nearby points share a packet). The walk goes through the
 * wide records as the per-point walk does, but its vectors are the packet's 16
 * points, not a record's lanes, each point with the same tests as its own walk:
 * a lane is expanded for the points far from it and opened for the others (a
 * leaf summed exactly, a record pushed with the bits of the points that walk
 * it). A point's terms are added in the lanes' order whatever its companions,
 * so its sum is the same in any packet (not the per-point kernel's, whose
 * lanes are summed in another order). On Sponza's 1M bench points a packet
 * visits 1.12x the nodes one point does (a simulation of the binary walk), and
 * its arithmetic is 16 points wide where the per-point walk leaves most lanes
 * idle near the surface: about 2x the points per second (bench/README.md).
 *
 * A record's lanes near the packet's whole sphere (centre q0, the middle of
 * the points' box, radius rho) are found in one vector computation, and opened
 * without the points' own tests: past the sphere's bound plus a relative slack
 * of 1e-6 (rho too carries 1e-6, far more than their float32 rounding), every
 * point's own test says near as well.
 *
 * The packet's points are read as three float16 from `points` + 3 * first,
 * which the host makes sure is 64-byte aligned (a whole buffer's start, first
 * a multiple of 16); a last, partial packet reads its points one by one, and
 * its spare lanes repeat its last point but walk nothing. */
__kernel void winding_packets(WINDING_ARGS) {
    const int first = get_global_id(0) * PACKET;
    if (first >= count) return;
    floatp qx, qy, qz;
    if (first + PACKET <= count) {
        __global const float16 *pv = (__global const float16 *)(points + 3 * first);
        const float16 a = pv[0], b = pv[1], c = pv[2];     /* x y z interleaved */
        qx = (float16)(a.s0, a.s3, a.s6, a.s9, a.sc, a.sf, b.s2, b.s5, b.s8, b.sb, b.se,
                       c.s1, c.s4, c.s7, c.sa, c.sd);
        qy = (float16)(a.s1, a.s4, a.s7, a.sa, a.sd, b.s0, b.s3, b.s6, b.s9, b.sc, b.sf,
                       c.s2, c.s5, c.s8, c.sb, c.se);
        qz = (float16)(a.s2, a.s5, a.s8, a.sb, a.se, b.s1, b.s4, b.s7, b.sa, b.sd, c.s0,
                       c.s3, c.s6, c.s9, c.sc, c.sf);
    } else {
        floatp_lanes sx, sy, sz;
        for (int j = 0; j < PACKET; ++j) {
            const int k = first + j < count ? first + j : count - 1;
            sx.s[j] = points[3 * k];
            sy.s[j] = points[3 * k + 1];
            sz.s[j] = points[3 * k + 2];
        }
        qx = sx.v;
        qy = sy.v;
        qz = sz.v;
    }
    LANES_EXTREME(qx, <, lox);
    LANES_EXTREME(qy, <, loy);
    LANES_EXTREME(qz, <, loz);
    LANES_EXTREME(qx, >, hix);
    LANES_EXTREME(qy, >, hiy);
    LANES_EXTREME(qz, >, hiz);
    const float3 lo = (float3)(lox, loy, loz), hi = (float3)(hix, hiy, hiz);
    const float3 q0 = 0.5f * (lo + hi);
    const float3 span = DIFF(hi, q0);
    const float rho = sqrt1(dot3(span, span)) * 1.000001f;
    const int n = count - first < PACKET ? count - first : PACKET;
    floatp w = (floatp)(0.0f);
    int flag = 0;
    int stack[STACK_SIZE];
    ushort stack_bits[STACK_SIZE];
    int top = 0, visits = 0;
    uint act = (1u << n) - 1u;    /* the points that walk the record (not the spare lanes) */
    __global const int *words = (__global const int *)nodes;
    __global const floatw *rows = (__global const floatw *)moments;
    if (node_is_leaf(root_y)) {     /* a root leaf: no records */
        PACKET_LEAF(root, root - root_y, PACKET_MASK(act));
    } else {
        int record = root;
        for (;;) {
            if (visits++ < num_nodes) {
                __global const floatw *m = rows + RECORD_ROWS * record;
                const intp active = PACKET_MASK(act);
                /* the lanes near the whole sphere: near every point, by its own test too */
                const floatw rx = DIFF(m[0], (floatw)(q0.x)), ry = DIFF(m[1], (floatw)(q0.y)),
                             rz = DIFF(m[2], (floatw)(q0.z));
                const floatw d0 = SQRTW(rx * rx + ry * ry + rz * rz);
                const floatw ub = d0 + (floatw)(rho) + d0 * (floatw)(1.0e-6f);
                const floatw ub2 = ub * ub;
                const uint near_all =
                    lane_bits((ub2 <= (floatw)(beta2) * m[3]) |
                              (ub2 * ub2 * ub < (floatw)(floor_scale) * m[FLOOR_ROW]));
                __global const int *ref = words + 8 * WIDTH * record + 6 * WIDTH;
                /* the lanes in their order, whatever the packet: a point's terms are
                 * added in the same order as in a packet of its own */
                for (uint bits = lane_bits(m[3] >= (floatw)(0.0f)); bits != 0u;
                     bits &= bits - 1u) {
                    const int c = lowest_lane(bits);
                    __global const float *ml = (__global const float *)m + c;
                    intp near = active;
                    if (!((near_all >> c) & 1u)) {
                        /* each point's own test (Barill et al. 2018), and the
                         * expansion where it is far */
                        const floatp px = DIFF((floatp)(ROW_L(0)), qx),
                                     py = DIFF((floatp)(ROW_L(1)), qy),
                                     pz = DIFF((floatp)(ROW_L(2)), qz);
                        const floatp r2 = px * px + py * py + pz * pz;
                        const floatp r1 = SQRTP(r2);
                        const intp far = active & (r2 > (floatp)(beta2 * ROW_L(3))) &
                                         (r2 * r2 * r1 >= (floatp)(floor_scale * ROW_L(FLOOR_ROW)));
                        PACKET_BITS_OF(far, far_bits);
                        if (far_bits != 0u) {
                            FAR_TERM(floatp, ROW_L, px, py, pz, r2, r1, term);
                            w += as_floatp(as_intp(term) & far);
                            near = active & ~far;
                        }
                    }
                    PACKET_BITS_OF(near, near_bits);
                    if (near_bits == 0u) continue;
                    const int x = ref[c], y = ref[WIDTH + c];
                    if (node_is_leaf(y)) {
                        PACKET_TRIANGLE(ROW_L(ROWS), ROW_L(ROWS + 1), ROW_L(ROWS + 2),
                                        ROW_L(ROWS + 3), ROW_L(ROWS + 4), ROW_L(ROWS + 5),
                                        ROW_L(ROWS + 6), ROW_L(ROWS + 7), ROW_L(ROWS + 8), near);
                        PACKET_LEAF(x + 1, x - y, near);
                    } else if (top < STACK_SIZE) {
                        stack[top] = x;
                        stack_bits[top++] = (ushort)near_bits;
#if CLANG_PREFETCH && defined(__clang__)
                        /* the record's test rows and references asked into the cache:
                         * a pushed record is often the next one walked (1.1x on a 1M
                         * terrain, bench/README.md) */
                        __global const float *next = moments + RECORD_ROWS * WIDTH * x;
                        __builtin_prefetch(next);
                        __builtin_prefetch(next + 16);
                        __builtin_prefetch(next + FLOOR_ROW * WIDTH);
                        __builtin_prefetch(words + 8 * WIDTH * x + 6 * WIDTH);
#endif
                    } else {
                        flag |= FLAG_OVERFLOW;
                    }
                }
            }
            if (top == 0) break;
            --top;
            record = stack[top];
            act = stack_bits[top];
        }
    }
    floatp_lanes out;
    out.v = w * (floatp)(0.25f * M_1_PI_F);
    for (int j = 0; j < n; ++j) {
        const int i = point_index(order, first + j);
        winding[i] = out.s[j];
        flags[i] = flag;
    }
}
#endif
