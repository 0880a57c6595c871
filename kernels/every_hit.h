/* Every hit of one ray in one mesh's tree, counted or kept: the walk that
 * kernels/all_hits.cl (one mesh) and kernels/instance_hits.cl (each instance
 * of a scene) share.
 *
 * A depth-first traversal of the binary nodes (docs/pages/layout.md) enters every
 * node whose box the ray's [tmin, tmax] enters, by the slab test of
 * kernels/ray_triangle.h, and tests every triangle of every such leaf with
 * the watertight test under EDGE_RULE (a crossing through a shared edge or
 * vertex counts once). A hit counts only where the ray enters the triangle's
 * own box (accept_hit), so the set of hits does not depend on the tree.
 *
 * Defines (-D): STACK_SIZE, COUNT, SIGNED, SLOTS_ONLY, WIDE and WIDTH, as all_hits.cl
 * documents them (WIDE=1 adds wide_tree_hits, the walk through wide records,
 * and with it CLANG_MOVMSK, CLANG_CTZ and CLANG_PREFETCH, wide_rows.h). The
 * includer may define HIT_INSTANCE=1: each kept hit then carries an instance
 * index too, and hits of equal t are ordered by instance before triangle.
 * SLOT_TRIANGLES=1: `vertices` holds each slot's triangle as its three corners
 * (kernels/traverse.cl order_triangles: slot s at 9 s, 9 s + 3, 9 s + 6; a
 * degenerate triangle as three copies of its first corner, so that accept_hit
 * leaves out its degenerate() test: ray_triangle.h DEGENERATE_TEST) and
 * slot_faces is not read; the wide walk then asks the triangles of the leaf
 * lanes it enters into the cache before it pushes the record lanes
 * (prefetch_triangle), so that their loads overlap. Measured against the
 * faces and vertices (9-11 alternated rounds of 262,144 of the queries
 * bench's rays, Zen 3), count_hits: 1.09x on the bunny, 1.07x on Sponza,
 * 1.18x on terrain-1m; the prefetch through the faces alone, 1.04x and 1.06x.
 */
#ifndef LBVH_EVERY_HIT_H
#define LBVH_EVERY_HIT_H

#ifndef STACK_SIZE
#define STACK_SIZE 64
#endif
#ifndef COUNT
#define COUNT 1
#endif
/* SIGNED=1 (counting only): each hit counts -1 where the ray enters a
 * triangle's front and +1 where it leaves by it (hit_triangle's sign, negated).
 * Along a ray from tmin = 0 to infinity, where the winding number of a closed
 * surface falls to 0, each crossing changes it by the crossing's sign, so the
 * count is the winding number at the origin (the degree of the surface about
 * it); the edge rule makes that exact for the rounded, translated corners the
 * test sees, through shared edges and vertices too. */
#ifndef SIGNED
#define SIGNED 0
#endif
#if SIGNED && !COUNT
#error "SIGNED counts the crossings: it keeps no hits"
#endif
/* SLOTS_ONLY=1 (collecting): a ray keeps its first hits while its slots last and
 * replaces none after; the host traces a ray with more hits than slots again */
#ifndef SLOTS_ONLY
#define SLOTS_ONLY 0
#endif

#if defined(TRIANGLE_TEST) && TRIANGLE_TEST != 0
#error "every hit is counted with the watertight test only"
#endif
#define EDGE_RULE 1
#if defined(SLOT_TRIANGLES) && SLOT_TRIANGLES
/* order_triangles made the degenerate triangles points: accept_hit need not
 * test each hit for it (1.07x on Sponza's hit counts with the test left out) */
#define DEGENERATE_TEST 0
#endif
#include "ray_triangle.h"

#ifndef HIT_INSTANCE
#define HIT_INSTANCE 0
#endif
#ifndef WIDE
#define WIDE 0
#endif
#ifndef SLOT_TRIANGLES
#define SLOT_TRIANGLES 0
#endif

/* (t, instance, prim) ordering: nearer first, then the lower instance, then the
 * lower triangle index. */
inline int before(float ta, int ia, int pa, float tb, int ib, int pb) {
    return ta < tb || (ta == tb && (ia < ib || (ia == ib && pa < pb)));
}

/* Where the found-th hit (t, inst, prim) of a ray goes among its cap slots from
 * `first`: the next free one while they last; past the cap the farthest kept
 * hit's, when this one is nearer; -1 for nowhere. */
