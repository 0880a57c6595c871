/* PLOC: Meister & Bittner 2018, "Parallel Locally-Ordered Clustering for
 * Bounding Volume Hierarchy Construction" (IEEE TVCG 24(3)).
 *
 * The leaves start as clusters in Morton order. A step:
 *   ploc_nearest  each cluster's nearest neighbour among the RADIUS clusters on
 *                 either side: the least half area of the union of the two boxes
 *                 (scaled_half_area at the ROOT box's box_scale, the same for every
 *                 step); candidates by distance k = 1 .. r, at each k the
 *                 preferred side first (the right, i + k, for an even i, the left
 *                 for an odd one), with a strict <: equal areas go to the nearer
 *                 cluster, and at equal distance to the preferred side;
 *   ploc_count    per chunk of clusters: the mutual pairs (nearest[nearest[i]] == i)
 *                 that start at i (i < nearest[i]) and the clusters kept (all but the
 *                 pairs' upper members);
 *   ploc_scan     one work-item: the chunks' exclusive prefix sums, in place, and the
 *                 next step's cluster count;
 *   ploc_merge    each pair makes a node (box: min/max of its two, children: the lower
 *                 position's cluster, then the upper's) at its lower member's place;
 *                 the others are copied in order: the compacted list goes to the other
 *                 cluster buffer (the host swaps the two).
 * Merges are numbered in increasing position within a step and steps follow
 * each other: before a step of m clusters, F - m merges were made, so the
 * step's k-th pair makes internal node F - m + k; the last node made (F - 2)
 * is the root. Leaf of slot k is node F - 1 + k (the Karras numbering of the
 * leaves, docs/pages/layout.md). lbvh/builders/ploc.py has the numpy twin
 * (ploc_numpy): the same float32 operations, bit for bit.
 *
 * A step of m >= 2 clusters always merges: follow i -> nearest[i] ->
 * nearest[nearest[i]] ...; i is among the candidates of nearest[i] (the window
 * is symmetric), so the areas along the walk never grow, and the finite walk
 * ends in a cycle, all of whose areas are then equal. In a cycle x0 -> x1 ->
 * x2 -> ... of length three or more, x1 chose x2 over x0 at an equal area, so
 * x2 is not farther from x1 than x0 is; around the cycle the distances never
 * grow, so they are all equal, and x0, x2 (distinct) lie on either side of x1:
 * the cycle moves one way along the list and cannot close. Every cycle is a
 * mutual pair.
 *
 * Why the nearer cluster, and the side by parity, among equal areas: a run of
 * clusters with one box (identical triangles) then merges in pairs (2i, 2i + 1)
 * and halves at every step: about log2(run) levels. Ties to the lower index,
 * the rule before, merged one pair per step and made a chain as deep as the
 * run (20,000 identical triangles: depth 19,999, beyond any traversal stack).
 *
 * The clusters of a step are held in planes (structure of arrays) of `cap`
 * (F) entries each: lower.x, lower.y, lower.z, upper.x, upper.y, upper.z, then
 * the node (an int). The nearest-neighbour pass then reads LANES consecutive
 * clusters' coordinates with one vector load. Leaf boxes hold +0.0 for -0.0
 * (as refit.cl's leaf_box): min3 and max3 of boxes without -0.0 are
 * symmetric, and the nodes' boxes are the refit's.
 *
 * The kernels of a step read the cluster count m from counts[side] on the
 * device, so the host queues several steps before it reads one (counts[2]:
 * set when a step of m >= 2 merged nothing, which the argument above rules
 * out; the host raises on it). A kernel's chunk is step_per_item(m, items,
 * min_per) clusters: its launch of `items` work-items is sized once for the
 * count the host last read, and the chunks shrink with m.
 *
 * The last steps, from at most the host's tail size of clusters on, run in one
 * work-item (ploc_tail): the same steps in the same order, without four
 * launches for each step of the few clusters left.
 *
 * RADIUS (define): the search radius (Meister & Bittner's r; default 16).
 * LANES (define): 8 on a CPU, where ploc_nearest takes eight consecutive
 * clusters at once in explicit vectors (PoCL does not vectorise a work-item's
 * loop by itself; see emit.cl), 1 on a GPU (one cluster per work-item).
 * CLANG_PREFETCH (define): as refit.cl's, 1 where the compiler is clang (PoCL):
 * ploc_leaves gathers the triangle boxes in slot order, randomly in memory
 * when the mesh's triangles are not in spatial order, and prefetches the box
 * PREFETCH_AHEAD slots on with clang's builtin (OpenCL's prefetch() does
 * nothing on PoCL; about 2.5x on a random soup of 1M triangles).
 */
