/* Stages 1 and 2: triangle boxes and the bounds of their centroids.
 *
 * Karras 2012, section 3: Morton codes are computed from primitive centroids
 * normalised by the scene's centroid bounds. The triangle boxes (min and max of
 * the three vertices, exact) are stored in the caller's triangle order as two
 * float4 each: the Morton stage then reads them contiguously and the refit
 * gathers one 32-byte record per leaf instead of a face and three vertices.
 * The centroid is the box centre, box_centre() in common.h.
 *
 * The reduction is two-level: each work-item reduces a contiguous chunk of
 * triangles to one box, then one work-item reduces those partial boxes.
 */
#include "common.h"

__kernel void triangle_bounds(__global const float *vertices,
                              __global const uint *faces,
                              const int n, const int per_item,
                              __global float4 *boxes /* lo, hi per triangle */,
                              __global float4 *partial /* 2 per work-item */) {
    const int gid = get_global_id(0);
    const int first = chunk_first(gid, per_item, n);
    const int last = chunk_last(gid, per_item, n);
    float3 cmin = (float3)(INFINITY), cmax = (float3)(-INFINITY);
    for (int t = first; t < last; ++t) {
        float3 lo, hi;
        triangle_box(vertices, faces, t, &lo, &hi);
        boxes[2 * t] = (float4)(lo.x, lo.y, lo.z, 0.0f);
        boxes[2 * t + 1] = (float4)(hi.x, hi.y, hi.z, 0.0f);
        float3 c = box_centre(lo, hi);
        cmin = min3(cmin, c);
        cmax = max3(cmax, c);
    }
    partial[2 * gid] = (float4)(cmin.x, cmin.y, cmin.z, 0.0f);
    partial[2 * gid + 1] = (float4)(cmax.x, cmax.y, cmax.z, 0.0f);
}

/* Second level: one work-item folds `count` partial boxes into out[0], out[1]. */
__kernel void reduce_boxes(__global const float4 *partial, const int count,
                           __global float4 *out) {
    if (get_global_id(0) != 0) return;
    float3 lo = (float3)(INFINITY), hi = (float3)(-INFINITY);
    for (int i = 0; i < count; ++i) {
        lo = min3(lo, partial[2 * i].xyz);
        hi = max3(hi, partial[2 * i + 1].xyz);
    }
    out[0] = (float4)(lo.x, lo.y, lo.z, 0.0f);
    out[1] = (float4)(hi.x, hi.y, hi.z, 0.0f);
}