inline long hit_slot(long first, int cap, int found, float t, int inst, int prim,
                     __global const float *out_t, __global const int *out_inst,
                     __global const int *out_prim) {
    if (found < cap) return first + found;
#if SLOTS_ONLY
    /* the host traces a ray with more hits than its slots again: none replaced */
    return -1;
#endif
    if (cap <= 0) return -1;
    long far = first;
    for (long k = first + 1; k < first + cap; ++k)
        if (before(out_t[far], HIT_INSTANCE ? out_inst[far] : 0, out_prim[far], out_t[k],
                   HIT_INSTANCE ? out_inst[k] : 0, out_prim[k]))
            far = k;
    return before(t, inst, prim, out_t[far], HIT_INSTANCE ? out_inst[far] : 0, out_prim[far])
               ? far : -1;
}

/* A step of the walk at an internal node whose children are a and b: the child
 * to enter next, -1 for none; b pushed when both are entered (a full stack sets
 * FLAG_OVERFLOW and skips it). */
inline int enter_children(__global const float4 *nodes, int a, int b, const Ray *ray, int *stack,
                          int *top, int *flag) {
    float ea, eb, leave;
    const int in_a = slab((__global const float *)(nodes + 2 * a), ray, ray->tmax, &ea, &leave);
    const int in_b = slab((__global const float *)(nodes + 2 * b), ray, ray->tmax, &eb, &leave);
    if (in_a && in_b) {
        if (*top < STACK_SIZE) stack[(*top)++] = b;
        else *flag |= FLAG_OVERFLOW;
    }
    return in_a ? a : (in_b ? b : -1);
}

/* The slots of ray i's kept hits: returns how many, from *first (offsets: the
 * host's prefix sum of the capped counts); none in the counting pass. */
inline int kept_slots(__global const long *offsets, int i, long *first) {
#if COUNT
    *first = 0;
    return 0;
#else
    *first = offsets[i];
    return (int)(offsets[i + 1] - offsets[i]);
#endif
}

#if !COUNT
/* Whether kept hit j goes before kept hit k: by t, then instance, then triangle. */
inline int kept_before(long j, long k, __global const float *out_t, __global const int *out_inst,
                       __global const int *out_prim) {
    return before(out_t[j], HIT_INSTANCE ? out_inst[j] : 0, out_prim[j], out_t[k],
                  HIT_INSTANCE ? out_inst[k] : 0, out_prim[k]);
}

inline void swap_kept(long j, long k, __global float *out_t, __global float *out_u,
                      __global float *out_v, __global int *out_prim, __global int *out_inst) {
    float f = out_t[j]; out_t[j] = out_t[k]; out_t[k] = f;
    f = out_u[j]; out_u[j] = out_u[k]; out_u[k] = f;
    f = out_v[j]; out_v[j] = out_v[k]; out_v[k] = f;
    int i = out_prim[j]; out_prim[j] = out_prim[k]; out_prim[k] = i;
#if HIT_INSTANCE
    i = out_inst[j]; out_inst[j] = out_inst[k]; out_inst[k] = i;
#endif
}

/* The n kept hits of a ray, slots [first, first + n), sorted in place by
 * kept_before: a heapsort (Williams 1964), O(n log n) however many hits a ray
 * has, so that the host needs no sort of its own. */
inline void sort_kept(long first, int n, __global float *out_t, __global float *out_u,
                      __global float *out_v, __global int *out_prim, __global int *out_inst) {
    for (int end = n; end > 0; --end) {
        /* heapify on the first pass; then sift the new root of [0, end) down */
        for (int start = end == n ? n / 2 - 1 : 0; start >= 0; --start) {
            int root = start;
            for (;;) {
                int child = 2 * root + 1;
                if (child >= end) break;
                if (child + 1 < end &&
                    kept_before(first + child, first + child + 1, out_t, out_inst, out_prim))
                    ++child;
                if (!kept_before(first + root, first + child, out_t, out_inst, out_prim)) break;
                swap_kept(first + root, first + child, out_t, out_u, out_v, out_prim, out_inst);
                root = child;
            }
            if (end != n) break;
        }
        swap_kept(first, first + end - 1, out_t, out_u, out_v, out_prim, out_inst);
    }
}
#endif

/* Slot s's triangle's hit (t, u, v) of *ray counted in *found (with SIGNED, by
 * `sign`, hit_triangle's, as SIGNED says) and, with COUNT=0, kept (hit_slot): t
 * along the direction *ray was made from (make_ray's scaling undone), the
 * triangle in prim_order's numbering and, with HIT_INSTANCE, `inst`. */
