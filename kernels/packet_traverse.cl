/* Ray traversal by packets of 8 rays through a tree's 8-wide records, driven
 * by lbvh/queries/packets.py: the closest-hit and any-hit queries of
 * kernels/traverse.cl for coherent rays (camera views, scans, rays towards
 * one light) on a CPU.
 *
 * A work-item traces the rays [chunk_first, chunk_last) in packets of 8
 * consecutive rays of the rays' order (RAY_ORDER=1: ray_order.cl's Morton
 * keys of origins and directions, which puts neighbouring rays together).
 * The packet shares each record's fetch, its ordering and its stack: one
 * record's box of each child is tested against all 8 rays at once, lane by
 * lane the slab test of kernels/ray_triangle.h slab() (Wald, Slusallek,
 * Benthin, Wagner 2001: coherent packets; Wald, Boulos, Shirley 2007: the
 * packet goes on into a node that any of its rays enters). Each stack entry
 * carries the mask of the rays that entered it and their entry distances,
 * so a ray leaves a subtree as its own walk would (its mask bit clears when
 * the entry lies beyond its closest hit), and a leaf's triangles are tested
 * only by the rays whose own slab test entered it, each by hit_triangle
 * with the ray's own constants: the single-ray walk's test, bit for bit.
 *
 * The answers are those of kernels/traverse.cl, bit for bit: a ray's hit
 * counts only where the ray enters the triangle's own box (accept_hit), so
 * every node above its closest hit passes that ray's own slab test whatever
 * the other rays do, and among triangles hit at exactly the same t the one
 * of the lowest index wins in both (tie_bound), which makes the answer
 * independent of the order the nodes are visited in. Any hit stops each ray
 * at its first hit: the same rays hit, possibly another triangle.
 *
 * Compile-time variants (-D): ANY_HIT, STACK_SIZE, RAY_ORDER, EXACT_LEAVES,
 * TRIANGLE_TEST, SLAB_PAD, NO_FP64 as kernels/traverse.cl; WIDTH must be 8.
 * Inputs and outputs as traverse.cl's traverse (no counters).
 */
#include "common.h"

#ifndef ANY_HIT
#define ANY_HIT 0
#endif
#ifndef STACK_SIZE
#define STACK_SIZE 64
#endif
#ifndef EXACT_LEAVES
#define EXACT_LEAVES 1
#endif
#ifndef RAY_ORDER
#define RAY_ORDER 0
#endif
#ifndef WIDTH
#define WIDTH 8
#endif
#if WIDTH != 8
#error "packets of 8 rays walk 8-wide records (WIDTH=8)"
#endif

#include "ray_triangle.h"
#include "wide_rows.h"

#define PACKET 8

typedef union { float8 v; float s[PACKET]; } packet_floats;

/* Bit r set where lane r of a comparison (0 or -1) is set. */
inline uint packet_bits(int8 v) { return lane_bits(v); }

/* One child box (its six planes) against the packet's rays over [tmin,
 * limit]: slab() of kernels/ray_triangle.h lane by lane (the near plane by
 * the sign bit of d, 1/d with jx.. for the near planes, NaN distances
 * ignored, the entry padded by SLAB_PAD), the same operations in the same
 * order. */
inline uint packet_slab(float lx, float ux, float ly, float uy, float lz, float uz,
                        const float8 *o, const float8 *inv_near, const float8 *inv_far,
                        const int8 *neg, int signs, float8 tmin, float8 limit, float8 *entry) {
    float8 near_x, near_y, near_z, far_x, far_y, far_z;
    if (signs >= 0) {
        /* the packet's rays share the signs of d (bits 0-2: x, y, z negative):
         * one plane each for all of them */
        near_x = (float8)(signs & 1 ? ux : lx);
        near_y = (float8)(signs & 2 ? uy : ly);
        near_z = (float8)(signs & 4 ? uz : lz);
        far_x = (float8)(signs & 1 ? lx : ux);
        far_y = (float8)(signs & 2 ? ly : uy);
        far_z = (float8)(signs & 4 ? lz : uz);
    } else {
        near_x = neg[0] ? (float8)(ux) : (float8)(lx);
        near_y = neg[1] ? (float8)(uy) : (float8)(ly);
        near_z = neg[2] ? (float8)(uz) : (float8)(lz);
        far_x = neg[0] ? (float8)(lx) : (float8)(ux);
        far_y = neg[1] ? (float8)(ly) : (float8)(uy);
        far_z = neg[2] ? (float8)(lz) : (float8)(uz);
    }
    float8 t0 = tmin;
    t0 = max_keep_w((near_x - o[0]) * inv_near[0], t0);
    t0 = max_keep_w((near_y - o[1]) * inv_near[1], t0);
    t0 = max_keep_w((near_z - o[2]) * inv_near[2], t0);
    float8 t1 = (float8)(INFINITY);
    t1 = min_keep_w((far_x - o[0]) * inv_far[0], t1);
    t1 = min_keep_w((far_y - o[1]) * inv_far[1], t1);
    t1 = min_keep_w((far_z - o[2]) * inv_far[2], t1);
    *entry = t0;
    return packet_bits(t0 <= min_keep_w(t1, limit) * SLAB_PAD);
}

