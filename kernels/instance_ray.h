/* A world ray moved into an instance's space: what kernels/instances.cl
 * (closest and any hit) and kernels/instance_hits.cl (every hit) share.
 *
 * An instance's inverse transform is 12 floats, M row by row then c
 * (lbvh/queries/instances.py): the moved ray is o' = M o + c, d' = M d, which
 * keeps the ray parameter t (o' + t d' is the world point o + t d moved).
 */
#ifndef LBVH_INSTANCE_RAY_H
#define LBVH_INSTANCE_RAY_H
#include "ray_triangle.h"

#include "scene_chunks.h"

/* *moved: the world ray w (ox, oy, oz, dx, dy, dz as given) moved by the inverse
 * transform m, over [tmin, tmax], prepared (prepare_ray). Returns 0, with
 * *moved unprepared, where the moved direction is zero: nothing to trace. */
inline int move_ray(__global const float *m, const float *w, float tmin, float tmax,
                    Ray *moved) {
    /* the identity (parts of one mesh) moves nothing, not even the sign of a zero */
    const int identity = m[0] == 1.0f && m[1] == 0.0f && m[2] == 0.0f && m[3] == 0.0f &&
                         m[4] == 1.0f && m[5] == 0.0f && m[6] == 0.0f && m[7] == 0.0f &&
                         m[8] == 1.0f && m[9] == 0.0f && m[10] == 0.0f && m[11] == 0.0f;
    if (identity) {
        moved->ox = w[0]; moved->oy = w[1]; moved->oz = w[2];
        moved->dx = w[3]; moved->dy = w[4]; moved->dz = w[5];
    } else {
        moved->ox = m[0] * w[0] + m[1] * w[1] + m[2] * w[2] + m[9];
        moved->oy = m[3] * w[0] + m[4] * w[1] + m[5] * w[2] + m[10];
        moved->oz = m[6] * w[0] + m[7] * w[1] + m[8] * w[2] + m[11];
        moved->dx = m[0] * w[3] + m[1] * w[4] + m[2] * w[5];
        moved->dy = m[3] * w[3] + m[4] * w[4] + m[5] * w[5];
        moved->dz = m[6] * w[3] + m[7] * w[4] + m[8] * w[5];
    }
    moved->tmin = tmin;
    moved->tmax = tmax;
    if (moved->dx == 0.0f && moved->dy == 0.0f && moved->dz == 0.0f) return 0;
    prepare_ray(moved);
    return 1;
}

/* The world ray of ray i as given (make_ray may have scaled its own copy), into
 * w[6]; whether any of it, or of [tmin, tmax], is NaN. */
inline int world_ray(__global const float *origins, __global const float *directions, int i,
                     float tmin, float tmax, float *w) {
    for (int k = 0; k < 3; ++k) {
        w[k] = origins[3 * i + k];
        w[3 + k] = directions[3 * i + k];
    }
    int nan = tmin != tmin || tmax != tmax;   /* isnan */
    for (int k = 0; k < 6; ++k) nan |= w[k] != w[k];
    return nan;
}

#endif
