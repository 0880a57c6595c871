/* One ray against boxes and triangles: the ray's constants, the slab test of a
 * box and the watertight triangle test, shared by the ray queries
 * (kernels/traverse.cl: closest and any hit; kernels/all_hits.cl: every hit
 * and the hit counts; kernels/instances.cl and kernels/instance_hits.cl: the
 * same through a scene of instances).
 *
 * Compile-time choices (-D), all optional:
 *   TRIANGLE_TEST=0  watertight test of Woop, Benthin, Wald 2013 (default),
 *                    its decisions exact where the device has doubles
 *   TRIANGLE_TEST=1  Moller-Trumbore 1997 (faster, leaks through shared edges)
 *   SLAB_PAD=x       factor on the far distance of a box (Ize 2013)
 *   NO_FP64=1        the watertight test in float32 only, as on devices
 *                    without doubles (decisions rounded, not exact)
 *   EDGE_RULE=1      a ray through an edge or a vertex hits exactly one of the
 *                    triangles around it (see ruled_inside); the default
 *                    accepts it in every one of them
 */
#ifndef LBVH_RAY_TRIANGLE_H
#define LBVH_RAY_TRIANGLE_H
#include "common.h"

#define TEST_WATERTIGHT 0
#define TEST_MOLLER 1
#ifndef TRIANGLE_TEST
#define TRIANGLE_TEST TEST_WATERTIGHT
#endif
#ifndef SLAB_PAD
/* 1 + 2 gamma(3), gamma(n) = n u / (1 - n u), u = 2^-24, rounded up to float. */
#define SLAB_PAD 0x1.000008p+0f
#endif

#define FLAG_OVERFLOW 1    /* a push found the stack full: a subtree was skipped */
#define FLAG_VISIT_LIMIT 2 /* more nodes visited than the tree has: not a tree */
#define FLAG_NAN_RAY 4     /* NaN in the ray: not traced (the host API refuses such rays) */

/* Doubles where the device has them (-DNO_FP64 leaves them out, to test the
 * path of devices without them): the exact decisions (exact.h). */
#if defined(cl_khr_fp64) && !defined(NO_FP64)
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#define EXACT_FP64 1
#include "exact.h"
#if TRIANGLE_TEST == TEST_WATERTIGHT
#define WATERTIGHT_FP64 1
#endif
#endif

#ifndef EDGE_RULE
#define EDGE_RULE 0
#endif

/* EDGE_RULE: the sign of the edge function F = P x Q of the 2D sheared vertices
 * P, Q (relative to the ray) where F is exactly 0, taken at the ray moved off
 * its line by (eps, eps^2) for an infinitesimal eps (simulation of simplicity,
 * Edelsbrunner & Muecke 1990): (P - q) x (Q - q) = F + eps (Py - Qy) +
 * eps^2 (Qx - Px). Two triangles sharing an edge compute the same F and the
 * same differences with the opposite sign, so the moved ray lies inside
 * exactly one of them where the ray crosses the surface (at an edge, or at a
 * vertex: one triangle of the fan), and in none or both where it only touches
 * it (a silhouette: the parity of the crossings is kept). 0: the edge is a
 * point in 2D (such a triangle has det = 0 and is missed anyway). Comparisons
 * only: the signs of the differences are exact in any precision. */
#define SIGN_OF(a, b) (((a) > (b)) - ((a) < (b)))   /* 1, -1, or 0 (equal, or NaN) */
/* s, or t where s is 0, or u where both are: by masks, without branches (the
 * nested conditionals compiled to three unpredictable branches per triangle) */
inline int first_nonzero(int s, int t, int u) {
    return s | (-(s == 0) & (t | (-(t == 0) & u)));
}
#define EDGE_SIGN(F, px, py, qx, qy) first_nonzero(SIGN_OF(F, 0), SIGN_OF(py, qy), SIGN_OF(qx, px))
inline int same_signs(int a, int b, int c) { return (a == b) & (b == c) & (a != 0); }
/* U = c x b, V = a x c, W = b x a (hit_triangle): whether the ray, moved, is
 * inside; without EDGE_RULE, whether no two of U, V, W have opposite signs. */
#if EDGE_RULE
#define RAY_INSIDE(U, V, W, ax, ay, bx, by, cx, cy) \
    same_signs(EDGE_SIGN(U, cx, cy, bx, by), EDGE_SIGN(V, ax, ay, cx, cy), \
               EDGE_SIGN(W, bx, by, ax, ay))
#else
#define RAY_INSIDE(U, V, W, ax, ay, bx, by, cx, cy) \
    (!((((U) < 0) | ((V) < 0) | ((W) < 0)) & (((U) > 0) | ((V) > 0) | ((W) > 0))))
#endif

/* The hot loop is written with comparisons instead of fmin/fmax/select/vload3:
 * PoCL calls those builtins out of line, which cost half the time. */

/* max and min keeping m when x is NaN (m is never NaN): fmax/fmin semantics. */
inline float max_keep(float x, float m) { return x > m ? x : m; }
inline float min_keep(float x, float m) { return x < m ? x : m; }