/* The smallest of the lanes set in `bits` (the packet's entry into a child,
 * to order the children nearest first). */
inline float packet_nearest(float8 e, uint bits) {
    const int8 on = (int8)(1, 2, 4, 8, 16, 32, 64, 128) & (int8)((int)bits);
    const float8 m = on != (int8)(0) ? e : (float8)(INFINITY);
    const float4 a = m.lo < m.hi ? m.lo : m.hi;
    const float2 b = a.lo < a.hi ? a.lo : a.hi;
    return b.x < b.y ? b.x : b.y;
}

/* Whether the rays of a packet (indices id[0..n)) stay together through the
 * tree, read from the rays' arrays before anything else is made of them:
 * their directions, each scaled to a largest component of 1, differ by at
 * most COHERENT_DIRECTION in every component from the first ray's, and how
 * far apart they can get within the box (the spread of their origins plus
 * that of their directions times the length of ray that can meet the box:
 * tmax, or the distance to the box's far side) is at most COHERENT_SPREAD
 * times the root box's largest extent (all in the largest component). A
 * camera's or a scanner's neighbouring rays pass; rays bounced off a surface
 * in random directions (ambient occlusion: 1.05-1.31x the single-ray walk's
 * time as packets) and rays in no order (shuffled camera rays: 0.54-0.62x
 * its speed) do not: their rays are left to the single-ray walk
 * (`deferred`). The bounds, 2^-4 each, are the measured ones: at 1/4 and 1/2
 * the Morton-sorted AO rays of terrain-1m passed and took 1.12x and 1.19x the
 * single-ray walk's time (closest, any hit); at 2^-4 0.97x and 0.98x its
 * speed, and camera rays kept 1.08-1.36x (bench/README.md). A NaN fails every
 * comparison: such a packet is deferred too. Only the speed depends on this
 * test, never an answer. */
#ifndef COHERENT_DIRECTION
#define COHERENT_DIRECTION 0x1p-4f
#endif
#ifndef COHERENT_SPREAD
#define COHERENT_SPREAD 0x1p-4f
#endif
inline float unit_max(float x, float y, float z) {
    return max_keep(max_keep(abs_bits(x), abs_bits(y)), abs_bits(z));
}
inline int packet_coherent(__global const float *origins, __global const float *directions,
                           __global const float *tmaxs, int interval_stride, const int *id,
                           int n, __global const float *root_box) {
    if (n < 2) return 1;
    const float extent = unit_max(root_box[4] - root_box[0], root_box[5] - root_box[1],
                                  root_box[6] - root_box[2]);
    __global const float *o0 = origins + 3 * id[0], *d0 = directions + 3 * id[0];
    const float far = unit_max(o0[0] - 0.5f * (root_box[0] + root_box[4]),
                               o0[1] - 0.5f * (root_box[1] + root_box[5]),
                               o0[2] - 0.5f * (root_box[2] + root_box[6])) + extent;
    const float m0 = unit_max(d0[0], d0[1], d0[2]);
    const float ax = d0[0] / m0, ay = d0[1] / m0, az = d0[2] / m0;
    float directions_apart = 0.0f, origins_apart = 0.0f,
          reach = tmaxs[id[0] * interval_stride] * m0;
    for (int r = 1; r < n; ++r) {
        __global const float *o = origins + 3 * id[r], *d = directions + 3 * id[r];
        const float m = unit_max(d[0], d[1], d[2]);
        const float apart = unit_max(d[0] / m - ax, d[1] / m - ay, d[2] / m - az);
        const float moved = unit_max(o[0] - o0[0], o[1] - o0[1], o[2] - o0[2]);
        if (!(apart <= COHERENT_DIRECTION && moved <= extent)) return 0;
        directions_apart = max_keep(apart, directions_apart);
        origins_apart = max_keep(moved, origins_apart);
        reach = max_keep(tmaxs[id[r] * interval_stride] * m, reach);
    }
    return origins_apart + directions_apart * min_keep(reach, far) <= COHERENT_SPREAD * extent;
}

