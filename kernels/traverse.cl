/* Ray traversal of a BVH in the project's layout (docs/pages/layout.md), driven by
 * lbvh/queries/traverse.py. The ray's constants, the slab test and the triangle
 * tests are kernels/ray_triangle.h's.
 *
 * Three kernels:
 *   order_faces  copies the faces in slot order, once per tree;
 *   order_triangles  copies the triangles' corners in slot order, once per
 *                tree and mesh (the every-hit walk's, kernels/every_hit.h);
 *   traverse     traces rays through the tree's wide records (kernels/wide.cl:
 *                up to WIDTH children per node, their boxes in rows of WIDTH
 *                floats, so that one vector slab test covers all children of
 *                a node; Wald, Benthin, Boulos 2008), or through the tree's
 *                own binary nodes (WIDE=0).
 *
 * A work-item traces the rays [chunk_first, chunk_last) one after the other
 * with an explicit stack, in closest-hit or any-hit mode (lbvh/queries/
 * traverse.py: on a GPU one ray per work-item in work-groups of 64; on a CPU
 * work-groups of one work-item over up to 64 rays).
 *
 * Ordered traversal: of the children whose boxes the ray enters, the one with
 * the smallest entry distance is visited first; equal entries: the smaller exit
 * distance; equal again: the one further right. The others are pushed, the
 * nearest last, each with its entry distance, and dropped when popped behind
 * the closest hit so far; a child whose entry lies beyond the closest hit is
 * not entered at all. Any hit (ANY_HIT=1) through wide records visits the
 * children hit unsorted instead, leaves first, each in their record's order:
 * any triangle ends that walk.
 *
 * The answers do not depend on the tree nor on the order the nodes are
 * visited in: a triangle's hit counts only where the ray enters the
 * triangle's own box by the same slab test, its t raised to that box's entry
 * (accept_hit), so the box of every node holding the closest hit's triangle
 * passes the slab test whatever else it holds; and of triangles hit at
 * exactly the same t the one of the lowest index (in the caller's numbering)
 * wins (tie_bound), which is what the numpy twins report. Any hit reports the
 * first triangle it finds.
 *
 * Compile-time variants (-D), all optional:
 *   ANY_HIT=1        stop at the first hit in [tmin, tmax] (occlusion)
 *   COUNTERS=1       write per ray the nodes visited (the root, whose box is
 *                    always tested, plus every node (a wide record, or a
 *                    binary node with WIDE=0) or leaf descended into or
 *                    popped) and the triangles tested
 *   STACK_SIZE=n     stack entries; a push beyond n sets FLAG_OVERFLOW and
 *                    drops that subtree (reported, never silent)
 *   TRIANGLE_TEST, SLAB_PAD, NO_FP64: the ray and triangle tests
 *                    (kernels/ray_triangle.h)
 *   WIDE=0           read the tree's own nodes instead of the wide records
 *   WIDTH=4 or 8     children per wide record (kernels/wide.cl), default 8
 *   RAY_ORDER=1      trace the rays in the order order[] gives (ray_order.cl),
 *                    skipping entries of -1 (packet_traverse.cl's deferred)
 *   EXACT_LEAVES=0   leaves' boxes may be parts of their triangles' (spatial
 *                    splits, lbvh/builders/sbvh.py): a leaf of one triangle is
 *                    then not taken for the triangle's own box (accept_hit)
 *   ORDER_GLOBAL=1   visit nodes by increasing entry distance over all pending
 *                    nodes (a heap; Kay & Kajiya 1986) instead of ordered
 *                    depth first; closest hit only (see push)
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
#ifndef STACK_SIZE
#define STACK_SIZE 64
#endif
#ifndef ORDER_GLOBAL
#define ORDER_GLOBAL 0
#endif
#ifndef EXACT_LEAVES
#define EXACT_LEAVES 1
#endif

#include "ray_triangle.h"

#if ORDER_GLOBAL && ANY_HIT
#error "ORDER_GLOBAL is for closest hits: an any-hit query stops at its first hit anyway"
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
#include "wide_slab.h"
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

/* The pending nodes: references (x, y) with their entry distances. Ordered
 * traversal keeps them on a stack (the nearest child of a node is pushed
 * last); ORDER_GLOBAL=1 keeps them in a binary min-heap on the entry distance
 * (Kay & Kajiya 1986): the traversal always goes on with the nearest pending
 * node of all, and stops when that lies beyond the closest hit. Either way a
 * push beyond STACK_SIZE entries drops the node and sets FLAG_OVERFLOW. */