typedef struct {
    float ox, oy, oz, dx, dy, dz;
    float ix, iy, iz;   /* 1/d: +-inf for +-0, and where 1/d overflows */
    /* 1/d for the near planes: +-FLT_MAX where 1/d overflows but d != 0 (see
     * make_ray); +-inf for +-0 as ix, iy, iz. */
    float jx, jy, jz;
    /* Offsets (in floats) of the near and far plane of each axis in a node
     * record: the sign bit of d picks them, so -0.0 counts as negative like
     * 1/-0 = -inf (Williams et al. 2005; pbrt's dirIsNeg). */
    int nx, ny, nz, fx, fy, fz;
    float tmin, tmax;
    /* Woop 2013, section 3: permutation making kz the dominant axis (kx, ky
     * swapped when d[kz] < 0 to keep the winding), the origin permuted, and
     * the shear constants, taken times d_kz (see make_ray): ex, ey, ez are
     * d_kx, d_ky, d_kz times a power of two, sz = 1 / d_kz. */
    int kx, ky, kz;
    float px, py, pz;
    /* t is measured along d * 2^-texp (see make_ray); 0 for ordinary rays. */
    int texp;
    float ex, ey, ez, sz;
    /* 1: d_kx or d_ky would lose bits in that power of two (shears below
     * float32's normal range): the triangle test runs in double. */
    int hard;
    /* jx.., ix.. and the sign bits of d in the order kx, ky, kz (accept_hit) */
    float jkx, jky, jkz, ikx, iky, ikz;
    int nkx, nky, nkz;
} Ray;

inline float axis(float x, float y, float z, int k) { return k == 0 ? x : (k == 1 ? y : z); }

/* The largest n for which c * 2^-n is exact (c's lowest set bit stays at or
 * above 2^-149); large for c = 0. */
inline int exact_shift(float c) {
    if (c == 0.0f) return 1 << 20;
    const uint bits = as_uint(c);
    const uint biased = (bits >> 23) & 0xffu;
    uint m = bits & 0x7fffffu;
    if (biased != 0u) m |= 0x800000u;
    /* c = m * 2^(max(biased, 1) - 150); m & -m is m's lowest set bit */
    const int lowest = 31 - (int)clz(m & (0u - m));
    return lowest + (biased != 0u ? (int)biased : 1) - 150 + 149;
}

/* The constants of a ray whose ox, oy, oz, dx, dy, dz, tmin and tmax are set
 * (make_ray reads them from the rays' arrays; kernels/instances.cl sets them
 * to a ray moved into an instance's space). *ray is a struct passed by
 * pointer, written in place: no value wider than 32 bytes crosses a function
 * boundary, and nothing is copied. */
/* make_ray and prepare_ray forced inline where the compiler is clang (PoCL):
 * PoCL 3 kept prepare_ray out of line, 3-9% of the traversal's samples, the
 * Ray written through memory; inline, 1.01-1.09x on the bench scenes' camera
 * rays, closest and any hit (bench/README.md). */
