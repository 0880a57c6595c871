/* The slab test of one ray against every lane of a wide record at once
 * (kernels/wide.cl's rows; Wald, Benthin, Boulos 2008): what the closest-hit
 * traversal (kernels/traverse.cl) and the every-hit walk (kernels/every_hit.h)
 * share. It is slab() of kernels/ray_triangle.h lane by lane: the same near
 * and far planes by the sign bits of d, the same 1/d (jx.. for the near planes
 * where 1/d overflowed), NaN distances ignored, the entry padded by SLAB_PAD.
 *
 * Defines: WIDTH (4 or 8, default 8), the lanes of a record (wide_rows.h).
 */
#ifndef LBVH_WIDE_SLAB_H
#define LBVH_WIDE_SLAB_H
#include "ray_triangle.h"

#include "wide_rows.h"

/* A ray's constants broadcast to the lanes, and the rows of a record holding
 * each axis's near and far planes. */
typedef struct {
    floatw ox, oy, oz, ix, iy, iz;
    int near_x, near_y, near_z, far_x, far_y, far_z;
    /* 1/d overflowed on some axis (rare): the near planes go by jx, jy, jz */
    int tiny_d;
} WideRay;

inline void make_wide_ray(const Ray *ray, WideRay *w) {
    w->near_x = ray->nx ? 1 : 0;
    w->near_y = ray->ny == 5 ? 3 : 2;
    w->near_z = ray->nz == 6 ? 5 : 4;
    w->far_x = 1 - w->near_x;
    w->far_y = 5 - w->near_y;
    w->far_z = 9 - w->near_z;
    w->ox = (floatw)(ray->ox); w->oy = (floatw)(ray->oy); w->oz = (floatw)(ray->oz);
    w->ix = (floatw)(ray->ix); w->iy = (floatw)(ray->iy); w->iz = (floatw)(ray->iz);
    w->tiny_d = ray->jx != ray->ix || ray->jy != ray->iy || ray->jz != ray->iz;
}

/* Record `row` (8 rows of WIDTH floats) against the ray over [tmin, limit]:
 * hit->s[c] non-zero where lane c is entered, enter->s[c] and leave->s[c] its
 * entry and exit distances. Empty lanes (lower +inf, upper -inf) never pass. */
inline void wide_slab(__global const floatw *row, const Ray *ray, const WideRay *w, float limit,
                      intw_lanes *hit, floatw_lanes *enter, floatw_lanes *leave) {
    floatw t0 = (floatw)(ray->tmin);
    if (w->tiny_d) {
        t0 = max_keep_w((row[w->near_x] - w->ox) * (floatw)(ray->jx), t0);
        t0 = max_keep_w((row[w->near_y] - w->oy) * (floatw)(ray->jy), t0);
        t0 = max_keep_w((row[w->near_z] - w->oz) * (floatw)(ray->jz), t0);
    } else {
        t0 = max_keep_w((row[w->near_x] - w->ox) * w->ix, t0);
        t0 = max_keep_w((row[w->near_y] - w->oy) * w->iy, t0);
        t0 = max_keep_w((row[w->near_z] - w->oz) * w->iz, t0);
    }
    floatw t1 = (floatw)(INFINITY);
    t1 = min_keep_w((row[w->far_x] - w->ox) * w->ix, t1);
    t1 = min_keep_w((row[w->far_y] - w->oy) * w->iy, t1);
    t1 = min_keep_w((row[w->far_z] - w->oz) * w->iz, t1);
    hit->v = t0 <= min_keep_w(t1, (floatw)(limit)) * SLAB_PAD;
    enter->v = t0;
    leave->v = t1;
}

#endif