#include "common.h"

#ifndef RADIUS
#define RADIUS 16
#endif
#ifndef LANES
#define LANES 8
#endif
#if LANES != 8 && LANES != 1
#error "LANES must be 8 or 1"
#endif

/* Clusters per work-item for a step of m clusters over `items` work-items. */
inline int step_per_item(int m, int items, int min_per) {
    const int even = (int)(((long)m + items - 1) / items);
    return even > min_per ? even : min_per;
}

/* This work-item's chunk [first, last) of a step of m clusters over `items`
 * work-items; returns m. */
inline int step_chunk(int m, int items, int min_per, int *first, int *last) {
    const int per = step_per_item(m, items, min_per);
    const int gid = get_global_id(0);
    *first = chunk_first(gid, per, m);
    *last = chunk_last(gid, per, m);
    return m;
}

/* Plane `plane` of the clusters at c (offsets as size_t: 7 planes of cap). */
inline __global const float *plane_of(__global const float *c, int cap, int plane) {
    return c + (size_t)plane * (size_t)cap;
}
inline float3 cluster_lo(__global const float *c, int cap, int i) {
    return (float3)(plane_of(c, cap, 0)[i], plane_of(c, cap, 1)[i], plane_of(c, cap, 2)[i]);
}
inline float3 cluster_hi(__global const float *c, int cap, int i) {
    return (float3)(plane_of(c, cap, 3)[i], plane_of(c, cap, 4)[i], plane_of(c, cap, 5)[i]);
}
inline int cluster_node(__global const float *c, int cap, int i) {
    return ((__global const int *)plane_of(c, cap, 6))[i];
}
inline void write_cluster(__global float *c, int cap, int i, float3 lo, float3 hi, int node) {
    const size_t stride = (size_t)cap;
    c[i] = lo.x;
    c[stride + i] = lo.y;
    c[2 * stride + i] = lo.z;
    c[3 * stride + i] = hi.x;
    c[4 * stride + i] = hi.y;
    c[5 * stride + i] = hi.z;
    ((__global int *)c)[6 * stride + i] = node;
}

inline void write_node(__global float *node_floats, int node, float3 lo, float3 hi, int a, int b) {
    __global float *p = node_floats + 8 * (size_t)node;
    store_float3(p, lo);
    ((__global int *)p)[3] = a;
    store_float3(p + 4, hi);
    ((__global int *)p)[7] = b;
}

/* Half area of the union of boxes a and b, a the cluster of lower position. */
inline float merged_area(float3 alo, float3 ahi, float3 blo, float3 bhi, float scale) {
    return scaled_half_area(min3(alo, blo), max3(ahi, bhi), scale);
}

/* The leaves: leaf node F - 1 + k of slot k (triangle prim_order[k]'s box,
 * +0.0 for -0.0) and the first clusters; a box of each chunk's leaves in
 * `partial` (bounds.cl's reduce_boxes makes the root box of them); counts[0] =
 * F, counts[2] = 0. A single triangle is the root: its parent is -1. */