#if defined(__clang__)
#define PREPARE_ATTR __attribute__((always_inline))
#else
#define PREPARE_ATTR
#endif
inline PREPARE_ATTR void prepare_ray(Ray *ray) {
    /* A direction far from unit length (tiny or denormal components, or
     * huge ones) makes 1/d and the shear constants leave float32's range.
     * Scaling d by a power of two (and t the other way) is exact, so such a
     * ray is traced as d * 2^-texp and its t scaled back at the end. */
    ray->texp = 0;
    /* max_keep: a NaN component is ignored, as by fmax (such a ray is not traced) */
    const float dmax = max_keep(max_keep(abs_bits(ray->dx), abs_bits(ray->dy)), abs_bits(ray->dz));
    if (dmax < 0x1p-60f || dmax > 0x1p60f) {
        /* Only as far as back into [2^-60, 2^60]: the least change of t's
         * scale, so t itself neither overflows nor underflows. */
        int e;
        (void)frexp(dmax, &e);
        e = e > 0 ? e - 60 : e + 59;
        ray->texp = e;
        ray->dx = ldexp(ray->dx, -e); ray->dy = ldexp(ray->dy, -e); ray->dz = ldexp(ray->dz, -e);
        ray->tmin = ldexp(ray->tmin, e); ray->tmax = ldexp(ray->tmax, e);
    }
    ray->ix = 1.0f / ray->dx;
    ray->iy = 1.0f / ray->dy;
    ray->iz = 1.0f / ray->dz;
    /* A component below 2^-128 (after the scaling above, the others may be up
     * to 2^60) has 1/d = +-inf: the far plane's distance +-inf is still a
     * bound on the exact one (+inf ahead of the origin; -inf behind it, where
     * the box is behind the ray as the exact distance says), but +inf for a
     * near plane ahead of the origin would cull a box the ray enters at a
     * finite t. The near planes use +-FLT_MAX instead: |FLT_MAX| <= |1/d|, so
     * the near distance only shrinks, and the entry stays a lower bound. */
    ray->jx = ray->dx > 0.0f && ray->ix > FLT_MAX ? FLT_MAX : (ray->dx < 0.0f && ray->ix < -FLT_MAX ? -FLT_MAX : ray->ix);
    ray->jy = ray->dy > 0.0f && ray->iy > FLT_MAX ? FLT_MAX : (ray->dy < 0.0f && ray->iy < -FLT_MAX ? -FLT_MAX : ray->iy);
    ray->jz = ray->dz > 0.0f && ray->iz > FLT_MAX ? FLT_MAX : (ray->dz < 0.0f && ray->iz < -FLT_MAX ? -FLT_MAX : ray->iz);
    const int negx = as_int(ray->dx) < 0, negy = as_int(ray->dy) < 0, negz = as_int(ray->dz) < 0;
    ray->nx = negx ? 4 : 0; ray->fx = 4 - ray->nx;
    ray->ny = negy ? 5 : 1; ray->fy = 6 - ray->ny;
    ray->nz = negz ? 6 : 2; ray->fz = 8 - ray->nz;
    const float ax = abs_bits(ray->dx), ay = abs_bits(ray->dy), az = abs_bits(ray->dz);
    const int kz = ax >= ay ? (ax >= az ? 0 : 2) : (ay >= az ? 1 : 2);
    int kx = kz == 2 ? 0 : kz + 1;
    int ky = kx == 2 ? 0 : kx + 1;
    const float dz = axis(ray->dx, ray->dy, ray->dz, kz);
    if (dz < 0.0f) { const int s = kx; kx = ky; ky = s; }
    ray->kx = kx; ray->ky = ky; ray->kz = kz;
    ray->px = axis(ray->ox, ray->oy, ray->oz, kx);
    ray->py = axis(ray->ox, ray->oy, ray->oz, ky);
    ray->pz = axis(ray->ox, ray->oy, ray->oz, kz);
    /* Woop 2013 shears by Sx = d_kx / d_kz and Sy = d_ky / d_kz; here the
     * sheared coordinates are taken times d_kz (times a power of two 2^-e):
     * x = ez p_kx - ex p_kz, y = ez p_ky - ey p_kz with (ex, ey, ez) =
     * (d_kx, d_ky, d_kz) 2^-e (hit_triangle). That multiplies every edge
     * function by ez^2 > 0 (signs, barycentrics and t unchanged) and has no
     * quotient to round: a vertex exactly on the ray's line (p = s d) gets
     * exactly (0, 0), since both products are the same real number, and no
     * shear underflows (d_kx / d_kz below 2^-126 rounded, or flushed to 0,
     * moved vertices by 2^-150 |p_kz|, and rays along an edge or past a sliver
     * hit it). e brings |ez| into [0.5, 1), so the coordinates stay within
     * |p_kx| + |p_kz| as with the quotients, where that is exact: a direction
     * component that would lose bits (a shear below float32's normal range)
     * makes the ray `hard`: its triangle tests run in double with d as it is
     * (without doubles: scaled only as far as is exact). */
    const float dx_k = axis(ray->dx, ray->dy, ray->dz, kx);
    const float dy_k = axis(ray->dx, ray->dy, ray->dz, ky);
    /* |dz| = m 2^e, m in [0.5, 1) (frexp's e, from the bits: dz is normal, in
     * [2^-60, 2^60] after the scaling above); the powers of two 2^-e and 2^e
     * are normal floats, the products by them exact unless one underflows,
     * which the round trip shows (no frexp/ldexp: PoCL calls them out of line). */
    int e = (int)((as_uint(dz) >> 23) & 0xffu) - 126;
    float down = as_float((uint)(127 - e) << 23), up = as_float((uint)(127 + e) << 23);
    ray->hard = 0;
    if (e > 0 && ((dx_k * down) * up != dx_k || (dy_k * down) * up != dy_k)) {
        ray->hard = 1;
#ifdef WATERTIGHT_FP64
        e = 0;
#else
        e = min(e, min(exact_shift(dx_k), exact_shift(dy_k)));
#endif
        down = as_float((uint)(127 - e) << 23);
    }
    ray->ex = dx_k * down;
    ray->ey = dy_k * down;
    ray->ez = dz * down;
    ray->sz = axis(ray->ix, ray->iy, ray->iz, kz);   /* 1 / dz */
    ray->jkx = axis(ray->jx, ray->jy, ray->jz, kx);
    ray->jky = axis(ray->jx, ray->jy, ray->jz, ky);
    ray->jkz = ray->sz;   /* dz is normal: jz = iz */
    ray->ikx = axis(ray->ix, ray->iy, ray->iz, kx);
    ray->iky = axis(ray->ix, ray->iy, ray->iz, ky);
    ray->ikz = ray->sz;
    ray->nkx = as_int(dx_k) < 0;
    ray->nky = as_int(dy_k) < 0;
    ray->nkz = as_int(dz) < 0;
}

/* Fills *ray from origin o, direction d and the interval [tmin, tmax]. */
inline PREPARE_ATTR void make_ray(Ray *ray, __global const float *o, __global const float *d,
                                  float tmin, float tmax) {
    ray->ox = o[0]; ray->oy = o[1]; ray->oz = o[2]; ray->tmin = tmin;
    ray->dx = d[0]; ray->dy = d[1]; ray->dz = d[2]; ray->tmax = tmax;
    prepare_ray(ray);
}

/* Whether any of the ray's origin, direction or interval is NaN. Such a ray would
 * pass every slab test (NaN distances are ignored), empty lanes of wide records
 * included: the walks report it (FLAG_NAN_RAY) instead of tracing it. */
inline int ray_has_nan(const Ray *ray) {
    return ray->ox != ray->ox || ray->oy != ray->oy || ray->oz != ray->oz ||
           ray->dx != ray->dx || ray->dy != ray->dy || ray->dz != ray->dz ||
           ray->tmin != ray->tmin || ray->tmax != ray->tmax;   /* isnan */
}

