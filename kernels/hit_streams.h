/* Every hit of many rays at once: the rays walk the wide records together, as
 * streams (kernels/all_hits.cl stream_hits; lbvh/queries/all_hits.py), for
 * both of all_hits.cl's passes.
 *
 * The per-ray walk (every_hit.h wide_tree_hits) waits on memory: every
 * record's rows are a load that depends on the last, and a ray that counts
 * its hits visits every record its line crosses (on a 1M-triangle terrain,
 * about 100 records of 256 bytes a ray, 78 MB of records). Here one
 * work-item takes a chunk of rays and walks the records depth first with
 * the list of its rays that entered each (ray stream traversal: Wald,
 * Gribble, Boulos & Kensler 2007, "SIMD ray stream tracing"; Tsakok 2009,
 * "Faster incoherent rays"; Barringer & Akenine-Moller 2014, "Dynamic ray
 * stream traversal"). A record is read once for all the rays of its list;
 * each ray of the list gets the vector slab test of wide_slab.h, by the
 * same arithmetic, and is appended to the list of every record lane it
 * enters; the triangles of the leaf lanes it enters are tested there and
 * then: their first triangles in one vector computation (lane_triangle_hits,
 * LANE_TRIANGLES), the rest by leaf_hits (every_hit.h). The lists are read in order and their
 * rays' data prefetched a few entries ahead (STREAM_AHEAD), so that the
 * loads overlap instead of waiting one on the next.
 *
 * Every ray enters exactly the records and leaves that its own walk would
 * enter (the same slab test on the same planes), so the counts and the kept
 * hits are the per-ray walk's, whatever the order: accept_hit makes each hit
 * independent of the tree (ray_triangle.h), and the slots keep the first hits
 * only where the host traces the ray again when they overflow (SLOTS_ONLY), the
 * nearest otherwise; each ray's kept hits are sorted after its chunk.
 *
 * Memory (the host's, lbvh/queries/all_hits.py stream_plan): per work-item
 * `per_chunk` rays' Ray (RAY_BYTES each) and slab constants (three float4),
 * and `scratch_words` list entries. A record with a list of n rays takes
 * WIDTH * n entries for its lanes' lists (a list of each lane at a fixed
 * offset, written without a branch), given back when its subtree is done
 * (a marker frame under its children). Where the entries or the frames
 * (STREAM_FRAMES) would run out, the rays of that record go on one by one,
 * by the per-ray walk from it (wide_walk_from): the same hits, so nothing
 * is lost, only the sharing.
 *
 * Defines: WIDTH (wide_rows.h), STACK_SIZE (the per-ray walk's), RAY_BYTES
 * (the host's room for one Ray; the build fails where a Ray is larger),
 * STREAM_FRAMES (frames on a work-item's stack), STREAM_AHEAD (list entries
 * prefetched ahead; 0 for none), CLANG_PREFETCH (every_hit.h), LANE_TRIANGLES
 * (below).
 */
#ifndef LBVH_HIT_STREAMS_H
#define LBVH_HIT_STREAMS_H

#include "every_hit.h"

#if !WIDE
#error "the streams walk the wide records: WIDE=1"
#endif
#ifndef RAY_BYTES
#define RAY_BYTES 192
#endif
#ifndef STREAM_FRAMES
#define STREAM_FRAMES 256
#endif
#ifndef STREAM_AHEAD
#define STREAM_AHEAD 8
#endif

/* the build fails here where the host's room for a Ray is too small */
typedef char ray_fits_in_ray_bytes[sizeof(Ray) <= RAY_BYTES ? 1 : -1];

/* Ray k of a work-item's chunk, in its RAY_BYTES slot. */
inline __global Ray *stream_ray(__global uchar *rays, int k) {
    return (__global Ray *)(rays + (long)RAY_BYTES * k);
}

/* The slab test's constants of ray k, three float4 (o, tmin), (j, tmax), (i, 0):
 * make_ray's origin, 1/d for the near planes (j) and the far ones (i), and
 * the interval. */
inline void put_stream_slab(__global float4 *slabs, int k, const Ray *ray) {
    slabs[3 * k] = (float4)(ray->ox, ray->oy, ray->oz, ray->tmin);
    slabs[3 * k + 1] = (float4)(ray->jx, ray->jy, ray->jz, ray->tmax);
    slabs[3 * k + 2] = (float4)(ray->ix, ray->iy, ray->iz, 0.0f);
}