__kernel void ploc_leaves(__global const float4 *boxes /* lo, hi per triangle (bounds.cl) */,
                          __global const int *prim_order, const int n, const int per_item,
                          __global float *nodes, __global int *parent,
                          __global float *clusters, __global int *counts,
                          __global float4 *partial /* 2 per work-item */) {
    const int gid = get_global_id(0);
    const int first = chunk_first(gid, per_item, n);
    const int last = chunk_last(gid, per_item, n);
    float3 rlo = (float3)(INFINITY), rhi = (float3)(-INFINITY);
    for (int k = first; k < last; ++k) {
        if (k + PREFETCH_AHEAD < last) PREFETCH_BOX(boxes + 2 * prim_order[k + PREFETCH_AHEAD]);
        const int t = prim_order[k];
        const float3 lo = boxes[2 * t].xyz + (float3)(0.0f);
        const float3 hi = boxes[2 * t + 1].xyz + (float3)(0.0f);
        write_node(nodes, n - 1 + k, lo, hi, k, -1);
        write_cluster(clusters, n, k, lo, hi, n - 1 + k);
        rlo = min3(rlo, lo);
        rhi = max3(rhi, hi);
    }
    partial[2 * gid] = (float4)(rlo.x, rlo.y, rlo.z, 0.0f);
    partial[2 * gid + 1] = (float4)(rhi.x, rhi.y, rhi.z, 0.0f);
    if (gid == 0) {
        counts[0] = n;
        counts[2] = 0;
        if (n == 1) parent[0] = -1;
    }
}

/* Cluster i's nearest neighbour among positions i - r .. i + r of m: by
 * distance k, the preferred side (right for an even i) first, a strict <. */
inline int nearest_one(__global const float *c, int cap, int m, int r, int i, float scale) {
    const float3 lo = cluster_lo(c, cap, i), hi = cluster_hi(c, cap, i);
    float best = INFINITY;
    int nn = -1;
    for (int k = 1; k <= r; ++k) {
        for (int side = 0; side < 2; ++side) {
            const int right = (side == 0) == ((i & 1) == 0);
            const int j = right ? i + k : i - k;
            if (j < 0 || j > m - 1) continue;
            const float3 jlo = cluster_lo(c, cap, j), jhi = cluster_hi(c, cap, j);
            const float a = right ? merged_area(lo, hi, jlo, jhi, scale)
                                  : merged_area(jlo, jhi, lo, hi, scale);
            if (a < best) {
                best = a;
                nn = j;
            }
        }
    }
    return nn;
}

#if LANES == 8
/* Eight consecutive floats from p (unaligned), each lane one cluster. */
inline float8 load8(__global const float *p) {
    return (float8)(p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7]);
}

/* Lanewise min3 and max3 (common.h): the first argument where it is not
 * greater (not less), as the scalar forms. */
inline float8 min8(float8 a, float8 b) { return a < b ? a : b; }
inline float8 max8(float8 a, float8 b) { return a > b ? a : b; }

/* Lanewise merged_area of the eight clusters whose box planes are `own`
 * (lower.x, .y, .z, upper.x, .y, .z) and the eight clusters from position
 * j0 on; `own_first`: the own clusters are the pairs' lower positions. */
inline float8 lanes_area(__global const float *c, int cap, int j0, const float8 *own,
                         int own_first, float scale) {
    float8 d[3];
    for (int axis = 0; axis < 3; ++axis) {
        const float8 lo = load8(plane_of(c, cap, axis) + j0);
        const float8 hi = load8(plane_of(c, cap, axis + 3) + j0);
        const float8 mlo = own_first ? min8(own[axis], lo) : min8(lo, own[axis]);
        const float8 mhi = own_first ? max8(own[axis + 3], hi) : max8(hi, own[axis + 3]);
        d[axis] = mhi * scale - mlo * scale;
    }
    return d[0] * d[1] + d[1] * d[2] + d[2] * d[0];
}
#endif

/* The nearest neighbours of positions [first, last) of m clusters (-1 when
 * m < 2), in nearest_one's order of candidates. With LANES 8, eight
 * consecutive clusters go at once, each distance one vector step for all eight
 * (every lane's candidates in the scalar order: its preferred side first);
 * clusters within r + 7 of either end of the list, and the range's last few,
 * one by one. */