__kernel void traverse_packets(__global const float4 *nodes, __global const float *records,
                               __global const int *prim_order, __global const float *vertices,
                               __global const uint *slot_faces, const int root, const int root_x,
                               const int root_y, const int num_nodes,
                               __global const float *origins, __global const float *directions,
                               __global const float *tmins, __global const float *tmaxs,
                               const int interval_stride, __global const int *order,
                               __global float *hits, __global int *flags,
                               __global int *deferred, const int count, const int per_item) {
    const int gid = get_global_id(0);
    const int first = chunk_first(gid, per_item, count);
    const int last = chunk_last(gid, per_item, count);
    __global const int *record_words = (__global const int *)records;
    int stack_x[STACK_SIZE];
    int stack_y[STACK_SIZE];
    uint stack_mask[STACK_SIZE];
    float8 stack_entry[STACK_SIZE];

    for (int k0 = first; k0 < last; k0 += PACKET) {
        Ray ray[PACKET];
        int id[PACKET];
        float best[PACKET], bu[PACKET], bv[PACKET];
        int best_slot[PACKET], flag[PACKET];
        packet_floats ox, oy, oz, jx, jy, jz, ix, iy, iz, t_min, t_max;
        int8 negx, negy, negz;
        uint live = 0u;   /* the rays of the packet being traced */
        const int n = last - k0 < PACKET ? last - k0 : PACKET;
        for (int r = 0; r < PACKET; ++r) {
            /* a short last packet repeats its first ray in the lanes past the
             * end, which are not traced */
            const int k = r < n ? k0 + r : k0;
#if RAY_ORDER
            id[r] = order[k];
#else
            id[r] = k;
#endif
        }
        /* A packet whose rays part at once would test every record's boxes for 8
         * rays on behalf of one or two: its rays go to the single-ray walk, which
         * traces the rays listed in deferred (-1: traced here) after this kernel
         * (lbvh/queries/packets.py). */
        __global const float *root_box = (__global const float *)(nodes + 2 * root);
        const int together =
            packet_coherent(origins, directions, tmaxs, interval_stride, id, n, root_box);
        for (int r = 0; r < n; ++r) deferred[k0 + r] = together ? -1 : id[r];
        if (!together) continue;
        for (int r = 0; r < PACKET; ++r) {
            const int i = id[r];
            make_ray(&ray[r], origins + 3 * i, directions + 3 * i, tmins[i * interval_stride],
                     tmaxs[i * interval_stride]);
            best[r] = INFINITY;
            bu[r] = 0.0f;
            bv[r] = 0.0f;
            best_slot[r] = -1;
            flag[r] = 0;
            if (ray_has_nan(&ray[r]))
                flag[r] |= FLAG_NAN_RAY;   /* reported, not traced */
            else if (r < n)
                live |= 1u << r;
            ox.s[r] = ray[r].ox; oy.s[r] = ray[r].oy; oz.s[r] = ray[r].oz;
            jx.s[r] = ray[r].jx; jy.s[r] = ray[r].jy; jz.s[r] = ray[r].jz;
            ix.s[r] = ray[r].ix; iy.s[r] = ray[r].iy; iz.s[r] = ray[r].iz;
            t_min.s[r] = ray[r].tmin;
            t_max.s[r] = ray[r].tmax;
        }
        /* the sign bits of d as lane masks (as prepare_ray's nx, ny, nz) */
        {
            packet_floats dx, dy, dz;
            for (int r = 0; r < PACKET; ++r) {
                dx.s[r] = ray[r].dx; dy.s[r] = ray[r].dy; dz.s[r] = ray[r].dz;
            }
            negx = as_int8(dx.v) < (int8)(0);
            negy = as_int8(dy.v) < (int8)(0);
            negz = as_int8(dz.v) < (int8)(0);
        }
        const float8 o[3] = {ox.v, oy.v, oz.v};
        const float8 inv_near[3] = {jx.v, jy.v, jz.v};
        const float8 inv_far[3] = {ix.v, iy.v, iz.v};
        const int8 neg[3] = {negx, negy, negz};
        /* the signs the rays share, or -1 */
        const uint sx = packet_bits(negx), sy = packet_bits(negy), sz = packet_bits(negz);
        const int signs = (sx == 0u || sx == 0xffu) && (sy == 0u || sy == 0xffu) &&
                                  (sz == 0u || sz == 0xffu)
                              ? (int)(sx & 1u) | (int)(sy & 1u) << 1 | (int)(sz & 1u) << 2
                              : -1;
        packet_floats best_v;
        best_v.v = (float8)(INFINITY);

        packet_floats x_entry;
        uint mask = live & packet_slab(root_box[0], root_box[4], root_box[1], root_box[5],
                                       root_box[2], root_box[6], o, inv_near, inv_far, neg, signs,
                                       t_min.v, t_max.v, &x_entry.v);
        int x = root_x, y = root_y;
        int sp = 0, visited = 1;
        uint done = 0u;   /* any hit: the rays that have hit */
        while (mask != 0u) {
            uint next_mask = 0u;
            int next_x = 0, next_y = 0;
            packet_floats next_entry;
            if (node_is_leaf(y)) {
                for (uint m = mask; m != 0u; m &= m - 1u) {
                    const int r = lowest_lane(m);
                    /* a leaf of one triangle is the triangle's own box (accept_hit) */
                    const float own = EXACT_LEAVES && y == -1 ? x_entry.s[r] : -1.0f;
                    for (int s = x; s < x - y; ++s) {
#if ANY_HIT
                        if (hit_triangle(vertices, 3 * (int)slot_faces[3 * s],
                                         3 * (int)slot_faces[3 * s + 1],
                                         3 * (int)slot_faces[3 * s + 2], &ray[r], own, &best[r],
                                         &bu[r], &bv[r])) {
                            best_slot[r] = s;
                            done |= 1u << r;
                            break;
                        }
#else
                        /* a tie goes to the lower index (tie_bound) */
                        float t = tie_bound(best[r]), u, v;
                        if (hit_triangle(vertices, 3 * (int)slot_faces[3 * s],
                                         3 * (int)slot_faces[3 * s + 1],
                                         3 * (int)slot_faces[3 * s + 2], &ray[r], own, &t, &u,
                                         &v) &&
                            (t < best[r] || prim_order[s] < prim_order[best_slot[r]])) {
                            best[r] = t;
                            bu[r] = u;
                            bv[r] = v;
                            best_slot[r] = s;
                            best_v.s[r] = t;
                        }
#endif
                    }
                }
            } else {
                const float8 limit = min_keep_w(best_v.v, t_max.v);
                __global const float *row = records + 8 * WIDTH * x;
                __global const int *ref = record_words + 8 * WIDTH * x + 6 * WIDTH;
                /* the children any ray enters, nearest (by the packet's least
                 * entry) first by insertion */
                uint child_mask[WIDTH];
                float child_near[WIDTH];
                float8 child_entry[WIDTH];
                int lane[WIDTH];
                int n = 0;
                for (int c = 0; c < WIDTH; ++c) {
                    float8 e;
                    const uint b = mask & packet_slab(row[c], row[WIDTH + c], row[2 * WIDTH + c],
                                                      row[3 * WIDTH + c], row[4 * WIDTH + c],
                                                      row[5 * WIDTH + c], o, inv_near, inv_far,
                                                      neg, signs, t_min.v, limit, &e);
                    if (b == 0u) continue;
                    const float near = packet_nearest(e, b);
                    child_mask[c] = b;
                    child_entry[c] = e;
                    child_near[c] = near;
                    int p = n++;
                    for (; p > 0; --p) {
                        const int q = lane[p - 1];
                        if (child_near[q] <= near) break;
                        lane[p] = q;
                    }
                    lane[p] = c;
                }
                for (int m = n - 1; m > 0; --m) {
                    const int c = lane[m];
                    if (sp >= STACK_SIZE) {
                        for (uint b = child_mask[c]; b != 0u; b &= b - 1u)
                            flag[lowest_lane(b)] |= FLAG_OVERFLOW;
                        continue;
                    }
                    stack_x[sp] = ref[c];
                    stack_y[sp] = ref[WIDTH + c];
                    stack_mask[sp] = child_mask[c];
                    stack_entry[sp] = child_entry[c];
                    ++sp;
                }
                if (n > 0) {
                    const int c = lane[0];
                    next_x = ref[c];
                    next_y = ref[WIDTH + c];
                    next_mask = child_mask[c];
                    next_entry.v = child_entry[c];
                }
            }
            /* Pop while no ray of the entry is still before its closest hit. */
            const float8 cut = min_keep_w(best_v.v, t_max.v) * SLAB_PAD;
            while (next_mask == 0u && sp > 0) {
                --sp;
                next_x = stack_x[sp];
                next_y = stack_y[sp];
                next_entry.v = stack_entry[sp];
                next_mask = stack_mask[sp] & ~done & packet_bits(next_entry.v <= cut);
            }
            next_mask &= ~done;
            mask = next_mask;
            x = next_x;
            y = next_y;
            x_entry = next_entry;
            if (mask != 0u && ++visited > num_nodes) {
                for (int r = 0; r < PACKET; ++r) flag[r] |= FLAG_VISIT_LIMIT;
                break;
            }
        }
        for (int r = 0; r < n; ++r) {
            const int i = id[r];
            float t = best[r];
            if (ray[r].texp != 0) t = ldexp(t, -ray[r].texp);
            hits[i] = t + 0.0f;
            hits[count + i] = bu[r];
            hits[2 * count + i] = bv[r];
            hits[3 * count + i] = as_float(best_slot[r] >= 0 ? prim_order[best_slot[r]] : -1);
            flags[i] = flag[r];
        }
    }
}
