/* Ray traversal of a BVH in the project's layout (docs/layout.md), driven by
 * lbvh/traverse.py.
 *
 * Two kernels:
 *   order_faces  copies the faces in slot order, once per tree;
 *   traverse     traces rays through the tree's wide records (kernels/wide.cl:
 *                up to WIDTH children per node, their boxes in rows of WIDTH
 *                floats, so that one vector slab test covers all children of
 *                a node; Wald, Benthin, Boulos 2008), or through the tree's
 *                own binary nodes (WIDE=0).
 *
 * A work-item traces the rays [chunk_first, chunk_last) one after the other
 * (the host gives every work-item one ray, in work-groups of 64, on PoCL as on
 * a GPU) with an explicit stack, in closest-hit or any-hit mode.
 *
 * Ordered traversal: of the children whose boxes the ray enters, the one with
 * the smallest entry distance is visited first; equal entries: the smaller exit
 * distance; equal again: the one further right. The others are pushed, the
 * nearest last, each with its entry distance, and dropped when popped behind
 * the closest hit so far; a child whose entry lies beyond the closest hit is
 * not entered at all.
 *
 * Compile-time variants (-D), all optional:
 *   ANY_HIT=1        stop at the first hit in [tmin, tmax] (occlusion)
 *   COUNTERS=1       write per ray the nodes visited (the root, whose box is
 *                    always tested, plus every node (a wide record, or a
 *                    binary node with WIDE=0) or leaf descended into or
 *                    popped) and the triangles tested
 *   TRIANGLE_TEST=0  watertight test of Woop, Benthin, Wald 2013 (default)
 *   TRIANGLE_TEST=1  Moller-Trumbore 1997 (faster, leaks through shared edges)
 *   STACK_SIZE=n     stack entries; a push beyond n sets FLAG_OVERFLOW and
 *                    drops that subtree (reported, never silent)
 *   SLAB_PAD=x       factor on the far distance of a box (Ize 2013)
 *   NO_FP64=1        leave out the double fallback of the watertight test
 *   WIDE=0           read the tree's own nodes instead of the wide records
 *   WIDTH=4 or 8     children per wide record (kernels/wide.cl), default 8
 *   RAY_ORDER=1      trace the rays in the order order[] gives (ray_order.cl)
 *
 * Rays come as four arrays: origins and directions (3 floats per ray), tmin
 * and tmax (one float per ray, or one for all rays with a stride of 0).
 * Results are four planes of `count` floats: t, u, v, as_float(prim), with
 * prim in the caller's original numbering, -1 and t = +inf for a miss. The
 * hit point is (1-u-v)*p0 + u*p1 + v*p2. The host rejects NaN and infinite
 * rays; one with NaN that reaches the kernel anyway is flagged and not
 * traced; the loop is bounded by the stack and by a visit limit of
 * num_nodes, so even a cyclic tree terminates.
 */
#include "common.h"

#ifndef ANY_HIT
#define ANY_HIT 0
#endif
#ifndef COUNTERS
#define COUNTERS 0
#endif
#define TEST_WATERTIGHT 0
#define TEST_MOLLER 1
#ifndef TRIANGLE_TEST
#define TRIANGLE_TEST TEST_WATERTIGHT
#endif
#ifndef STACK_SIZE
#define STACK_SIZE 64
#endif
#ifndef SLAB_PAD
/* 1 + 2 gamma(3), gamma(n) = n u / (1 - n u), u = 2^-24, rounded up to float. */
#define SLAB_PAD 0x1.000008p+0f
#endif

#define FLAG_OVERFLOW 1    /* a push found the stack full: a subtree was skipped */
#define FLAG_VISIT_LIMIT 2 /* more nodes visited than the tree has: not a tree */
#define FLAG_NAN_RAY 4     /* NaN in the ray: not traced (the host API refuses such rays) */

/* The double fallback of the watertight test where the device has doubles
 * (-DNO_FP64 leaves it out, to test the path of devices without them). */
#if TRIANGLE_TEST == TEST_WATERTIGHT && defined(cl_khr_fp64) && !defined(NO_FP64)
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#define WATERTIGHT_FP64 1
#endif

/* The hot loop is written with comparisons instead of fmin/fmax/select/vload3:
 * PoCL calls those builtins out of line, which cost half the time. */

