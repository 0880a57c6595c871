/* Every hit along each ray, and the hit counts (lbvh/queries/all_hits.py); and
 * move_runs, which gathers the kept hits from their slots (at the end).
 *
 * Per ray, the walk of kernels/every_hit.h: a depth-first traversal of every
 * node (binary, or wide record with WIDE=1) whose box the ray's [tmin, tmax] enters, every triangle of every such
 * leaf tested with the watertight test (Woop, Benthin, Wald 2013) under
 * EDGE_RULE: a ray through an edge or a vertex shared by several triangles
 * hits exactly one of them where it crosses the surface (simulation of
 * simplicity, see ray_triangle.h), so a crossing counts once. A hit counts
 * only where the ray enters the triangle's own box (accept_hit), so the set
 * of hits does not depend on the tree.
 *
 * Two passes over the same traversal: COUNT=1 writes how many hits each ray
 * has in [tmin, tmax]; COUNT=0 writes that count too, and the hits into the
 * ray's slots [offsets[i], offsets[i + 1]) (the host gives a few slots a ray
 * first, then, to the rays with more hits than that, room for all they keep):
 * t, u, v and the triangle in the caller's numbering; past the slots a hit
 * replaces the farthest kept one when it is nearer (by t, then triangle
 * index), so the nearest ones are kept; then the ray's kept hits are sorted
 * in that order (sort_kept).
 *
 * Defines:
 *   STACK_SIZE=n  stack entries; a push beyond n sets FLAG_OVERFLOW and skips
 *                 that subtree (the host sizes it from the tree's depth).
 *   COUNT=0|1     the pass.
 *   SIGNED=1      (COUNT=1) each hit counts by the sign of its crossing, +1
 *                 leaving a triangle by its front, -1 entering (every_hit.h):
 *                 a closed mesh's winding number at the origin of a ray from
 *                 0 to infinity.
 *   SLOTS_ONLY=1  (COUNT=0) a ray fills its slots with its first hits and
 *                 replaces none after, unsorted past them: the host traces
 *                 a ray with more hits than slots again (every_hit.h).
 *   WIDE=1        walk the tree's wide records (kernels/wide.cl, `records`,
 *                 the root's reference (root_x, root_y); WIDTH=4 or 8 lanes)
 *                 instead of its binary nodes: the same hits, one vector slab
 *                 test per record (wide_tree_hits in every_hit.h).
 *   CLANG_MOVMSK, CLANG_CTZ, CLANG_PREFETCH (WIDE=1): clang's builtins for the
 *                 lanes' bit mask, its lowest bit and the records' prefetch,
 *                 where the host says the compiler is clang (wide_rows.h).
 *   SLOT_TRIANGLES=1  `vertices` holds each slot's triangle's corners
 *                 (traverse.cl order_triangles) and slot_faces is not read;
 *                 the wide walk prefetches its leaf lanes' triangles
 *                 (every_hit.h).
 *   COUNTERS=1    (with COUNT=1, WIDE=0) also write per ray the internal nodes and the
 *                 leaves entered and the triangles tested: with tmax at the
 *                 closest hit, the work any traversal must do for that ray
 *                 (the ray-sampled cost of lbvh/verification/quality.py).
 *   SLAB_PAD, NO_FP64: kernels/ray_triangle.h.
 *   RAY_BYTES, STREAM_FRAMES, STREAM_AHEAD, LANE_TRIANGLES (stream_hits_kernel):
 *                 hit_streams.h.
 *
 * stream_hits_kernel (WIDE=1): either pass with the rays walked as streams
 * (hit_streams.h), the host's choice on a CPU: the same counts, hits and flags.
 */
#include "common.h"
#include "every_hit.h"
#if WIDE
#include "hit_streams.h"
#endif

#ifndef COUNTERS
#define COUNTERS 0
#endif
#if COUNTERS && !COUNT
#error "COUNTERS goes with the counting pass"
#endif
#if COUNTERS && WIDE
#error "COUNTERS counts binary nodes: WIDE=0"
#endif

__kernel void all_hits(__global const float4 *nodes, __global const float *records,
                       __global const int *prim_order,
                       __global const float *vertices, __global const uint *slot_faces,
                       const int root, const int root_x, const int root_y, const int num_nodes,
                       __global const float *origins, __global const float *directions,
                       __global const float *tmins, __global const float *tmaxs,
                       const int interval_stride, const int count,
                       __global const long *offsets, __global int *counts,
                       __global float *out_t, __global float *out_u, __global float *out_v,
                       __global int *out_prim, __global int *flags, __global int4 *work) {
    const int i = get_global_id(0);
    if (i >= count) return;
    Ray ray;
    make_ray(&ray, origins + 3 * i, directions + 3 * i, tmins[i * interval_stride],
             tmaxs[i * interval_stride]);
    long first;
    const int cap = kept_slots(offsets, i, &first);
    int found = 0, flag = 0;
    const int nan_ray = ray_has_nan(&ray);
    if (nan_ray) flag |= FLAG_NAN_RAY;
    int visits = 0, leaves = 0, tested = 0;
#if WIDE
    if (!nan_ray)
        wide_tree_hits(nodes, records, prim_order, vertices, slot_faces, root, root_x, root_y,
                       num_nodes, &ray, first, cap, out_t, out_u, out_v, out_prim, &found, &flag);
#else
    if (!nan_ray)
        tree_hits(nodes, prim_order, vertices, slot_faces, root, num_nodes, &ray, 0, first, cap,
                  out_t, out_u, out_v, out_prim, out_prim, &found, &flag, &visits, &leaves,
                  &tested);
#endif
    /* every hit counted in both passes: the collecting pass's count tells the host
     * whether the ray's slots held all it keeps (lbvh/queries/all_hits.py) */
    counts[i] = found;
#if !COUNT
    if (!SLOTS_ONLY || found <= cap)   /* else traced again */
        sort_kept(first, min(found, cap), out_t, out_u, out_v, out_prim, out_prim);
#endif
#if COUNTERS
    work[i] = (int4)(visits - leaves, leaves, tested, 0);
#endif
    flags[i] = flag;
}

