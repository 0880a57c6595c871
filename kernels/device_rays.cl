/* Rays held in the caller's device arrays (pyopencl.array.Array): their
 * conversion to float32, the checks of lbvh/queries/rays.py on the device, the
 * bad rays turned into misses, and the traversal's flags turned into the
 * result's arrays (lbvh/queries/rays.py, lbvh/queries/traverse.py). One item
 * per work-item; each kernel stops at `count`.
 *
 * Defines:
 *   SRC_T=type   to_float32: the element type converted (float, double, int,
 *                uint, long, ulong; double only where the device has it)
 *   COUNTERS=0|1 hits_from_flags: also split the per-ray counters
 */
#include "common.h"

#define FLAG_OVERFLOW 1
#define FLAG_VISIT_LIMIT 2

/* A device without doubles gets no double conversion (the host refuses float64
 * arrays there), so every variant compiles on every device. */
#if defined(SRC_T) && (!defined(SRC_IS_DOUBLE) || defined(cl_khr_fp64))
#if defined(SRC_IS_DOUBLE)
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#endif
/* dst[i] = (float)src[first + i], rounding to nearest as numpy's astype(np.float32) does */
__kernel void to_float32(__global const SRC_T *src, const int first, __global float *dst,
                         const int count) {
    const int i = get_global_id(0);
    if (i < count) dst[i] = (float)src[first + i];
}
#endif

/* The rules of check_rays on float32 bit patterns (no flush of denormals can
 * change them); the numpy twin is lbvh.queries.rays.invalid_mask. */
inline int finite_bits(uint x) { return (x & 0x7f800000u) != 0x7f800000u; }

inline int bad_ray(__global const float *o, __global const float *d, float tmin, float tmax) {
    int bad = !(finite_bits(as_uint(o[0])) && finite_bits(as_uint(o[1])) &&
                finite_bits(as_uint(o[2])) && finite_bits(as_uint(d[0])) &&
                finite_bits(as_uint(d[1])) && finite_bits(as_uint(d[2])));
    bad |= ((as_uint(d[0]) | as_uint(d[1]) | as_uint(d[2])) << 1) == 0u;   /* zero length */
    const uint lo = as_uint(tmin), hi = as_uint(tmax);
    const int lo_ok = (lo << 1) == 0u || lo < 0x7f800000u;         /* +-0 or finite positive */
    const int hi_nan = (hi & 0x7fffffffu) > 0x7f800000u;
    const uint lo_mag = lo & 0x7fffffffu;
    /* tmin <= tmax for a tmin in [0, max]: tmax negative only as -0 against a zero tmin */
    const int ordered = (hi & 0x80000000u) ? (lo_mag == 0u && (hi << 1) == 0u) : (hi >= lo_mag);
    return bad | !lo_ok | hi_nan | !ordered;
}

/* bad[i]: ray i breaks a rule; *bad_count: how many do (zeroed by the host). */
__kernel void ray_validity(__global const float *origins, __global const float *directions,
                           __global const float *tmin, __global const float *tmax,
                           const int interval_stride, const int count, __global char *bad,
                           __global int *bad_count) {
    const int i = get_global_id(0);
    if (i >= count) return;
    const int b = bad_ray(origins + 3 * i, directions + 3 * i, tmin[i * interval_stride],
                          tmax[i * interval_stride]);
    bad[i] = (char)b;
    if (b) atomic_inc(bad_count);
}

/* Per-ray intervals with tmin NaN where bad: the traversal does not trace those
 * (FLAG_NAN_RAY) and reports a miss. */
__kernel void mark_invalid(__global const float *tmin, __global const float *tmax,
                           const int interval_stride, __global const char *bad, const int count,
                           __global float *tmin_out, __global float *tmax_out) {
    const int i = get_global_id(0);
    if (i >= count) return;
    tmin_out[i] = bad[i] ? NAN : tmin[i * interval_stride];
    tmax_out[i] = tmax[i * interval_stride];
}

/* The traversal's flag words to the result's bool arrays (overflow, hit) and
 * the overflow count; with COUNTERS the counters split per field, 0 for bad rays.
 * hit_planes: the traversal's four planes of `count` words (t, u, v, triangle). */
__kernel void hits_from_flags(__global const int *flags, __global const int *hit_planes,
                              __global const char *bad, const int count,
                              __global char *overflow, __global char *hit,
                              __global int *overflow_count, __global const int *counters,
                              __global int *nodes, __global int *tris) {
    const int i = get_global_id(0);
    if (i >= count) return;
    const int o = (flags[i] & (FLAG_OVERFLOW | FLAG_VISIT_LIMIT)) != 0;
    overflow[i] = (char)o;
    if (o) atomic_inc(overflow_count);
    hit[i] = (char)(hit_planes[3 * count + i] >= 0);
#if COUNTERS
    nodes[i] = bad[i] ? 0 : counters[2 * i];
    tris[i] = bad[i] ? 0 : counters[2 * i + 1];
#endif
}