/* max and min keeping m when x is NaN (m is never NaN): fmax/fmin semantics. */
inline float max_keep(float x, float m) { return x > m ? x : m; }
inline float min_keep(float x, float m) { return x < m ? x : m; }

typedef struct {
    float ox, oy, oz, dx, dy, dz;
    float ix, iy, iz;   /* 1/d: +-inf for +-0 */
    /* Offsets (in floats) of the near and far plane of each axis in a node
     * record: the sign bit of d picks them, so -0.0 counts as negative like
     * 1/-0 = -inf (Williams et al. 2005; pbrt's dirIsNeg). */
    int nx, ny, nz, fx, fy, fz;
    float tmin, tmax;
    /* Woop 2013, section 3: permutation making kz the dominant axis (kx, ky
     * swapped when d[kz] < 0 to keep the winding), the origin permuted, and
     * the shear constants. */
    int kx, ky, kz;
    float px, py, pz;
    /* t is measured along d * 2^-texp (see make_ray); 0 for ordinary rays. */
    int texp;
    float sx, sy, sz;
} Ray;

inline float axis(float x, float y, float z, int k) { return k == 0 ? x : (k == 1 ? y : z); }

inline Ray make_ray(__global const float *o, __global const float *d, float tmin, float tmax) {
    Ray ray;
    ray.ox = o[0]; ray.oy = o[1]; ray.oz = o[2]; ray.tmin = tmin;
    ray.dx = d[0]; ray.dy = d[1]; ray.dz = d[2]; ray.tmax = tmax;
    /* A direction far from unit length (tiny or denormal components, or
     * huge ones) makes 1/d and the shear constants leave float32's range.
     * Scaling d by a power of two (and t the other way) is exact, so such a
     * ray is traced as d * 2^-texp and its t scaled back at the end. */
    ray.texp = 0;
    const float dmax = fmax(fmax(fabs(ray.dx), fabs(ray.dy)), fabs(ray.dz));
    if (dmax < 0x1p-60f || dmax > 0x1p60f) {
        /* Only as far as back into [2^-60, 2^60]: the least change of t's
         * scale, so t itself neither overflows nor underflows. */
        int e;
        (void)frexp(dmax, &e);
        e = e > 0 ? e - 60 : e + 59;
        ray.texp = e;
        ray.dx = ldexp(ray.dx, -e); ray.dy = ldexp(ray.dy, -e); ray.dz = ldexp(ray.dz, -e);
        ray.tmin = ldexp(ray.tmin, e); ray.tmax = ldexp(ray.tmax, e);
    }
    ray.ix = 1.0f / ray.dx;
    ray.iy = 1.0f / ray.dy;
    ray.iz = 1.0f / ray.dz;
    const int negx = as_int(ray.dx) < 0, negy = as_int(ray.dy) < 0, negz = as_int(ray.dz) < 0;
    ray.nx = negx ? 4 : 0; ray.fx = 4 - ray.nx;
    ray.ny = negy ? 5 : 1; ray.fy = 6 - ray.ny;
    ray.nz = negz ? 6 : 2; ray.fz = 8 - ray.nz;
    const float ax = fabs(ray.dx), ay = fabs(ray.dy), az = fabs(ray.dz);
    const int kz = ax >= ay ? (ax >= az ? 0 : 2) : (ay >= az ? 1 : 2);
    int kx = kz == 2 ? 0 : kz + 1;
    int ky = kx == 2 ? 0 : kx + 1;
    const float dz = axis(ray.dx, ray.dy, ray.dz, kz);
    if (dz < 0.0f) { const int s = kx; kx = ky; ky = s; }
    ray.kx = kx; ray.ky = ky; ray.kz = kz;
    ray.px = axis(ray.ox, ray.oy, ray.oz, kx);
    ray.py = axis(ray.ox, ray.oy, ray.oz, ky);
    ray.pz = axis(ray.ox, ray.oy, ray.oz, kz);
    ray.sx = axis(ray.dx, ray.dy, ray.dz, kx) / dz;
    ray.sy = axis(ray.dx, ray.dy, ray.dz, ky) / dz;
    ray.sz = 1.0f / dz;
    return ray;
}