#if WIDE
/* Either pass as streams: work-item g takes chunks g, g + items, ... of
 * per_chunk rays each (the host's stream_plan), with its own room for their Rays
 * (RAY_BYTES each), slab constants and lists (scratch_words entries); offsets,
 * out_* and the sort as all_hits above. */
__kernel void stream_hits_kernel(__global const float4 *nodes, __global const float *records,
                                 __global const int *prim_order, __global const float *vertices,
                                 __global const uint *slot_faces, const int root,
                                 const int root_x, const int root_y, const int num_nodes,
                                 __global const float *origins,
                                 __global const float *directions,
                                 __global const float *tmins, __global const float *tmaxs,
                                 const int interval_stride, const int count,
                                 __global const long *offsets, __global int *counts,
                                 __global float *out_t, __global float *out_u,
                                 __global float *out_v, __global int *out_prim,
                                 __global int *flags, const int per_chunk, __global uchar *rays,
                                 __global float4 *slabs, __global int *scratch,
                                 const int scratch_words) {
    const int gid = get_global_id(0), items = get_global_size(0);
    __global uchar *my_rays = rays + (long)gid * per_chunk * RAY_BYTES;
    __global float4 *my_slabs = slabs + (long)gid * per_chunk * 3;
    __global int *list = scratch + (long)gid * scratch_words;
    const int chunks = (count + per_chunk - 1) / per_chunk;
    for (int chunk = gid; chunk < chunks; chunk += items) {
        const int first = chunk * per_chunk, n = min(per_chunk, count - first);
        int entered = 0;
        for (int k = 0; k < n; ++k) {
            const int i = first + k;
            Ray ray;
            make_ray(&ray, origins + 3 * i, directions + 3 * i, tmins[i * interval_stride],
                     tmaxs[i * interval_stride]);
            long slot;
            const int cap = kept_slots(offsets, i, &slot);
            int found = 0, flag = 0;
            const int nan_ray = ray_has_nan(&ray);
            float entry, leave;
            if (nan_ray) {
                flag |= FLAG_NAN_RAY;
            } else if (slab((__global const float *)(nodes + 2 * root), &ray, ray.tmax, &entry,
                            &leave)) {
                if (node_is_leaf(root_y)) {   /* a tree of one leaf: no records */
                    leaf_hits(prim_order, vertices, slot_faces, root_x, -root_y, &ray, 0, slot,
                              cap, out_t, out_u, out_v, out_prim, out_prim, &found);
                } else {
                    *stream_ray(my_rays, k) = ray;
                    put_stream_slab(my_slabs, k, &ray);
                    list[entered++] = k;
                }
            }
            counts[i] = found;
            flags[i] = flag;
        }
        if (entered > 0)
            stream_hits(records, prim_order, vertices, slot_faces, root_x, num_nodes, my_rays,
                        my_slabs, list, entered, scratch_words, offsets + first, counts + first,
                        out_t, out_u, out_v, out_prim, flags + first);
#if !COUNT
        for (int i = first; i < first + n; ++i) {
            long slot;
            const int cap = kept_slots(offsets, i, &slot);
            if (!SLOTS_ONLY || counts[i] <= cap)   /* else traced again */
                sort_kept(slot, min(counts[i], cap), out_t, out_u, out_v, out_prim, out_prim);
        }
#endif
    }
}
#endif

/* The kept hits moved from the collecting pass's slots into the flat arrays the
 * host returns, on the device (lbvh/queries/all_hits.py move_runs): run k, words
 * [src_first[k], src_first[k] + count[k]) of src, goes to [dst_first[k], ...) of
 * dst, one 32-bit column at a time, the runs [chunk_first, chunk_last) per
 * work-item. Only the kept hits cross to the host, not the slots; measured
 * against the host's gather of them (bench/README.md). */
__kernel void move_runs(__global const uint *src, __global uint *dst,
                        __global const long *src_first, __global const long *dst_first,
                        __global const int *count, const int runs, const int per_item) {
    const int gid = get_global_id(0);
    const int last = chunk_last(gid, per_item, runs);
    for (int k = chunk_first(gid, per_item, runs); k < last; ++k) {
        const long from = src_first[k], to = dst_first[k];
        for (int j = 0; j < count[k]; ++j) dst[to + j] = src[from + j];
    }
}