inline void push(int *sx, int *sy, float *se, int *sp, int *flag, int x, int y, float e) {
    if (*sp >= STACK_SIZE) {
        *flag |= FLAG_OVERFLOW;
        return;
    }
    int c = (*sp)++;
#if ORDER_GLOBAL
    while (c > 0) {   /* sift up */
        const int parent = (c - 1) >> 1;
        if (se[parent] <= e) break;
        sx[c] = sx[parent];
        sy[c] = sy[parent];
        se[c] = se[parent];
        c = parent;
    }
#endif
    sx[c] = x;
    sy[c] = y;
    se[c] = e;
}

#if ORDER_GLOBAL
/* Take the heap's nearest entry (sp > 0). */
inline void pop_nearest(int *sx, int *sy, float *se, int *sp, int *x, int *y, float *e) {
    *x = sx[0];
    *y = sy[0];
    *e = se[0];
    const int n = --(*sp);
    const int lx = sx[n], ly = sy[n];
    const float le = se[n];
    int i = 0;
    for (;;) {   /* sift the last entry down from the root */
        int c = 2 * i + 1;
        if (c >= n) break;
        if (c + 1 < n && se[c + 1] < se[c]) ++c;
        if (se[c] >= le) break;
        sx[i] = sx[c];
        sy[i] = sy[c];
        se[i] = se[c];
        i = c;
    }
    sx[i] = lx;
    sy[i] = ly;
    se[i] = le;
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

/* The corners of each slot's triangle, slot_triangles[9 s + 3 j + a] =
 * vertices[3 faces[prim_order[s]][j] + a]: a leaf's triangle is then one run
 * of 36 bytes, read (and asked into the cache ahead) without the two
 * dependent loads through the faces (kernels/every_hit.h SLOT_TRIANGLES). */
__kernel void order_triangles(__global const float *vertices, __global const uint *faces,
                              __global const int *prim_order, const int num_prims,
                              const int per_item, __global float *slot_triangles) {
    const int gid = get_global_id(0);
    const int last = chunk_last(gid, per_item, num_prims);
    for (int s = chunk_first(gid, per_item, num_prims); s < last; ++s) {
        const int t = prim_order[s];
        /* a degenerate triangle (ray_triangle.h, the same test) as a point: its
         * first corner three times, which no ray hits */
        const int point = degenerate(vertices, 3 * (int)faces[3 * t], 3 * (int)faces[3 * t + 1],
                                     3 * (int)faces[3 * t + 2]);
        for (int j = 0; j < 3; ++j) {
            const uint v = faces[3 * t + (point ? 0 : j)];
            slot_triangles[9 * s + 3 * j] = vertices[3 * v];
            slot_triangles[9 * s + 3 * j + 1] = vertices[3 * v + 1];
            slot_triangles[9 * s + 3 * j + 2] = vertices[3 * v + 2];
        }
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
        /* rays in the order of ray_order.cl's keys; or the rays that the packets
         * left (packet_traverse.cl's deferred), -1 for those they traced */
        const int i = order[k];
        if (i < 0) continue;
#else
        const int i = k;
#endif
        Ray ray;
        make_ray(&ray, origins + 3 * i, directions + 3 * i, tmins[i * interval_stride],
                 tmaxs[i * interval_stride]);
#if WIDE
        WideRay wray;
        make_wide_ray(&ray, &wray);
#endif
        float best = INFINITY, bu = 0.0f, bv = 0.0f;
        int best_slot = -1, flag = 0, visited = 1, tested = 0;
        int sp = 0;
        float entry, leave;
        int x = root_x, y = root_y;
        float x_entry;   /* the slab test's entry distance of node (x, y) */
        const int nan_ray = ray_has_nan(&ray);   /* reported, not traced */
        if (nan_ray) flag |= FLAG_NAN_RAY;
        int go = !nan_ray &&
                 slab((__global const float *)(nodes + 2 * root), &ray, ray.tmax, &entry, &leave);
        x_entry = entry;
        while (go) {
            int have_next = 0, next_x = 0, next_y = 0;
            float next_entry = 0.0f;
            if (node_is_leaf(y)) {
                /* A leaf of one triangle is the triangle's own box (accept_hit), unless
                 * spatial splits clipped it (EXACT_LEAVES=0) */
                const float own = EXACT_LEAVES && y == -1 ? x_entry : -1.0f;
                for (int s = x; s < x - y; ++s) {
                    ++tested;
#if ANY_HIT
                    if (hit_triangle(vertices, 3 * (int)slot_faces[3 * s], 3 * (int)slot_faces[3 * s + 1],
                                     3 * (int)slot_faces[3 * s + 2], &ray, own, &best, &bu, &bv)) {
                        best_slot = s;
                        break;
                    }
#else
                    /* A hit at exactly the closest t so far wins where its
                     * triangle's index is lower (tie_bound) */
                    float t = tie_bound(best), u, v;
                    if (hit_triangle(vertices, 3 * (int)slot_faces[3 * s], 3 * (int)slot_faces[3 * s + 1],
                                     3 * (int)slot_faces[3 * s + 2], &ray, own, &t, &u, &v) &&
                        (t < best || prim_order[s] < prim_order[best_slot])) {
                        best = t;
                        bu = u;
                        bv = v;
                        best_slot = s;
                    }
#endif
                }
#if ANY_HIT
                if (best_slot >= 0) break;
#endif
            } else {
                const float limit = min_keep(best, ray.tmax);
#if WIDE
                /* The slab test of slab() for all lanes at once. */
                intw_lanes hit;
                floatw_lanes enter, exit;
                wide_slab((__global const floatw *)records + 8 * x, &ray, &wray, limit, &hit,
                          &enter, &exit);
                /* The lanes hit (their bit mask, walked bit by bit: no branch
                 * per lane), nearest first by insertion: a later lane goes
                 * before an earlier one of equal entry and exit. */
                int lane[WIDTH];
                int n = 0;
#if ANY_HIT
                /* Any hit: the lanes hit unsorted, the leaves' first (a lane's
                 * y word is negative for a leaf), then the records', each in
                 * the record's order, in one pass over a 16-bit mask. Any
                 * triangle ends the walk, so the nearest child is no better a
                 * guess than the others, and the sort costs more than it saves
                 * (measured 1.7x on Sponza's primary rays, 1.05x on the bunny
                 * and terrain-1m); a leaf is a hit to be had without descending
                 * (1.56-1.63x on Sponza's primary rays, within noise elsewhere;
                 * two passes instead of one lost 12% on terrain-1m;
                 * bench/README.md). */
                {
                    const intw ys = ((__global const intw *)(record_words + 8 * WIDTH * x))[7];
                    const uint all = lane_bits(hit.v);
                    const uint leaves = all & lane_bits(ys < (intw)(0));
                    for (uint m = leaves | (all & ~leaves) << 8; m != 0u; m &= m - 1u)
                        lane[n++] = lowest_bit16(m) & (WIDTH - 1);
                }
#else
                for (uint m = lane_bits(hit.v); m != 0u; m &= m - 1u) {
                    const int c = lowest_lane(m);
                    const float e = enter.s[c], l = exit.s[c];
                    int p = n++;
                    for (; p > 0; --p) {
                        const int o = lane[p - 1];
                        if (enter.s[o] < e || (enter.s[o] == e && exit.s[o] < l)) break;
                        lane[p] = o;
                    }
                    lane[p] = c;
                }
#endif
                if (n > 0) {
                    __global const int *ref = record_words + 8 * WIDTH * x + 6 * WIDTH;
                    for (int m = n - 1; m > 0; --m)
                        push(stack_x, stack_y, stack_entry, &sp, &flag, ref[lane[m]],
                             ref[WIDTH + lane[m]], enter.s[lane[m]]);
                    next_x = ref[lane[0]];
                    next_y = ref[WIDTH + lane[0]];
                    next_entry = enter.s[lane[0]];
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
                    next_entry = left_first ? e0 : e1;
                    have_next = 1;
                    const int2 far = child_ref(record_words, x, left_first ? 1 : 0);
                    push(stack_x, stack_y, stack_entry, &sp, &flag, far.x, far.y,
                         left_first ? e1 : e0);
                } else if (h0 || h1) {
                    const int2 only = child_ref(record_words, x, h0 ? 0 : 1);
                    next_x = only.x;
                    next_y = only.y;
                    next_entry = h0 ? e0 : e1;
                    have_next = 1;
                }
#endif
            }
#if ORDER_GLOBAL
            /* Best first: the nearest child goes on only if no pending node is nearer. */
            if (have_next && sp > 0 && stack_entry[0] < next_entry) {
                push(stack_x, stack_y, stack_entry, &sp, &flag, next_x, next_y, next_entry);
                have_next = 0;
            }
            if (!have_next) {
                /* The nearest pending node; none left, or beyond the closest hit: done. */
                const float cut = min_keep(best, ray.tmax) * SLAB_PAD;
                if (sp == 0 || stack_entry[0] > cut) break;
                pop_nearest(stack_x, stack_y, stack_entry, &sp, &next_x, &next_y, &next_entry);
            }
#else
            if (!have_next) {
                /* Pop, dropping subtrees whose entry lies beyond the closest hit. */
                const float cut = min_keep(best, ray.tmax) * SLAB_PAD;
                while (sp > 0 && stack_entry[sp - 1] > cut) --sp;
                if (sp == 0) break;
                --sp;
                next_x = stack_x[sp];
                next_y = stack_y[sp];
                next_entry = stack_entry[sp];
            }
#endif
            x = next_x;
            y = next_y;
            x_entry = next_entry;
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