/* Slab test (Kay-Kajiya) of the box record at `box`
 * (lower.xyz, word, upper.xyz, word), made robust:
 * - near and far planes picked by the sign bit of d (-0.0 is negative);
 * - an origin on a slab plane with a zero direction component gives
 *   0 * inf = NaN on that axis; max_keep/min_keep ignore it, so that axis does
 *   not bound the ray, which is right: the origin lies on the closed slab;
 * - a flat box (lower == upper on an axis) is accepted with entry == exit;
 * - the far distance is multiplied by 1 + 2 gamma(3) (Ize 2013, "Robust BVH
 *   Ray Traversal", JCGT 2(2)), which covers the rounding of the subtraction,
 *   the reciprocal and the product, so no box containing a hit is lost.
 * Returns whether [entry, exit] meets [ray.tmin, limit]; *leave is the box's
 * own exit distance (unpadded), used to order children of equal entry. */
inline int slab(__global const float *box, const Ray *ray, float limit,
                float *entry, float *leave) {
    float t0 = ray->tmin;
    t0 = max_keep((box[ray->nx] - ray->ox) * ray->ix, t0);
    t0 = max_keep((box[ray->ny] - ray->oy) * ray->iy, t0);
    t0 = max_keep((box[ray->nz] - ray->oz) * ray->iz, t0);
    float t1 = INFINITY;
    t1 = min_keep((box[ray->fx] - ray->ox) * ray->ix, t1);
    t1 = min_keep((box[ray->fy] - ray->oy) * ray->iy, t1);
    t1 = min_keep((box[ray->fz] - ray->oz) * ray->iz, t1);
    *entry = t0;
    *leave = t1;
    return t0 <= min_keep(t1, limit) * SLAB_PAD;
}

/* Zero-area triangles (repeated or collinear vertices) must never be hit, but
 * after rounding their projected edge functions can all share a sign. A
 * triangle is degenerate when |e1 x e2| <= 2^-20 |e1| |e2|, evaluated on the
 * edges scaled to a largest component of 1 (no overflow or underflow). Called
 * only for a hit that would be accepted, so it costs nothing on the way. */
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

/* One triangle against the ray; on a hit with tmin <= t <= tmax and t < *best,
 * updates *best, *bu, *bv and returns 1. Zero-area triangles never hit. */
#if TRIANGLE_TEST == TEST_WATERTIGHT && defined(WATERTIGHT_FP64)
/* The watertight test in double from the sheared float coordinates (see below). */
inline int hit_triangle_fp64(__global const float *vertices, int i0, int i1, int i2,
                             const Ray *ray, float ax, float ay, float az, float bx, float by,
                             float bz, float cx, float cy, float cz,
                             float *best, float *bu, float *bv) {
    const double U = (double)cx * (double)by - (double)cy * (double)bx;
    const double V = (double)ax * (double)cy - (double)ay * (double)cx;
    const double W = (double)bx * (double)ay - (double)by * (double)ax;
    if ((U < 0.0 || V < 0.0 || W < 0.0) && (U > 0.0 || V > 0.0 || W > 0.0)) return 0;
    const double det = U + V + W;
    if (det == 0.0) return 0;
    const double sz = (double)ray->sz;
    const double T = U * (sz * (double)az) + V * (sz * (double)bz) + W * (sz * (double)cz);
    const float t = (float)(T / det);
    if (!(t >= ray->tmin && t <= ray->tmax && t < *best)) return 0;
    if (degenerate(vertices, i0, i1, i2)) return 0;
    *best = t;
    *bu = (float)(V / det);
    *bv = (float)(W / det);
    return 1;
}
#endif

#if TRIANGLE_TEST == TEST_WATERTIGHT
/* Woop, Benthin, Wald 2013, "Watertight Ray/Triangle Intersection", JCGT 2(1):
 * translate to the origin, permute and shear so that the ray is +z, then 2D
 * edge functions. An edge shared by two triangles is evaluated from the same
 * two vertices with the same operations, so a ray cannot slip between them. */