/* Slab test (Kay-Kajiya) of the box record at `box`
 * (lower.xyz, word, upper.xyz, word), made robust:
 * - near and far planes picked by the sign bit of d (-0.0 is negative);
 * - an origin on a slab plane with a zero direction component gives
 *   0 * inf = NaN on that axis; max_keep/min_keep ignore it, so that axis does
 *   not bound the ray, which is right: the origin lies on the closed slab;
 * - a flat box (lower == upper on an axis) is accepted with entry == exit;
 * - a direction component whose 1/d overflows: the near planes' distances
 *   use +-FLT_MAX (jx, jy, jz; see make_ray), the far planes' +-inf;
 * - the far distance is multiplied by 1 + 2 gamma(3) (Ize 2013, "Robust BVH
 *   Ray Traversal", JCGT 2(2)), which covers the rounding of the subtraction,
 *   the reciprocal and the product, so no box containing a hit is lost.
 * Returns whether [entry, exit] meets [ray.tmin, limit]; *leave is the box's
 * own exit distance (unpadded), used to order children of equal entry. */
inline int slab(__global const float *box, const Ray *ray, float limit,
                float *entry, float *leave) {
    float t0 = ray->tmin;
    t0 = max_keep((box[ray->nx] - ray->ox) * ray->jx, t0);
    t0 = max_keep((box[ray->ny] - ray->oy) * ray->jy, t0);
    t0 = max_keep((box[ray->nz] - ray->oz) * ray->jz, t0);
    float t1 = INFINITY;
    t1 = min_keep((box[ray->fx] - ray->ox) * ray->ix, t1);
    t1 = min_keep((box[ray->fy] - ray->oy) * ray->iy, t1);
    t1 = min_keep((box[ray->fz] - ray->oz) * ray->iz, t1);
    *entry = t0;
    *leave = t1;
    return t0 <= min_keep(t1, limit) * SLAB_PAD;
}

/* Zero-area triangles (repeated or collinear vertices) are never hit.
 * Where the device has doubles (EXACT_FP64) a triangle is degenerate exactly
 * when its three points lie on a line: the three 2D orientations of its
 * projections on the axis planes (the components of (b - a) x (c - a)) are
 * exactly zero (exact.h), which depends on the triangle as a set of points
 * only, neither on the order of its corners nor on a scale by a power of two.
 * The watertight test below then needs no such test (its decisions are exact,
 * and a collinear triangle's edge functions are all exactly zero or of two
 * signs); order_triangles uses it to store degenerate triangles as points.
 * Without doubles the approximation of old: degenerate when
 * |e1 x e2| <= 2^-20 |e1| |e2|, the edges from the first corner scaled to a
 * largest component of 1, which also takes slivers thinner than 2^-20 of
 * their length for lines. DEGENERATE_TEST=0 leaves the test out of
 * accept_hit, for triangles read from traverse.cl's order_triangles, which has
 * made each degenerate one a point (its three corners its first: no hit). */
#ifndef DEGENERATE_TEST
#define DEGENERATE_TEST 1
#endif
#ifdef EXACT_FP64
inline int degenerate(__global const float *vertices, int i0, int i1, int i2) {
    const float ax = vertices[i0], ay = vertices[i0 + 1], az = vertices[i0 + 2];
    const float bx = vertices[i1], by = vertices[i1 + 1], bz = vertices[i1 + 2];
    const float cx = vertices[i2], cy = vertices[i2 + 1], cz = vertices[i2 + 2];
    return orient2d_is_zero(ax, ay, bx, by, cx, cy) && orient2d_is_zero(ay, az, by, bz, cy, cz) &&
           orient2d_is_zero(az, ax, bz, bx, cz, cx);
}
#else
#define DEGENERATE_SINE2 0x1p-40f
inline float max_abs3(float x, float y, float z) {
    x = x < 0.0f ? -x : x;
    y = y < 0.0f ? -y : y;
    z = z < 0.0f ? -z : z;
    return x > y ? (x > z ? x : z) : (y > z ? y : z);
}
inline int degenerate(__global const float *vertices, int i0, int i1, int i2) {
    /* Edges of halved vertices: the direction is the same and vertices up to
     * +-FLT_MAX cannot overflow the difference (inf would make the test NaN). */
    float ax = vertices[i1] * 0.5f - vertices[i0] * 0.5f;
    float ay = vertices[i1 + 1] * 0.5f - vertices[i0 + 1] * 0.5f;
    float az = vertices[i1 + 2] * 0.5f - vertices[i0 + 2] * 0.5f;
    float bx = vertices[i2] * 0.5f - vertices[i0] * 0.5f;
    float by = vertices[i2 + 1] * 0.5f - vertices[i0 + 1] * 0.5f;
    float bz = vertices[i2 + 2] * 0.5f - vertices[i0 + 2] * 0.5f;
    const float sa = max_abs3(ax, ay, az), sb = max_abs3(bx, by, bz);
    if (sa == 0.0f || sb == 0.0f) return 1;
    ax = ax / sa; ay = ay / sa; az = az / sa;
    bx = bx / sb; by = by / sb; bz = bz / sb;
    const float nx = ay * bz - az * by, ny = az * bx - ax * bz, nz = ax * by - ay * bx;
    const float nn = nx * nx + ny * ny + nz * nz;
    return nn <= DEGENERATE_SINE2 * (ax * ax + ay * ay + az * az) * (bx * bx + by * by + bz * bz);
}
#endif