inline void keep_hit(__global const int *prim_order, int s, int sign, float t, float u, float v,
                     const Ray *ray, int inst, long first, int cap, __global float *out_t,
                     __global float *out_u, __global float *out_v, __global int *out_prim,
                     __global int *out_inst, int *found) {
#if !COUNT
    /* t along d * 2^-texp (make_ray) back to d; + 0.0f: no -0.0 */
    if (ray->texp != 0) t = ldexp(t, -ray->texp);
    t += 0.0f;
    const int prim = prim_order[s];
    const long slot = hit_slot(first, cap, *found, t, inst, prim, out_t, out_inst, out_prim);
    if (slot >= 0) {
        out_t[slot] = t;
        out_u[slot] = u;
        out_v[slot] = v;
        out_prim[slot] = prim;
#if HIT_INSTANCE
        out_inst[slot] = inst;
#endif
    }
#endif
#if SIGNED
    *found -= sign;
#else
    ++*found;
#endif
}

/* Every hit of *ray among the `count` triangles of slots [s0, s0 + count): *found
 * counts them; with COUNT=0 they are kept in [first, first + cap) (hit_slot), t
 * along the direction *ray was made from (make_ray's scaling undone), the
 * triangle in prim_order's numbering and, with HIT_INSTANCE, `inst`. */
inline void leaf_hits(__global const int *prim_order, __global const float *vertices,
                      __global const uint *slot_faces, int s0, int count, const Ray *ray,
                      int inst, long first, int cap, __global float *out_t,
                      __global float *out_u, __global float *out_v, __global int *out_prim,
                      __global int *out_inst, int *found) {
    for (int s = s0; s < s0 + count; ++s) {
        float t = INFINITY, u = 0.0f, v = 0.0f;
#if SLOT_TRIANGLES
        const int sign = hit_triangle(vertices, 9 * s, 9 * s + 3, 9 * s + 6, ray, -1.0f, &t, &u,
                                      &v);
#else
        const int sign = hit_triangle(vertices, 3 * (int)slot_faces[3 * s],
                                      3 * (int)slot_faces[3 * s + 1],
                                      3 * (int)slot_faces[3 * s + 2], ray, -1.0f, &t, &u, &v);
#endif
        if (sign == 0) continue;
        keep_hit(prim_order, s, sign, t, u, v, ray, inst, first, cap, out_t, out_u, out_v, out_prim,
                 out_inst, found);
    }
}

/* Every hit of *ray in the tree at `root` (of `num_nodes` nodes): *found counts
 * them; with COUNT=0 they are kept in [first, first + cap) (hit_slot), t along
 * the direction *ray was made from (make_ray's scaling undone), the triangle in
 * prim_order's numbering and, with HIT_INSTANCE, `inst`. *visits, *leaves and
 * *tested count the nodes entered, the leaves among them and the triangles
 * tested; *flag gets FLAG_OVERFLOW or FLAG_VISIT_LIMIT. */
inline void tree_hits(__global const float4 *nodes, __global const int *prim_order,
                      __global const float *vertices, __global const uint *slot_faces,
                      int root, int num_nodes, const Ray *ray, int inst, long first, int cap,
                      __global float *out_t, __global float *out_u, __global float *out_v,
                      __global int *out_prim, __global int *out_inst, int *found, int *flag,
                      int *visits, int *leaves, int *tested) {
    float entry, leave;
    int node = slab((__global const float *)(nodes + 2 * root), ray, ray->tmax, &entry,
                    &leave) ? root : -1;
    int stack[STACK_SIZE];
    int top = 0, steps = 0;
    for (;;) {
        if (node >= 0) {
            ++*visits;
            if (++steps > num_nodes) {
                *flag |= FLAG_VISIT_LIMIT;
                break;
            }
            const int a = as_int(nodes[2 * node].w), b = as_int(nodes[2 * node + 1].w);
            if (node_is_leaf(b)) {
                ++*leaves;
                *tested -= b;
                leaf_hits(prim_order, vertices, slot_faces, a, -b, ray, inst, first, cap, out_t,
                          out_u, out_v, out_prim, out_inst, found);
                node = -1;
            } else {
                node = enter_children(nodes, a, b, ray, stack, &top, flag);
            }
            continue;
        }
        if (top == 0) break;
        node = stack[--top];
    }
}

#if WIDE
#include "wide_slab.h"

/* Slot s's triangle asked into the cache ahead of its test (SLOT_TRIANGLES: its
 * 36 bytes at `vertices` + 9 s, over one or two lines of 64 bytes), by clang's
 * builtin where the host says the compiler is clang (CLANG_PREFETCH, as
 * prefetch_record), else by OpenCL's prefetch(). */