inline int hit_triangle(__global const float *vertices, int i0, int i1, int i2, const Ray *ray,
                        float *best, float *bu, float *bv) {
    const int kx = ray->kx, ky = ray->ky, kz = ray->kz;
    const float az = vertices[i0 + kz] - ray->pz;
    const float bz = vertices[i1 + kz] - ray->pz;
    const float cz = vertices[i2 + kz] - ray->pz;
    const float ax = (vertices[i0 + kx] - ray->px) - ray->sx * az;
    const float ay = (vertices[i0 + ky] - ray->py) - ray->sy * az;
    const float bx = (vertices[i1 + kx] - ray->px) - ray->sx * bz;
    const float by = (vertices[i1 + ky] - ray->py) - ray->sy * bz;
    const float cx = (vertices[i2 + kx] - ray->px) - ray->sx * cz;
    const float cy = (vertices[i2 + ky] - ray->py) - ray->sy * cz;
    const float U = cx * by - cy * bx;
    const float V = ax * cy - ay * cx;
    const float W = bx * ay - by * ax;
    const float det = U + V + W;
    const float T = U * (ray->sz * az) + V * (ray->sz * bz) + W * (ray->sz * cz);
#ifdef WATERTIGHT_FP64
    /* Section 3.3: an edge function that rounds to zero is recomputed in
     * double, where products of floats are exact and its sign is right. The
     * same is done when a float32 product leaves float32's normal range
     * (triangles ~1e19 or ~1e-19 in size around the ray: overflow, or
     * denormals that lose digits): then the whole test runs in double and
     * only t, u, v return to float. */
    if (fabs(U) < FLT_MIN || fabs(V) < FLT_MIN || fabs(W) < FLT_MIN ||
        !(fabs(det) >= FLT_MIN && fabs(det) <= FLT_MAX) ||
        !(fabs(T) >= FLT_MIN && fabs(T) <= FLT_MAX))
        return hit_triangle_fp64(vertices, i0, i1, i2, ray, ax, ay, az, bx, by, bz, cx, cy, cz,
                                 best, bu, bv);
#endif
    if ((U < 0.0f || V < 0.0f || W < 0.0f) && (U > 0.0f || V > 0.0f || W > 0.0f)) return 0;
    if (det == 0.0f) return 0;
    const float t = T / det;
    if (!(t >= ray->tmin && t <= ray->tmax && t < *best)) return 0;
    if (degenerate(vertices, i0, i1, i2)) return 0;
    *best = t;
    *bu = V / det;
    *bv = W / det;
    return 1;
}
#else
/* Moller, Trumbore 1997, "Fast, Minimum Storage Ray/Triangle Intersection". */
inline int hit_triangle(__global const float *vertices, int i0, int i1, int i2, const Ray *ray,
                        float *best, float *bu, float *bv) {
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
    const float t = (e2x * rx + e2y * ry + e2z * rz) * inv;
    if (!(t >= ray->tmin && t <= ray->tmax && t < *best)) return 0;
    if (degenerate(vertices, i0, i1, i2)) return 0;
    *best = t;
    *bu = u;
    *bv = v;
    return 1;
}
#endif

#ifndef WIDE
#define WIDE 1
#endif
#ifndef WIDTH
#define WIDTH 8
#endif
#ifndef RAY_ORDER
#define RAY_ORDER 0
#endif

#if WIDE
/* A wide record's rows (kernels/wide.cl) as vectors, and as lanes. */
#if WIDTH == 4
typedef float4 floatw;
typedef int4 intw;
#elif WIDTH == 8
typedef float8 floatw;
typedef int8 intw;
#else
#error "WIDTH must be 4 or 8"
#endif
typedef union { floatw v; float s[WIDTH]; } floatw_lanes;
typedef union { intw v; int s[WIDTH]; } intw_lanes;

/* max_keep and min_keep lane by lane (NaN in x keeps m). */
inline floatw max_keep_w(floatw x, floatw m) { return x > m ? x : m; }
inline floatw min_keep_w(floatw x, floatw m) { return x < m ? x : m; }
#else
/* The box and the reference of child k (0 left, 1 right) of binary node x,
 * read from the tree's own nodes (for trees whose wide records would not fit
 * in one device buffer): a leaf child's reference is its node words, an
 * internal child's is (its node index, 0). */
inline __global const float *child_box(__global const float *nodes, __global const int *words,
                                       int x, int k) {
    return nodes + 8 * words[8 * x + 3 + 4 * k];
}
inline int2 child_ref(__global const int *words, int x, int k) {
    const int c = words[8 * x + 3 + 4 * k];
    const int y = words[8 * c + 7];
    return node_is_leaf(y) ? (int2)(words[8 * c + 3], y) : (int2)(c, 0);
}
#endif

/* The faces in slot order, slot_faces[s] = faces[prim_order[s]]: a leaf's
 * triangles are then read without going through prim_order (one dependent
 * load less per triangle); prim_order maps only the closest hit back. */
