/* Ray order: one 30-bit key per ray, so that sorting the rays by key puts rays
 * that visit the same nodes next to each other (Garanzha & Loop 2010, "Fast
 * Ray Sorting and Breadth-First Packet Traversal for GPU Ray Tracing",
 * section 3: rays hashed by origin cell and direction, then sorted). A
 * work-item traces its rays one after the other, so the nodes a ray shares
 * with the previous one are still in cache.
 *
 *   key = morton(origin cell) << 15 | morton(direction cell)
 *   origin cell:    (o - lower) * inv_extent in [0, 1], 5 bits per axis
 *   direction cell: (d / max|d_i| + 1) / 2 in [0, 1], 5 bits per axis
 *
 * The key only orders the work; every ray gets the same answer in any order.
 * inv_extent comes from the host (float32), so the numpy twin
 * (lbvh/ray_order.py) computes the same keys on a device whose division is
 * correctly rounded.
 */
#include "common.h"

#define CELL_BITS 5

/* Bits per axis of a query point's cell (point_keys): 10, a 30-bit key. */
#define POINT_CELL_BITS 10

/* t in [0, 1] to a cell in [0, 2^bits - 1]; NaN and values outside land in range. */
inline uint cell_of_bits(float t, int bits) {
    float q = t * (float)(1 << bits);
    q = q > 0.0f ? q : 0.0f;  /* NaN compares false: 0 */
    q = q < (float)((1 << bits) - 1) ? q : (float)((1 << bits) - 1);
    return (uint)q;
}

/* The 10 low bits of v spread out, two zero bits after each (bit b to bit
 * 3b), by four shifts and masks instead of a loop over the bits (the
 * point keys of 1M points took 10 ms that way on 2 cores). */
inline uint spread_cell(uint v) {
    v &= 0x3ffu;
    v = (v | (v << 16)) & 0x030000ffu;
    v = (v | (v << 8)) & 0x0300f00fu;
    v = (v | (v << 4)) & 0x030c30c3u;
    return (v | (v << 2)) & 0x09249249u;
}

/* Interleave three cells of `bits` bits (at most 10), x highest (the bit order
 * of morton.cl): bit b of x, y, z goes to bit 3b + 2, 3b + 1, 3b. */
inline uint interleave_bits(uint x, uint y, uint z, int bits) {
    const uint keep = (1u << bits) - 1u;
    return spread_cell(x & keep) << 2 | spread_cell(y & keep) << 1 | spread_cell(z & keep);
}

inline uint cell_of(float t) { return cell_of_bits(t, CELL_BITS); }

inline uint interleave(uint x, uint y, uint z) { return interleave_bits(x, y, z, CELL_BITS); }

__kernel void ray_keys(__global const float *origins, __global const float *directions,
                       const int count, const int per_item, const float4 lower,
                       const float4 inv_extent, __global uint *keys, __global int *order) {
    const int gid = get_global_id(0);
    const int last = chunk_last(gid, per_item, count);
    for (int i = chunk_first(gid, per_item, count); i < last; ++i) {
        const float3 o = load_float3(origins, i);
        const float3 d = load_float3(directions, i);
        const float3 a = (o - lower.xyz) * inv_extent.xyz;
        /* the largest |d_k| (> 0: checked on the host), written out: PoCL 3 calls
         * max and fabs out of line */
        const float ax = abs_bits(d.x), ay = abs_bits(d.y), az = abs_bits(d.z);
        const float m = ax > ay ? (ax > az ? ax : az) : (ay > az ? ay : az);
        const float3 u = (d / m + 1.0f) * 0.5f;
        const uint origin_code = interleave(cell_of(a.x), cell_of(a.y), cell_of(a.z));
        const uint direction_code = interleave(cell_of(u.x), cell_of(u.y), cell_of(u.z));
        keys[i] = origin_code << (3 * CELL_BITS) | direction_code;
        order[i] = i;
    }
}

/* The same for query points (lbvh/queries/closest.py): the Morton code of the
 * point's cell, 10 bits per axis, so that nearby points are answered one after
 * the other and find the same nodes in cache. */
__kernel void point_keys(__global const float *points, const int count, const int per_item,
                         const float4 lower, const float4 inv_extent, __global uint *keys,
                         __global int *order) {
    const int gid = get_global_id(0);
    const int last = chunk_last(gid, per_item, count);
    for (int i = chunk_first(gid, per_item, count); i < last; ++i) {
        const float3 a = (load_float3(points, i) - lower.xyz) * inv_extent.xyz;
        keys[i] = interleave_bits(cell_of_bits(a.x, POINT_CELL_BITS),
                                  cell_of_bits(a.y, POINT_CELL_BITS),
                                  cell_of_bits(a.z, POINT_CELL_BITS), POINT_CELL_BITS);
        order[i] = i;
    }
}

/* The query points in the order of point_keys' sort: sorted[k] = points[order[k]],
 * so that a walk answering the points in that order reads them as one run
 * (kernels/winding.cl, POINT_ORDER=1): the loads here are independent of each
 * other and overlap, where a walk's first load of a scattered point waits. */
__kernel void gather_points(__global const float *points, __global const int *order,
                            const int count, const int per_item, __global float *sorted) {
    const int gid = get_global_id(0);
    const int last = chunk_last(gid, per_item, count);
    for (int k = chunk_first(gid, per_item, count); k < last; ++k) {
        const int i = order[k];
        sorted[3 * k] = points[3 * i];
        sorted[3 * k + 1] = points[3 * i + 1];
        sorted[3 * k + 2] = points[3 * i + 2];
    }
}