/* wide_slab for ray k from its slab constants: the lanes of record `row` that the
 * ray's [tmin, tmax] enters, as a bit mask. The same planes, products and
 * comparisons as wide_slab: near planes by the sign bit of d (that of 1/d, -0
 * included), times j, which equals i except where 1/d overflowed, where
 * wide_slab takes j too. */
inline uint stream_slab(__global const floatw *row, __global const float4 *slabs, int k) {
    const float4 a = slabs[3 * k], j = slabs[3 * k + 1], i = slabs[3 * k + 2];
    const floatw ox = (floatw)(a.x), oy = (floatw)(a.y), oz = (floatw)(a.z);
    const int nx = as_int(i.x) < 0, ny = as_int(i.y) < 0, nz = as_int(i.z) < 0;
    floatw t0 = (floatw)(a.w);
    t0 = max_keep_w((row[nx] - ox) * (floatw)(j.x), t0);
    t0 = max_keep_w((row[2 + ny] - oy) * (floatw)(j.y), t0);
    t0 = max_keep_w((row[4 + nz] - oz) * (floatw)(j.z), t0);
    floatw t1 = (floatw)(INFINITY);
    t1 = min_keep_w((row[1 - nx] - ox) * (floatw)(i.x), t1);
    t1 = min_keep_w((row[3 - ny] - oy) * (floatw)(i.y), t1);
    t1 = min_keep_w((row[5 - nz] - oz) * (floatw)(i.z), t1);
    return lane_bits(t0 <= min_keep_w(t1, (floatw)(j.w)) * SLAB_PAD);
}

/* Ray k of a stream asked into the cache ahead of its turn: its slab constants
 * (first and third line, as they fall) and its Ray. */
inline void prefetch_stream_ray(__global const float4 *slabs, __global uchar *rays, int k) {
#if CLANG_PREFETCH && defined(__clang__)
    __builtin_prefetch(slabs + 3 * k);
    __builtin_prefetch(slabs + 3 * k + 2);
    __global const uchar *r = rays + (long)RAY_BYTES * k;
    for (int b = 0; b < RAY_BYTES; b += 64) __builtin_prefetch(r + b);
#endif
}

/* LANE_TRIANGLES: a ray's leaf lanes in a record have their first triangles tested
 * in one vector computation (lane_triangle_hits), from the corners that the
 * record's visit gathers once for its whole list (gather_lane_triangles); where
 * the watertight test has its double fallback (ray_triangle.h WATERTIGHT_FP64)
 * and the triangles are read in slot order (SLOT_TRIANGLES), else 0; the host
 * may say 0 (tests: the same hits as the triangles one by one). */
#ifndef LANE_TRIANGLES
#if defined(WATERTIGHT_FP64) && SLOT_TRIANGLES
#define LANE_TRIANGLES 1
#else
#define LANE_TRIANGLES 0
#endif
#elif LANE_TRIANGLES && !(defined(WATERTIGHT_FP64) && SLOT_TRIANGLES)
#error "LANE_TRIANGLES=1 needs the double fallback and SLOT_TRIANGLES"
#endif

#if LANE_TRIANGLES
/* tri[3 v + a], lane c: axis a of corner v of the first triangle of leaf lane c
 * (slot ref[c]'s, SLOT_TRIANGLES), for the lanes set in leaf_lanes; 0 in the
 * others. */
inline void gather_lane_triangles(__global const float *vertices, __global const int *ref,
                                  uint leaf_lanes, floatw_lanes *tri) {
    for (int j = 0; j < 9; ++j) tri[j].v = (floatw)(0.0f);
    for (uint m = leaf_lanes; m != 0u; m &= m - 1u) {
        const int c = lowest_lane(m);
        __global const float *p = vertices + 9 * ref[c];
        for (int j = 0; j < 9; ++j) tri[j].s[c] = p[j];
    }
}