__kernel void order_faces(__global const uint *faces, __global const int *prim_order,
                          const int num_prims, const int per_item, __global uint *slot_faces) {
    const int gid = get_global_id(0);
    const int last = chunk_last(gid, per_item, num_prims);
    for (int s = chunk_first(gid, per_item, num_prims); s < last; ++s) {
        const int t = prim_order[s];
        slot_faces[3 * s] = faces[3 * t];
        slot_faces[3 * s + 1] = faces[3 * t + 1];
        slot_faces[3 * s + 2] = faces[3 * t + 2];
    }
}

/* Rays origins[3i..], directions[3i..], tmin[i * interval_stride],
 * tmax[i * interval_stride]. The root's box is tested from its node; the root
 * enters the loop as the reference (root_x, root_y), in the encoding of the
 * wide records (kernels/wide.cl: a leaf's node words, or (record, 0)); with
 * WIDE=0 `records` is the node array itself and an internal root is
 * (root, 0). Triangles come from slot_faces (see order_faces). */
__kernel void traverse(__global const float4 *nodes, __global const float *records,
                       __global const int *prim_order,
                       __global const float *vertices, __global const uint *slot_faces,
                       const int root, const int root_x, const int root_y, const int num_nodes,
                       __global const float *origins, __global const float *directions,
                       __global const float *tmins, __global const float *tmaxs,
                       const int interval_stride, __global const int *order,
                       __global float *hits, __global int *flags, __global int2 *counters,
                       const int count, const int per_item) {
    const int gid = get_global_id(0);
    const int first = chunk_first(gid, per_item, count);
    const int last = chunk_last(gid, per_item, count);
    __global const int *record_words = (__global const int *)records;
    /* A stack entry is a reference (x, y) and the entry distance, to drop
     * subtrees behind a closer hit. */
    int stack_x[STACK_SIZE];
    int stack_y[STACK_SIZE];
    float stack_entry[STACK_SIZE];

    for (int k = first; k < last; ++k) {
#if RAY_ORDER
        const int i = order[k];  /* rays in the order of ray_order.cl's keys */
#else
        const int i = k;
#endif
        const Ray ray = make_ray(origins + 3 * i, directions + 3 * i,
                                 tmins[i * interval_stride], tmaxs[i * interval_stride]);
#if WIDE
        /* The rows of a record holding each axis's near and far planes. */
        const int near_x = ray.nx ? 1 : 0, near_y = ray.ny == 5 ? 3 : 2, near_z = ray.nz == 6 ? 5 : 4;
        const int far_x = 1 - near_x, far_y = 5 - near_y, far_z = 9 - near_z;
        const floatw ox = (floatw)(ray.ox), oy = (floatw)(ray.oy), oz = (floatw)(ray.oz);
        const floatw ix = (floatw)(ray.ix), iy = (floatw)(ray.iy), iz = (floatw)(ray.iz);
#endif
        float best = INFINITY, bu = 0.0f, bv = 0.0f;
        int best_slot = -1, flag = 0, visited = 1, tested = 0;
        int sp = 0;
        float entry, leave;
        int x = root_x, y = root_y;
        /* A NaN ray would pass every slab test (NaN distances are ignored),
         * empty lanes of wide records included: it is reported, not traced. */
        const int nan_ray = isnan(ray.ox) || isnan(ray.oy) || isnan(ray.oz) || isnan(ray.dx) ||
                            isnan(ray.dy) || isnan(ray.dz) || isnan(ray.tmin) || isnan(ray.tmax);
        if (nan_ray) flag |= FLAG_NAN_RAY;
        int go = !nan_ray &&
                 slab((__global const float *)(nodes + 2 * root), &ray, ray.tmax, &entry, &leave);
        while (go) {
            int have_next = 0, next_x = 0, next_y = 0;
            if (node_is_leaf(y)) {
                for (int s = x; s < x - y; ++s) {
                    ++tested;
                    if (hit_triangle(vertices, 3 * (int)slot_faces[3 * s], 3 * (int)slot_faces[3 * s + 1],
                                     3 * (int)slot_faces[3 * s + 2], &ray, &best, &bu, &bv)) {
                        best_slot = s;
#if ANY_HIT
                        break;
#endif
                    }
                }
#if ANY_HIT
                if (best_slot >= 0) break;
#endif
            } else {
                const float limit = min_keep(best, ray.tmax);
#if WIDE
                /* The slab test of slab() for all lanes at once. */
                __global const floatw *row = (__global const floatw *)records + 8 * x;
                floatw t0 = (floatw)(ray.tmin);
                t0 = max_keep_w((row[near_x] - ox) * ix, t0);
                t0 = max_keep_w((row[near_y] - oy) * iy, t0);
                t0 = max_keep_w((row[near_z] - oz) * iz, t0);
                floatw t1 = (floatw)(INFINITY);
                t1 = min_keep_w((row[far_x] - ox) * ix, t1);
                t1 = min_keep_w((row[far_y] - oy) * iy, t1);
                t1 = min_keep_w((row[far_z] - oz) * iz, t1);
                intw_lanes hit;
                hit.v = t0 <= min_keep_w(t1, (floatw)(limit)) * SLAB_PAD;
                floatw_lanes enter, exit;
                enter.v = t0;
                exit.v = t1;
                /* The lanes hit, nearest first (insertion sort; a later lane
                 * goes before an earlier one of equal entry and exit). */
                int lane[WIDTH];
                int n = 0;
                for (int c = 0; c < WIDTH; ++c) {
                    if (!hit.s[c]) continue;
                    const float e = enter.s[c], l = exit.s[c];
                    int p = n++;
                    for (; p > 0; --p) {
                        const int o = lane[p - 1];
                        if (enter.s[o] < e || (enter.s[o] == e && exit.s[o] < l)) break;
                        lane[p] = o;
                    }
                    lane[p] = c;
                }
                if (n > 0) {
                    __global const int *ref = record_words + 8 * WIDTH * x + 6 * WIDTH;
                    for (int m = n - 1; m > 0; --m) {
                        if (sp < STACK_SIZE) {
                            stack_x[sp] = ref[lane[m]];
                            stack_y[sp] = ref[WIDTH + lane[m]];
                            stack_entry[sp] = enter.s[lane[m]];
                            ++sp;
                        } else {
                            flag |= FLAG_OVERFLOW;
                        }
                    }
                    next_x = ref[lane[0]];
                    next_y = ref[WIDTH + lane[0]];
                    have_next = 1;
                }
#else
                float e0, x0, e1, x1;
                const int h0 = slab(child_box(records, record_words, x, 0), &ray, limit, &e0, &x0);
                const int h1 = slab(child_box(records, record_words, x, 1), &ray, limit, &e1, &x1);
                if (h0 && h1) {
                    /* Nearer entry first; equal entries: nearer exit; else the right child. */
                    const int left_first = e0 < e1 || (e0 == e1 && x0 < x1);
                    const int2 near = child_ref(record_words, x, left_first ? 0 : 1);
                    next_x = near.x;
                    next_y = near.y;
                    have_next = 1;
                    if (sp < STACK_SIZE) {
                        const int2 far = child_ref(record_words, x, left_first ? 1 : 0);
                        stack_x[sp] = far.x;
                        stack_y[sp] = far.y;
                        stack_entry[sp] = left_first ? e1 : e0;
                        ++sp;
                    } else {
                        flag |= FLAG_OVERFLOW;
                    }
                } else if (h0 || h1) {
                    const int2 only = child_ref(record_words, x, h0 ? 0 : 1);
                    next_x = only.x;
                    next_y = only.y;
                    have_next = 1;
                }
#endif
            }
            if (!have_next) {
                /* Pop, dropping subtrees whose entry lies beyond the closest hit. */
                const float cut = min_keep(best, ray.tmax) * SLAB_PAD;
                while (sp > 0 && stack_entry[sp - 1] > cut) --sp;
                if (sp == 0) break;
                --sp;
                next_x = stack_x[sp];
                next_y = stack_y[sp];
            }
            x = next_x;
            y = next_y;
            if (++visited > num_nodes) {
                flag |= FLAG_VISIT_LIMIT;
                break;
            }
        }
        /* + 0.0f turns a t of -0.0 (T = -0) into +0.0 */
        if (ray.texp != 0) best = ldexp(best, -ray.texp);
        hits[i] = best + 0.0f;
        hits[count + i] = bu;
        hits[2 * count + i] = bv;
        hits[3 * count + i] = as_float(best_slot >= 0 ? prim_order[best_slot] : -1);
        flags[i] = flag;
#if COUNTERS
        counters[i] = (int2)(visited, tested);
#endif
    }
}