/* Whether a triangle's hit at *t counts, and its t. The hit must lie in
 * [tmin, tmax] and before *best; the triangle must not be degenerate; and the
 * ray must enter the triangle's own box, by the slab test with the slab()
 * arithmetic, with *t raised to that box's entry where it lies before it.
 *
 * The last rule makes the answers independent of the tree. A float32
 * triangle test can return a hit a little outside the triangle's box (the
 * sheared coordinates carry u |p - o| of rounding, the slab test's padding is
 * relative to t along each axis): such a hit was found in a tree where the
 * triangle shares a leaf whose box the ray enters, and lost in one where it
 * has a leaf of its own. Every box that holds the triangle holds its box, and
 * the slab test is monotone in the planes (the same roundings of ordered
 * inputs), so with t0_b <= t1_b * pad and t0_b <= t every such box passes
 * slab() for every limit >= t, and the stack never drops it: the triangle
 * with the closest hit is tested in every tree. A ray that the slab test
 * takes to miss the triangle's box never tested it in a tree of one
 * triangle per leaf, so nothing is lost that such a tree would find, and the
 * raised t is no further from the exact one than the box's entry is (the
 * exact hit lies in the box). */
inline int accept_hit(__global const float *vertices, int i0, int i1, int i2, const Ray *ray,
                      float best, float *t, float own, float ax, float bx, float cx, float ay,
                      float by, float cy, float az, float bz, float cz) {
    /* own >= 0: the triangle has a leaf of its own, whose box (the triangle's)
     * the traversal entered at t = own by this very slab test: nothing to
     * compute. Else ax .. cz: the vertices minus the origin, axes in the order
     * kx, ky, kz, as the float test computes them. min(v_i) - o = min(v_i - o) (the rounding of
     * a subtraction is monotone), so these give slab()'s near and far distances
     * of the box; taking the axes in another order changes neither max_keep's
     * nor min_keep's result. */
    float th = *t;
    if (!(th >= ray->tmin && th <= ray->tmax && th < best)) return 0;
    float t0 = own;
    if (own < 0.0f) {
        const float lx = min_keep(min_keep(ax, bx), cx), ux = max_keep(max_keep(ax, bx), cx);
        const float ly = min_keep(min_keep(ay, by), cy), uy = max_keep(max_keep(ay, by), cy);
        const float lz = min_keep(min_keep(az, bz), cz), uz = max_keep(max_keep(az, bz), cz);
        t0 = ray->tmin;
        t0 = max_keep((ray->nkx ? ux : lx) * ray->jkx, t0);
        t0 = max_keep((ray->nky ? uy : ly) * ray->jky, t0);
        t0 = max_keep((ray->nkz ? uz : lz) * ray->jkz, t0);
        float t1 = INFINITY;
        t1 = min_keep((ray->nkx ? lx : ux) * ray->ikx, t1);
        t1 = min_keep((ray->nky ? ly : uy) * ray->iky, t1);
        t1 = min_keep((ray->nkz ? lz : uz) * ray->ikz, t1);
        if (!(t0 <= t1 * SLAB_PAD)) return 0;
    }
    th = max_keep(t0, th);
    if (!(th <= ray->tmax && th < best)) return 0;
#if DEGENERATE_TEST && !defined(WATERTIGHT_FP64)
    if (degenerate(vertices, i0, i1, i2)) return 0;
#endif
    *t = th;
    return 1;
}

/* The closest-hit walks' tie rule (traverse.cl, packet_traverse.cl): a hit
 * at exactly the closest t so far, best, may still win (by the lower triangle
 * index), so the triangle test is asked for t < tie_bound(best), the next
 * float32 above best, which is t <= best for the float32 t it computes. t is
 * never negative (t >= tmin >= 0), so the next float is one ulp up; from +-0
 * the least positive float. */
inline float tie_bound(float best) {
    if (best == 0.0f) return as_float(1u);
    return best < INFINITY ? as_float(as_uint(best) + 1u) : INFINITY;
}

/* accept_hit for the tests that do not keep the float translation at hand. */
inline int accept_hit_loading(__global const float *vertices, int i0, int i1, int i2,
                              const Ray *ray, float best, float *t, float own) {
    const int kx = ray->kx, ky = ray->ky, kz = ray->kz;
    return accept_hit(vertices, i0, i1, i2, ray, best, t, own,
                      vertices[i0 + kx] - ray->px, vertices[i1 + kx] - ray->px,
                      vertices[i2 + kx] - ray->px, vertices[i0 + ky] - ray->py,
                      vertices[i1 + ky] - ray->py, vertices[i2 + ky] - ray->py,
                      vertices[i0 + kz] - ray->pz, vertices[i1 + kz] - ray->pz,
                      vertices[i2 + kz] - ray->pz);
}

/* One triangle against the ray; on a hit with tmin <= t <= tmax and t < *best,
 * updates *best, *bu, *bv and returns the sign of det: +1 where the ray enters
 * the triangle's front (its corners counter-clockwise seen from the origin,
 * n . d < 0), -1 where it leaves by it; 0 for a miss. Zero-area triangles
 * never hit. For the watertight test, det has the sign that U, V and W share
 * (U + V + W, the edge functions of the sheared corners, times ez^2 > 0), so a
 * crossing of a closed surface is counted +1 or -1 consistently with its
 * neighbours through a shared edge (every_hit.h SIGNED). */