/* The lanes in `lanes` whose first triangle (in `tri`) the ray, not a hard
 * one, certainly misses, found in one float32 vector computation: the caller
 * tests the others by hit_triangle (ray_triangle.h), whose decisions are
 * exact, so the hits are the same as the triangles one by one. A lane is a
 * certain miss where two of its float32 edge functions U', V', W' have
 * opposite signs by more than their error bound
 *   |F' - F| <= 2^-17 Q S + 2^-39 Q^2 + 2^-120,
 * with Q the largest |p - o| of the triangle's float32 offsets, S the largest
 * |x'|, |y'| of its sheared corners and F the exact edge function (as in
 * hit_triangle; |ex|, |ey| <= |ez| < 1 for a ray that is not hard). Each offset
 * and sheared coordinate is off by at most 6.01 u Q + 2^-125 (u = 2^-24;
 * offsets round once, the shear's products and difference once each; 2^-125
 * for results below float32's normal range, flushed or not), so each edge
 * function by 32.1 u Q S + 145 u^2 Q^2 plus terms that Q >= 2^-100 keeps below
 * the bound; a triangle with Q outside [2^-100, 2^60) (where a product could
 * overflow) is left to hit_triangle. Forced inline: its rows stay in registers. */
__attribute__((always_inline)) inline uint
lane_triangle_misses(const floatw_lanes *tri, const Ray *ray, uint lanes) {
    const int kx = ray->kx, ky = ray->ky, kz = ray->kz;
    const floatw px = (floatw)(ray->px), py = (floatw)(ray->py), pz = (floatw)(ray->pz);
    const floatw ex = (floatw)(ray->ex), ey = (floatw)(ray->ey), ez = (floatw)(ray->ez);
    const intw magnitude = (intw)(0x7fffffff);
#define LANE_ABS(x) as_floatw(as_intw(x) & magnitude)
#define LANE_MAX(x, y) max_keep_w((x), (y))
    const floatw az = tri[kz].v - pz, bz = tri[3 + kz].v - pz, cz = tri[6 + kz].v - pz;
    const floatw pax = tri[kx].v - px, pay = tri[ky].v - py;
    const floatw pbx = tri[3 + kx].v - px, pby = tri[3 + ky].v - py;
    const floatw pcx = tri[6 + kx].v - px, pcy = tri[6 + ky].v - py;
    const floatw ax = pax * ez - az * ex;
    const floatw ay = pay * ez - az * ey;
    const floatw bx = pbx * ez - bz * ex;
    const floatw by = pby * ez - bz * ey;
    const floatw cx = pcx * ez - cz * ex;
    const floatw cy = pcy * ez - cz * ey;
    const floatw U = cx * by - cy * bx;
    const floatw V = ax * cy - ay * cx;
    const floatw W = bx * ay - by * ax;
    floatw Q = LANE_MAX(LANE_MAX(LANE_ABS(az), LANE_ABS(bz)), LANE_ABS(cz));
    Q = LANE_MAX(Q, LANE_MAX(LANE_MAX(LANE_ABS(pax), LANE_ABS(pay)), LANE_ABS(pbx)));
    Q = LANE_MAX(Q, LANE_MAX(LANE_MAX(LANE_ABS(pby), LANE_ABS(pcx)), LANE_ABS(pcy)));
    floatw S = LANE_MAX(LANE_MAX(LANE_ABS(ax), LANE_ABS(ay)), LANE_ABS(bx));
    S = LANE_MAX(S, LANE_MAX(LANE_MAX(LANE_ABS(by), LANE_ABS(cx)), LANE_ABS(cy)));
    const floatw bound = ((floatw)(0x1p-17f) * Q) * S + ((floatw)(0x1p-39f) * Q) * Q +
                         (floatw)(0x1p-120f);
    const floatw nb = -bound;
    const intw pos = (U > bound) | (V > bound) | (W > bound);
    const intw neg = (U < nb) | (V < nb) | (W < nb);
    /* no product underflows past the bound's terms, none overflows (false for NaN) */
    const intw settled = (Q >= (floatw)(0x1p-100f)) & (Q < (floatw)(0x1p60f));
#undef LANE_ABS
#undef LANE_MAX
    return lanes & lane_bits(pos & neg & settled);
}
#endif

/* The hits of the `n` rays of a stream (their Rays and slab constants made,
 * list[0, n) the rays that entered the root record x0's box): counted into
 * counts[k] (which hold each ray's hits so far), and with COUNT=0 kept in ray
 * k's slots [offsets[k], offsets[k + 1]) as leaf_hits keeps them (every_hit.h
 * hit_slot: the kept set does not depend on the order the hits come in);
 * flags[k] gets the per-ray walks' overflow. */