inline void nearest_range(__global const float *c, int cap, int m, int first, int last,
                          float scale, __global int *nearest) {
    const int r = m - 1 < RADIUS ? m - 1 : RADIUS;
    int i = first;
#if LANES == 8
    const int8 lane = (int8)(0, 1, 2, 3, 4, 5, 6, 7);
    for (; i + 8 <= last; i += 8) {
        if (i - r < 0 || i + 7 + r > m - 1) {
            for (int k = i; k < i + 8; ++k) nearest[k] = nearest_one(c, cap, m, r, k, scale);
            continue;
        }
        float8 own[6];
        for (int plane = 0; plane < 6; ++plane) own[plane] = load8(plane_of(c, cap, plane) + i);
        float8 best = (float8)(INFINITY);
        int8 nn = (int8)(-1);
        /* lanes at an even position take the right candidate first */
        const int8 even = ((lane + i) & 1) == 0;
        for (int k = 1; k <= r; ++k) {
            const float8 left = lanes_area(c, cap, i - k, own, 0, scale);
            const float8 right = lanes_area(c, cap, i + k, own, 1, scale);
            const float8 first_area = even ? right : left;
            const int8 first_j = even ? lane + (i + k) : lane + (i - k);
            const float8 second_area = even ? left : right;
            const int8 second_j = even ? lane + (i - k) : lane + (i + k);
            int8 better = first_area < best;
            best = better ? first_area : best;
            nn = better ? first_j : nn;
            better = second_area < best;
            best = better ? second_area : best;
            nn = better ? second_j : nn;
        }
        nearest[i] = nn.s0;
        nearest[i + 1] = nn.s1;
        nearest[i + 2] = nn.s2;
        nearest[i + 3] = nn.s3;
        nearest[i + 4] = nn.s4;
        nearest[i + 5] = nn.s5;
        nearest[i + 6] = nn.s6;
        nearest[i + 7] = nn.s7;
    }
#endif
    for (; i < last; ++i) nearest[i] = nearest_one(c, cap, m, r, i, scale);
}

/* Each cluster's nearest neighbour (nearest_range over the work-item's chunk). */
__kernel void ploc_nearest(__global const float *c, const int cap, __global const int *counts,
                           const int side, const int items, const int min_per,
                           __global const float4 *root_box, __global int *nearest) {
    int first, last;
    const int m = step_chunk(counts[side], items, min_per, &first, &last);
    if (first >= last) return;
    nearest_range(c, cap, m, first, last, box_scale(root_box[0].xyz, root_box[1].xyz), nearest);
}

/* Whether position i is in a mutual pair (its partner: nearest[i]). */
inline int is_mutual(__global const int *nearest, int i, int nn) {
    return nn >= 0 && nearest[nn] == i;
}

/* Per chunk: pairs starting in it, clusters it keeps (chunk_counts: 2 ints each). */
__kernel void ploc_count(__global const int *nearest, __global const int *counts, const int side,
                         const int items, const int min_per, __global int *chunk_counts) {
    int first, last;
    const int m = step_chunk(counts[side], items, min_per, &first, &last);
    if (first >= last) return;
    const int gid = get_global_id(0);
    int pairs = 0, kept = 0;
    for (int i = first; i < last; ++i) {
        const int nn = nearest[i];
        const int mutual = is_mutual(nearest, i, nn);
        pairs += mutual && i < nn;
        kept += !mutual || i < nn;
    }
    chunk_counts[2 * gid] = pairs;
    chunk_counts[2 * gid + 1] = kept;
}

/* One work-item: exclusive prefix sums of the chunks' counts, in place; the
 * next step's count in counts[1 - side]; counts[2] = 1 if nothing merged. */