#if TRIANGLE_TEST == TEST_WATERTIGHT && defined(WATERTIGHT_FP64)
/* The watertight test with exact decisions (the default where the device has
 * doubles). Woop, Benthin, Wald 2013, "Watertight Ray/Triangle Intersection",
 * JCGT 2(1): translate to the origin, permute so that kz is the dominant axis,
 * shear so that the ray is +z, then 2D edge functions; here the shear is
 * taken times d_kz (make_ray): x = ez q_kx - ex q_kz, y = ez q_ky - ey q_kz for
 * q = p - o, and then
 *   U = x_c y_b - y_c x_b = ez e . (q_c x q_b)   (the Pluecker form)
 *   T = U q_a,z + V q_b,z + W q_c,z = -ez^2 det[q_a, q_b, q_c]   (Cramer)
 * with t = T / (det d_kz), det = U + V + W.
 *
 * Decisions exact (Shewchuk 1997, adaptive predicates): the signs of U, V, W
 * and of T are those of the exact real numbers for the float32 vertices, the
 * float32 origin and the traced direction. First in double from the float32
 * inputs: q = p - o rounds at most once (relative 2^-53), and with |ex|,
 * |ey| <= |ez| each computed edge function lies within 64 u ez^2 Q^2 (u =
 * 2^-53, Q the largest |q| of the triangle) of the exact one, T within
 * 2^-45 ez^2 Q^3 (derivation in lbvh.queries.exact; the bounds taken here are
 * 2^-45 and 2^-42, 4x and 8x wider). A sign that its bound does not settle is
 * computed exactly (exact.h: expansions of the multilinear forms in the input
 * floats). Nothing underflows or overflows in double for float32 inputs, so
 * the decisions are the exact ones at every scale.
 *
 * What follows: a ray hits a triangle by the exact test, whatever the order or
 * winding of its corners and whatever power of two the scene is scaled by
 * (within float32's range); a triangle whose corners are collinear (exactly)
 * is never hit, since its edge functions are then all zero or of both signs;
 * a shared edge is decided once for both triangles (watertight); t is >= 0
 * exactly where the ray's origin is on the triangle's plane or in front of
 * it, and exactly 0 where it is on the plane.
 *
 * t, u and v are computed in double from the same values by one formula that
 * no order of the corners changes (sum3: the same terms, the same roundings),
 * so they do not depend on the corners' order either, and scale with the
 * scene bit for bit (t by the scale, u and v not at all) while t is a normal
 * float32. Where the double t has the wrong sign (|t| below its rounding, the
 * origin a hair off the plane) or rounds to 0 off the plane, t is the
 * smallest float32 of the exact sign. */

/* |x| for doubles without a library call (fabs is out of line on PoCL 3). */
inline double abs64(double x) { return x < 0.0 ? -x : x; }

/* a + b + c summed the same way for any order of the three and negated
 * exactly for the negated three: the two smallest in magnitude first, or
 * where the two largest cancel, exactly the smallest. */
inline double sum3(double a, double b, double c) {
    double x = a, y = b, z = c, s;
    if (abs64(x) > abs64(y)) { s = x; x = y; y = s; }
    if (abs64(y) > abs64(z)) { s = y; y = z; z = s; }
    if (abs64(x) > abs64(y)) { s = x; x = y; y = s; }
    return y == -z ? x : (x + y) + z;
}

/* The exact sign of the edge function F = x_p y_r - y_p x_r of the corners p
 * and r (unpermuted floats in the order kx, ky, kz): ez e . ((p - o) x (r - o))
 * = ez (det[e, p, r] - det[e, p, o] - det[e, o, r]). */
inline int exact_edge_sign(const Ray *ray, float p0, float p1, float p2, float r0, float r1,
                           float r2) {
    double h[EXPANSION_TERMS];
    int m = 0;
    const float e0 = ray->ex, e1 = ray->ey, e2 = ray->ez;
    const float o0 = ray->px, o1 = ray->py, o2 = ray->pz;
    expansion_add_det3(h, &m, 1.0, e0, e1, e2, p0, p1, p2, r0, r1, r2);
    expansion_add_det3(h, &m, -1.0, e0, e1, e2, p0, p1, p2, o0, o1, o2);
    expansion_add_det3(h, &m, -1.0, e0, e1, e2, o0, o1, o2, r0, r1, r2);
    const int s = expansion_sign(h, m);
    return e2 < 0.0f ? -s : s;
}

/* The exact sign of T = -ez^2 det[a - o, b - o, c - o], expanded
 * multilinearly: det[a, b, c] - det[o, b, c] - det[a, o, c] - det[a, b, o]. */
inline int exact_numerator_sign(const Ray *ray, float a0, float a1, float a2, float b0, float b1,
                                float b2, float c0, float c1, float c2) {
    double h[EXPANSION_TERMS];
    int m = 0;
    const float o0 = ray->px, o1 = ray->py, o2 = ray->pz;
    expansion_add_det3(h, &m, 1.0, a0, a1, a2, b0, b1, b2, c0, c1, c2);
    expansion_add_det3(h, &m, -1.0, o0, o1, o2, b0, b1, b2, c0, c1, c2);
    expansion_add_det3(h, &m, -1.0, a0, a1, a2, o0, o1, o2, c0, c1, c2);
    expansion_add_det3(h, &m, -1.0, a0, a1, a2, b0, b1, b2, o0, o1, o2);
    return -expansion_sign(h, m);
}