inline void stream_hits(__global const float *records, __global const int *prim_order,
                        __global const float *vertices, __global const uint *slot_faces,
                        int x0, int num_nodes, __global uchar *rays,
                        __global const float4 *slabs, __global int *list, int n,
                        int scratch_words, __global const long *offsets, __global int *counts,
                        __global float *out_t, __global float *out_u, __global float *out_v,
                        __global int *out_prim, __global int *flags) {
    __global const int *words = (__global const int *)records;
    int f_rec[STREAM_FRAMES], f_start[STREAM_FRAMES], f_len[STREAM_FRAMES];
    f_rec[0] = x0; f_start[0] = 0; f_len[0] = n;
    int frames = 1, used = n;
    while (frames > 0) {
        --frames;
        const int x = f_rec[frames], start = f_start[frames], len = f_len[frames];
        if (x < 0) {   /* a marker: the subtree above it is done, its lists given back */
            used = start;
            continue;
        }
        __global const int *mine = list + start;
        if ((long)used + (long)WIDTH * len > scratch_words || frames + 1 + WIDTH > STREAM_FRAMES) {
            for (int j = 0; j < len; ++j) {   /* no room: ray by ray from here */
                const int k = mine[j];
                Ray ray = *stream_ray(rays, k);
                long first;
                const int cap = kept_slots(offsets, k, &first);
                int found = counts[k], flag = 0;
                wide_walk_from(records, prim_order, vertices, slot_faces, x, num_nodes, &ray,
                               first, cap, out_t, out_u, out_v, out_prim, &found, &flag);
                counts[k] = found;
                flags[k] |= flag;
            }
            continue;
        }
        __global const floatw *row = (__global const floatw *)records + 8 * x;
        __global const int *ref = words + 8 * WIDTH * x + 6 * WIDTH;
        /* a lane's y word (row 7) is negative for a leaf, 0 for a record */
        const uint leaf_lanes = lane_bits(((__global const intw *)ref)[1] < (intw)(0));
#if LANE_TRIANGLES
        floatw_lanes tri[9];   /* the leaf lanes' first triangles, for every ray of the list */
        gather_lane_triangles(vertices, ref, leaf_lanes, tri);
#endif
        const int mark = used;
        __global int *out = list + used;
        used += WIDTH * len;
        int lane_n[WIDTH];
        for (int c = 0; c < WIDTH; ++c) lane_n[c] = 0;
        for (int j = 0; j < len; ++j) {
            const int k = mine[j];
#if STREAM_AHEAD
            if (j + STREAM_AHEAD < len) prefetch_stream_ray(slabs, rays, mine[j + STREAM_AHEAD]);
#endif
            const uint entered = stream_slab(row, slabs, k);
            const uint inner = entered & ~leaf_lanes;
            /* k goes on every lane's list; the count moves on where it entered */
#pragma unroll
            for (int c = 0; c < WIDTH; ++c) {
                out[c * len + lane_n[c]] = k;
                lane_n[c] += (int)((inner >> c) & 1u);
            }
            const uint leaves = entered & leaf_lanes;
            if (leaves != 0u) {
                Ray ray = *stream_ray(rays, k);
                long first;
                const int cap = kept_slots(offsets, k, &first);
                int found = counts[k];
                /* the lanes whose first triangle the vector test has not ruled out */
                uint scalar = leaves;
#if LANE_TRIANGLES
                if (!ray.hard) scalar = leaves & ~lane_triangle_misses(tri, &ray, leaves);
#endif
                for (uint m = leaves; m != 0u; m &= m - 1u) {
                    const int c = lowest_lane(m);
                    const int done = (int)((~scalar >> c) & 1u);
                    leaf_hits(prim_order, vertices, slot_faces, ref[c] + done,
                              -ref[WIDTH + c] - done, &ray, 0, first, cap, out_t, out_u, out_v,
                              out_prim, out_prim, &found);
                }
                counts[k] = found;
            }
        }
        /* the marker under the lanes' frames gives their lists back after them */
        f_rec[frames] = -1; f_start[frames] = mark; f_len[frames] = 0; ++frames;
        for (int c = 0; c < WIDTH; ++c) {
            if (lane_n[c] == 0) continue;
            prefetch_record(records, ref[c]);
            f_rec[frames] = ref[c]; f_start[frames] = mark + c * len; f_len[frames] = lane_n[c];
            ++frames;
        }
    }
}

#endif