inline void prefetch_triangle(__global const float *vertices, int s) {
    __global const float *p = vertices + 9 * s;
#if CLANG_PREFETCH && defined(__clang__)
    __builtin_prefetch(p);
    __builtin_prefetch(p + 8);
#else
    prefetch(p, 9);
#endif
}

/* The walk of wide_tree_hits (below) from record x on, for a ray that entered its
 * box; also where a stream's rays go on one by one (hit_streams.h). */
inline void wide_walk_from(__global const float *records, __global const int *prim_order,
                           __global const float *vertices, __global const uint *slot_faces,
                           int x, int num_nodes, const Ray *ray, long first, int cap,
                           __global float *out_t, __global float *out_u, __global float *out_v,
                           __global int *out_prim, int *found, int *flag) {
    WideRay w;
    make_wide_ray(ray, &w);
    __global const int *words = (__global const int *)records;
    int stack[STACK_SIZE];
    int top = 0, steps = 0;
    for (;;) {
        if (++steps > num_nodes) {
            *flag |= FLAG_VISIT_LIMIT;
            break;
        }
        intw_lanes hit;
        floatw_lanes enter, exit;
        wide_slab((__global const floatw *)records + 8 * x, ray, &w, ray->tmax, &hit, &enter,
                  &exit);
        __global const int *ref = words + 8 * WIDTH * x + 6 * WIDTH;
        const uint entered = lane_bits(hit.v);
        /* a lane's y word (row 7) is negative for a leaf, 0 for a record */
        const uint leaves = entered & lane_bits(((__global const intw *)ref)[1] < (intw)(0));
        const uint inner = entered & ~leaves;
        const int next = inner != 0u ? lowest_lane(inner) : -1;
#if SLOT_TRIANGLES
        for (uint m = leaves; m != 0u; m &= m - 1u)
            prefetch_triangle(vertices, ref[lowest_lane(m)]);
#endif
        for (uint m = inner; m != 0u; m &= m - 1u) {
            const int c = lowest_lane(m);
            prefetch_record(records, ref[c]);
            if (c == next) continue;
            if (top < STACK_SIZE) stack[top++] = ref[c];
            else *flag |= FLAG_OVERFLOW;
        }
        for (uint m = leaves; m != 0u; m &= m - 1u) {
            const int c = lowest_lane(m);
            leaf_hits(prim_order, vertices, slot_faces, ref[c], -ref[WIDTH + c], ray, 0, first,
                      cap, out_t, out_u, out_v, out_prim, out_prim, found);
        }
        if (next >= 0) {
            x = ref[next];
        } else {
            if (top == 0) break;
            x = stack[--top];
        }
    }
}

/* tree_hits through the tree's wide records (kernels/wide.cl): the root's
 * reference (root_x, root_y) as kernels/traverse.cl takes it (a leaf's node
 * words, or (record, 0)), after its box in `nodes` is entered. At a record,
 * one vector slab test (wide_slab.h) gives the lanes the ray's [tmin, tmax]
 * enters, as a bit mask (lane_bits): the records among them are asked into
 * the cache (prefetch_record: every one will be visited, whatever the order)
 * and all but the first pushed, then the leaves among them are tested there
 * and then, and the walk goes on to the first record. Only records go on the
 * stack: a leaf is never pushed and popped again. The same hits as the binary
 * walk: accept_hit decides each triangle by its own box. Measured against
 * the walk that pushed every lane it entered, leaves included, one branch a
 * lane (9 alternated rounds of 262,144 of the queries bench's rays, Zen 3):
 * count_hits 1.16x on the bunny, 1.10x on Sponza and terrain-1m; the
 * prefetch alone 1.07-1.11x; records renumbered depth first, nothing. */
inline void wide_tree_hits(__global const float4 *nodes, __global const float *records,
                           __global const int *prim_order, __global const float *vertices,
                           __global const uint *slot_faces, int root, int root_x, int root_y,
                           int num_nodes, const Ray *ray, long first, int cap,
                           __global float *out_t, __global float *out_u, __global float *out_v,
                           __global int *out_prim, int *found, int *flag) {
    float entry, leave;
    if (!slab((__global const float *)(nodes + 2 * root), ray, ray->tmax, &entry, &leave))
        return;
    if (node_is_leaf(root_y)) {   /* a tree of one leaf: no records */
        leaf_hits(prim_order, vertices, slot_faces, root_x, -root_y, ray, 0, first, cap, out_t,
                  out_u, out_v, out_prim, out_prim, found);
        return;
    }
    wide_walk_from(records, prim_order, vertices, slot_faces, root_x, num_nodes, ray, first, cap,
                   out_t, out_u, out_v, out_prim, found, flag);
}

#endif

#endif