#if EDGE_RULE
/* EDGE_SIGN of the exact sheared corners: where F is exactly 0, the exact
 * signs of y_p - y_r = ez (p_y - r_y) - ey (p_z - r_z), then of x_r - x_p (the
 * origin cancels: four products of two floats). */
inline int exact_ruled_sign(const Ray *ray, int f, float p0, float p1, float p2, float r0, float r1,
                            float r2) {
    if (f != 0) return f;
    const float ex = ray->ex, ey = ray->ey, ez = ray->ez;
    const int sy = exact_sign4(ez, p1, -ez, r1, -ey, p2, ey, r2);
    if (sy != 0) return sy;
    return exact_sign4(ez, r0, -ez, p0, -ex, r2, ex, p2);
}
#endif

inline int hit_triangle(__global const float *vertices, int i0, int i1, int i2, const Ray *ray,
                        float own, float *best, float *bu, float *bv) {
    const int kx = ray->kx, ky = ray->ky, kz = ray->kz;
    const float fax = vertices[i0 + kx], fay = vertices[i0 + ky], faz = vertices[i0 + kz];
    const float fbx = vertices[i1 + kx], fby = vertices[i1 + ky], fbz = vertices[i1 + kz];
    const float fcx = vertices[i2 + kx], fcy = vertices[i2 + ky], fcz = vertices[i2 + kz];
    const double ox = ray->px, oy = ray->py, oz = ray->pz;
    const double ex = ray->ex, ey = ray->ey, ez = ray->ez;
    const double qax = (double)fax - ox, qay = (double)fay - oy, qaz = (double)faz - oz;
    const double qbx = (double)fbx - ox, qby = (double)fby - oy, qbz = (double)fbz - oz;
    const double qcx = (double)fcx - ox, qcy = (double)fcy - oy, qcz = (double)fcz - oz;
    const double ax = qax * ez - qaz * ex, ay = qay * ez - qaz * ey;
    const double bx = qbx * ez - qbz * ex, by = qby * ez - qbz * ey;
    const double cx = qcx * ez - qcz * ex, cy = qcy * ez - qcz * ey;
    double U = cx * by - cy * bx;
    double V = ax * cy - ay * cx;
    double W = bx * ay - by * ax;
    double Q = abs64(qax);
    Q = abs64(qay) > Q ? abs64(qay) : Q; Q = abs64(qaz) > Q ? abs64(qaz) : Q;
    Q = abs64(qbx) > Q ? abs64(qbx) : Q; Q = abs64(qby) > Q ? abs64(qby) : Q;
    Q = abs64(qbz) > Q ? abs64(qbz) : Q; Q = abs64(qcx) > Q ? abs64(qcx) : Q;
    Q = abs64(qcy) > Q ? abs64(qcy) : Q; Q = abs64(qcz) > Q ? abs64(qcz) : Q;
    const double ez2 = ez * ez;
    const double bound = (ez2 * 0x1p-45) * Q * Q;
    const int pos = (U > bound) | ((V > bound) << 1) | ((W > bound) << 2);
    const int neg = (U < -bound) | ((V < -bound) << 1) | ((W < -bound) << 2);
    if (pos != 0 && neg != 0) return 0;   /* two edges of certain opposite signs */
    int s;   /* the sign U, V, W and det share */
    if (pos == 7) {
        s = 1;
    } else if (neg == 7) {
        s = -1;
    } else {
        /* the settled signs, and the others exactly */
#define SETTLED(bit, p0, p1, p2, r0, r1, r2) \
    ((pos & (bit)) ? 1 : ((neg & (bit)) ? -1 : exact_edge_sign(ray, p0, p1, p2, r0, r1, r2)))
        const int su = SETTLED(1, fcx, fcy, fcz, fbx, fby, fbz);
        const int sv = SETTLED(2, fax, fay, faz, fcx, fcy, fcz);
        const int sw = SETTLED(4, fbx, fby, fbz, fax, fay, faz);
#undef SETTLED
#if EDGE_RULE
        const int ru = exact_ruled_sign(ray, su, fcx, fcy, fcz, fbx, fby, fbz);
        const int rv = exact_ruled_sign(ray, sv, fax, fay, faz, fcx, fcy, fcz);
        const int rw = exact_ruled_sign(ray, sw, fbx, fby, fbz, fax, fay, faz);
        if (!same_signs(ru, rv, rw)) return 0;
        /* a ray through an edge or a vertex: det has the sign of the others */
        if (su == 0 && sv == 0 && sw == 0) return 0;   /* in the plane, or collinear */
        s = su + sv + sw > 0 ? 1 : -1;
#else
        if ((su < 0 || sv < 0 || sw < 0) && (su > 0 || sv > 0 || sw > 0)) return 0;
        if (su == 0 && sv == 0 && sw == 0) return 0;   /* in the plane, or collinear */
        s = su + sv + sw > 0 ? 1 : -1;
#endif
        /* An edge function the bound did not settle is noise of the size of its
         * bound: where it is 0 or its double value has the wrong sign it counts 0
         * in det, t, u and v, so that det sums values of one sign (a ray through
         * a vertex gets t from the edges it does not touch). */
        U = (su > 0) == (U > 0.0) && (su < 0) == (U < 0.0) ? U : 0.0;
        V = (sv > 0) == (V > 0.0) && (sv < 0) == (V < 0.0) ? V : 0.0;
        W = (sw > 0) == (W > 0.0) && (sw < 0) == (W < 0.0) ? W : 0.0;
    }
    const double det = sum3(U, V, W);
    const double T = sum3(U * qaz, V * qbz, W * qcz);
    const double tbound = (ez2 * 0x1p-42) * Q * Q * Q;
    const int sT = T > tbound ? 1 : (T < -tbound ? -1 :
                   exact_numerator_sign(ray, fax, fay, faz, fbx, fby, fbz, fcx, fcy, fcz));
    const float dkz = axis(ray->dx, ray->dy, ray->dz, kz);
    const int st = dkz < 0.0f ? -(sT * s) : sT * s;   /* the exact sign of t */
    /* det = 0: every edge function was noise (the ray in the triangle's plane
     * to rounding); t then has its exact sign and accept_hit raises it to the
     * triangle's box entry */
    float t = det != 0.0 ? (float)abs64(T / (det * (double)dkz)) : 0.0f;
    if (st == 0) t = 0.0f;
    else {
        if (t == 0.0f) t = 0x1p-149f;
        if (st < 0) t = -t;
    }
    if (!accept_hit_loading(vertices, i0, i1, i2, ray, *best, &t, own)) return 0;
    *best = t;
    *bu = det != 0.0 ? (float)(V / det) : 0.0f;
    *bv = det != 0.0 ? (float)(W / det) : 0.0f;
    return s;
}

