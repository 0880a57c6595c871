/* Leaf collapse: turn subtrees into leaves where the SAH says testing their
 * triangles costs less than traversing them, then compact the tree.
 *
 * Cost model (the SAH of MacDonald & Booth 1990, as lbvh/quality.py): the
 * cost of node n per ray reaching it, C(n), is the cheaper of
 *   leaf:    C_TRI * count(n)                                  (allowed when
 *            count(n) <= max_leaf_size and the subtree's slots are contiguous)
 *   subtree: C_NODE + (A(l)/A(n)) * C(l) + (A(r)/A(n)) * C(r)
 * computed bottom-up; this is the optimal pruning of the tree under the SAH
 * (each subtree's choice is independent of the others'). A(.)/A(n) is taken
 * as 1 when A(n) = 0. Areas are computed with the three boxes scaled by the
 * power of two that brings the parent's coordinates below 1 (exact), so they
 * neither overflow nor underflow in float32 for any finite scene; the factor
 * 2 of the surface area cancels in the ratio.
 *
 * Kernels, in order:
 *   1. collapse_costs:   bottom-up walk with the second-arrival scheme of
 *                        refit.cl (Karras 2012, section 4): per node
 *                        (first slot, end slot, count, cost) and the decision.
 *   2. mark_kept:        a node stays when no proper ancestor became a leaf;
 *                        per chunk, the counts of kept nodes and output leaves.
 *   3. scan_chunks:      exclusive scan of the chunk counts (one work-item).
 *   4. assign_indices:   new index of each kept node and the leaf list, in the
 *                        old index order (a stable compaction: the root stays 0).
 *   5. emit_compacted:   the new node records and parent links.
 *
 * Floats: FP_CONTRACT OFF (common.h) and a fixed order of operations, so the
 * numpy twin (lbvh/collapse.py) reproduces every cost bit for bit on a device
 * with correctly rounded division.
 */
#include "common.h"

/* Per-node statistics of a subtree: slots [first, end), primitive count, cost. */
typedef struct { int first; int end; int count; float cost; } subtree_t;

inline void store_stats(__global int4 *stats, int node, subtree_t s) {
    stats[node] = (int4)(s.first, s.end, s.count, as_int(s.cost));
}

inline subtree_t load_stats_volatile(volatile __global int *stats_words, int node) {
    volatile __global int *p = stats_words + 4 * node;
    subtree_t s;
    s.first = p[0];
    s.end = p[1];
    s.count = p[2];
    s.cost = as_float(p[3]);
    return s;
}

inline void node_box(__global const float4 *nodes, int node, float3 *lo, float3 *hi) {
    *lo = nodes[2 * node].xyz;
    *hi = nodes[2 * node + 1].xyz;
}

/* Combine the two children of p (left first, whoever arrived second). */
inline subtree_t combine(__global const float4 *nodes, int p, int left, int right,
                         subtree_t sl, subtree_t sr, float c_node, float c_tri,
                         int max_leaf_size, int *collapse) {
    float3 plo, phi, llo, lhi, rlo, rhi;
    node_box(nodes, p, &plo, &phi);
    node_box(nodes, left, &llo, &lhi);
    node_box(nodes, right, &rlo, &rhi);
    const float s = box_scale(plo, phi);
    const float an = scaled_half_area(plo, phi, s);
    const float rl = an > 0.0f ? scaled_half_area(llo, lhi, s) / an : 1.0f;
    const float rr = an > 0.0f ? scaled_half_area(rlo, rhi, s) / an : 1.0f;
    subtree_t out;
    out.first = sl.first < sr.first ? sl.first : sr.first;   /* not min/max: out of line on PoCL 3 */
    out.end = sl.end > sr.end ? sl.end : sr.end;
    out.count = sl.count + sr.count;
    const float subtree_cost = c_node + (rl * sl.cost + rr * sr.cost);
    const float leaf_cost = c_tri * (float)out.count;
    *collapse = out.count <= max_leaf_size && out.end - out.first == out.count
                && leaf_cost <= subtree_cost;
    out.cost = *collapse ? leaf_cost : subtree_cost;
    return out;
}