__kernel void ploc_scan(__global int *chunk_counts, __global int *counts, const int side,
                        const int items, const int min_per) {
    if (get_global_id(0) != 0) return;
    const int m = counts[side];
    const int per = step_per_item(m, items, min_per);
    const int chunks = (int)(((long)m + per - 1) / per);
    int pairs = 0, kept = 0;
    for (int c = 0; c < chunks; ++c) {
        const int p = chunk_counts[2 * c], k = chunk_counts[2 * c + 1];
        chunk_counts[2 * c] = pairs;
        chunk_counts[2 * c + 1] = kept;
        pairs += p;
        kept += k;
    }
    counts[1 - side] = kept;
    if (m >= 2 && pairs == 0) counts[2] = 1;
}

/* Position i of a step of m clusters: merged by its partner (nothing written),
 * the lower member of a pair (node *made over the two, written at *at), or kept
 * (copied to *at). Both boxes are read before any branch (the partner's is
 * unused unless i starts a pair; in ploc_tail's in place compaction it may be
 * overwritten already then): about 1.2x faster than reading them behind the
 * branches (a step of 1M clusters on PoCL). */
inline void merge_one(__global const float *c, int cap, __global const int *nearest, int m, int i,
                      __global float *nodes, __global int *parent, __global float *out,
                      int *made, int *at) {
    const int nn = nearest[i];
    const int partner = nn >= 0 ? nn : i;
    const int mutual = nn >= 0 && nearest[partner] == i;
    const int pair = mutual && i < nn;
    const float3 lo = cluster_lo(c, cap, i), hi = cluster_hi(c, cap, i);
    const float3 plo = cluster_lo(c, cap, partner), phi = cluster_hi(c, cap, partner);
    const int node = cluster_node(c, cap, i), other = cluster_node(c, cap, partner);
    const float3 mlo = pair ? min3(lo, plo) : lo;
    const float3 mhi = pair ? max3(hi, phi) : hi;
    if (pair) {
        write_node(nodes, *made, mlo, mhi, node, other);
        parent[node] = *made;
        parent[other] = *made;
        if (m == 2) parent[*made] = -1;
    }
    if (!mutual || pair) {   /* not merged by its partner */
        write_cluster(out, cap, *at, mlo, mhi, pair ? *made : node);
        ++*at;
    }
    *made += pair;
}

/* The merges and the compaction: pair k of the step (k counted in increasing
 * position) makes node F - m + k over (cluster[i], cluster[nearest[i]]) and
 * sets both children's parents (the root's, -1, when m == 2); every kept
 * cluster goes to its place in `out`. F = cap. */
__kernel void ploc_merge(__global const float *c, const int cap, __global const int *nearest,
                         __global const int *counts, const int side, const int items,
                         const int min_per, __global const int *chunk_prefix,
                         __global float *nodes, __global int *parent, __global float *out) {
    int first, last;
    const int m = step_chunk(counts[side], items, min_per, &first, &last);
    if (first >= last) return;
    const int gid = get_global_id(0);
    int made = cap - m + chunk_prefix[2 * gid];
    int at = chunk_prefix[2 * gid + 1];
    for (int i = first; i < last; ++i) merge_one(c, cap, nearest, m, i, nodes, parent, out,
                                                 &made, &at);
}

/* The last steps in one work-item, in place: each step's nearest neighbours,
 * then its merges and compaction in increasing position (a cluster is written
 * at or before its own position, after every read of that position). Does
 * nothing while more than `limit` clusters are left: the host queues it after
 * each batch of steps. */
__kernel void ploc_tail(__global float *c, const int cap, __global int *counts, const int side,
                        const int limit, __global const float4 *root_box,
                        __global int *nearest, __global float *nodes, __global int *parent) {
    if (get_global_id(0) != 0) return;
    int m = counts[side];
    if (m > limit) return;
    const float scale = box_scale(root_box[0].xyz, root_box[1].xyz);
    while (m > 1) {
        nearest_range(c, cap, m, 0, m, scale, nearest);
        int made = cap - m, at = 0;
        for (int i = 0; i < m; ++i) merge_one(c, cap, nearest, m, i, nodes, parent, c, &made, &at);
        if (at == m) {
            counts[2] = 1;   /* nothing merged */
            break;
        }
        m = at;
    }
    counts[side] = m;
}