#elif TRIANGLE_TEST == TEST_WATERTIGHT
/* Woop, Benthin, Wald 2013, in float32 only (devices without doubles, or
 * NO_FP64): watertight, but its decisions are the rounded ones (they may
 * change with the corners' order on slivers and underflow on tiny scenes). */
inline int hit_triangle(__global const float *vertices, int i0, int i1, int i2, const Ray *ray,
                        float own, float *best, float *bu, float *bv) {
    const int kx = ray->kx, ky = ray->ky, kz = ray->kz;
    const float ex = ray->ex, ey = ray->ey, ez = ray->ez;
    const float az = vertices[i0 + kz] - ray->pz;
    const float bz = vertices[i1 + kz] - ray->pz;
    const float cz = vertices[i2 + kz] - ray->pz;
    const float pax = vertices[i0 + kx] - ray->px, pay = vertices[i0 + ky] - ray->py;
    const float pbx = vertices[i1 + kx] - ray->px, pby = vertices[i1 + ky] - ray->py;
    const float pcx = vertices[i2 + kx] - ray->px, pcy = vertices[i2 + ky] - ray->py;
    const float ax = pax * ez - az * ex;
    const float ay = pay * ez - az * ey;
    const float bx = pbx * ez - bz * ex;
    const float by = pby * ez - bz * ey;
    const float cx = pcx * ez - cz * ex;
    const float cy = pcy * ez - cz * ey;
    const float U = cx * by - cy * bx;
    const float V = ax * cy - ay * cx;
    const float W = bx * ay - by * ax;
    const float det = U + V + W;
    const float T = U * (ray->sz * az) + V * (ray->sz * bz) + W * (ray->sz * cz);
    if (!RAY_INSIDE(U, V, W, ax, ay, bx, by, cx, cy)) return 0;
    if (det == 0.0f) return 0;
    float t = T / det;
    if (!accept_hit(vertices, i0, i1, i2, ray, *best, &t, own, pax, pbx, pcx, pay, pby, pcy, az,
                    bz, cz))
        return 0;
    *best = t;
    *bu = V / det;
    *bv = W / det;
    return det > 0.0f ? 1 : -1;
}
#else
/* Moller, Trumbore 1997, "Fast, Minimum Storage Ray/Triangle Intersection". */
inline int hit_triangle(__global const float *vertices, int i0, int i1, int i2, const Ray *ray,
                        float own, float *best, float *bu, float *bv) {
    const float p0x = vertices[i0], p0y = vertices[i0 + 1], p0z = vertices[i0 + 2];
    const float e1x = vertices[i1] - p0x, e1y = vertices[i1 + 1] - p0y, e1z = vertices[i1 + 2] - p0z;
    const float e2x = vertices[i2] - p0x, e2y = vertices[i2 + 1] - p0y, e2z = vertices[i2 + 2] - p0z;
    const float qx = ray->dy * e2z - ray->dz * e2y;   /* P = d x e2 */
    const float qy = ray->dz * e2x - ray->dx * e2z;
    const float qz = ray->dx * e2y - ray->dy * e2x;
    const float det = e1x * qx + e1y * qy + e1z * qz;
    if (det == 0.0f) return 0;
    const float inv = 1.0f / det;
    const float tx = ray->ox - p0x, ty = ray->oy - p0y, tz = ray->oz - p0z;
    const float u = (tx * qx + ty * qy + tz * qz) * inv;
    if (!(u >= 0.0f && u <= 1.0f)) return 0;
    const float rx = ty * e1z - tz * e1y;             /* Q = T x e1 */
    const float ry = tz * e1x - tx * e1z;
    const float rz = tx * e1y - ty * e1x;
    const float v = (ray->dx * rx + ray->dy * ry + ray->dz * rz) * inv;
    if (!(v >= 0.0f && u + v <= 1.0f)) return 0;
    float t = (e2x * rx + e2y * ry + e2z * rz) * inv;
    if (!accept_hit_loading(vertices, i0, i1, i2, ray, *best, &t, own)) return 0;
    *best = t;
    *bu = u;
    *bv = v;
    return det > 0.0f ? 1 : -1;
}
#endif

#endif