/* 1. Leaves are nodes leaf_first + k (Karras numbering) or leaf_nodes[k]. */
__kernel void collapse_costs(__global const float4 *nodes, __global const int *parent,
                             __global int *arrivals, __global const int *leaf_nodes,
                             const int use_leaf_list, const int leaf_first, const int num_leaves,
                             const int per_item, const float c_node, const float c_tri,
                             const int max_leaf_size, __global int4 *stats,
                             __global int *becomes_leaf) {
    const int gid = get_global_id(0);
    const int first = chunk_first(gid, per_item, num_leaves);
    const int last = chunk_last(gid, per_item, num_leaves);
    __global const int *node_words = (__global const int *)nodes;
    volatile __global int *stats_words = (volatile __global int *)stats;
    for (int k = first; k < last; ++k) {
        int node = use_leaf_list ? leaf_nodes[k] : leaf_first + k;
        subtree_t own;
        own.first = node_words[8 * node + 3];
        own.count = -node_words[8 * node + 7];
        own.end = own.first + own.count;
        own.cost = c_tri * (float)own.count;
        store_stats(stats, node, own);
        becomes_leaf[node] = 1;
        for (;;) {
            const int p = parent[node];
            if (p < 0 || !second_arrival(arrivals, p)) break;
            const int left = node_words[8 * p + 3];
            const int right = node_words[8 * p + 7];
            const subtree_t other = load_stats_volatile(stats_words, left == node ? right : left);
            const subtree_t sl = left == node ? own : other;
            const subtree_t sr = left == node ? other : own;
            int collapse;
            own = combine(nodes, p, left, right, sl, sr, c_node, c_tri, max_leaf_size, &collapse);
            store_stats(stats, p, own);
            becomes_leaf[p] = collapse;
            node = p;
        }
    }
}

/* 2. flags[n] = (kept, output leaf); chunk_counts[gid] = their sums over the chunk.
 * A node is kept when no proper ancestor became a leaf. Only a node of at
 * most max_leaf_size triangles can become a leaf (combine), and counts grow
 * towards the root, so each node climbs only while the ancestors are that
 * small: at most max_leaf_size - 1 steps, where climbing to the root made
 * the pass O(nodes x depth). */
__kernel void mark_kept(__global const int *parent, __global const int *becomes_leaf,
                        __global const int4 *stats, const int max_leaf_size,
                        const int num_nodes, const int per_item, __global int2 *flags,
                        __global int2 *chunk_counts) {
    const int gid = get_global_id(0);
    const int first = chunk_first(gid, per_item, num_nodes);
    const int last = chunk_last(gid, per_item, num_nodes);
    int2 sum = (int2)(0, 0);
    for (int n = first; n < last; ++n) {
        int p = parent[n];
        while (p >= 0 && !becomes_leaf[p] && stats[p].z <= max_leaf_size) p = parent[p];
        const int kept = p < 0 || !becomes_leaf[p];
        const int2 f = (int2)(kept, kept && becomes_leaf[n]);
        flags[n] = f;
        sum += f;
    }
    chunk_counts[gid] = sum;
}

/* 3. Exclusive scan of the chunk counts; the grand totals go to chunk_counts[num_chunks]. */
__kernel void scan_chunks(__global int2 *chunk_counts, const int num_chunks) {
    if (get_global_id(0) != 0) return;
    int2 sum = (int2)(0, 0);
    for (int g = 0; g < num_chunks; ++g) {
        const int2 c = chunk_counts[g];
        chunk_counts[g] = sum;
        sum += c;
    }
    chunk_counts[num_chunks] = sum;
}

/* 4. new_index[n] for kept nodes (-1 otherwise) and leaf_list[j] = new index of the j-th output leaf. */
__kernel void assign_indices(__global const int2 *flags, __global const int2 *chunk_counts,
                             const int num_nodes, const int per_item, __global int *new_index,
                             __global int *leaf_list) {
    const int gid = get_global_id(0);
    const int first = chunk_first(gid, per_item, num_nodes);
    const int last = chunk_last(gid, per_item, num_nodes);
    int2 next = chunk_counts[gid];
    for (int n = first; n < last; ++n) {
        const int2 f = flags[n];
        new_index[n] = f.x ? next.x : -1;
        if (f.y) leaf_list[next.y] = next.x;
        next += f;
    }
}

/* 5. Records of the kept nodes at their new indices; output leaves get their slot range. */
__kernel void emit_compacted(__global const float4 *nodes, __global const int *parent,
                             __global const int2 *flags, __global const int4 *stats,
                             __global const int *new_index, const int num_nodes,
                             const int per_item, __global float4 *out_nodes,
                             __global int *out_parent) {
    const int gid = get_global_id(0);
    const int first = chunk_first(gid, per_item, num_nodes);
    const int last = chunk_last(gid, per_item, num_nodes);
    __global const int *node_words = (__global const int *)nodes;
    for (int n = first; n < last; ++n) {
        const int2 f = flags[n];
        if (!f.x) continue;
        const int i = new_index[n];
        int a, b;
        if (f.y) {
            const int4 s = stats[n];
            a = s.x;
            b = -s.z;
        } else {
            a = new_index[node_words[8 * n + 3]];
            b = new_index[node_words[8 * n + 7]];
        }
        float4 lo = nodes[2 * n], hi = nodes[2 * n + 1];
        lo.w = as_float(a);
        hi.w = as_float(b);
        out_nodes[2 * i] = lo;
        out_nodes[2 * i + 1] = hi;
        const int p = parent[n];
        out_parent[i] = p < 0 ? -1 : new_index[p];
    }
}
