/* Treelet restructuring: Karras & Aila 2013, "Fast Parallel Construction of
 * High-Quality Bounding Volume Hierarchies" (HPG), sections 3 and 4.
 *
 * One round is a bottom-up walk with the second-arrival scheme of refit.cl
 * (Karras 2012, section 4). When a walk is the second to reach node R, every
 * node below R is final, so R's treelet can be rebuilt:
 *   - formation (section 4.1): start from R's two children as treelet leaves
 *     and, while there are fewer than TREELET_LEAVES, expand the treelet leaf
 *     of largest surface area that is an internal node of the BVH (it is
 *     replaced by its left child in place, its right child is appended);
 *   - optimal topology (section 4.2, Algorithm 2): dynamic programming over
 *     the subsets S of the treelet leaves, in increasing order of the bit mask
 *     (every proper subset of S comes before S):
 *         C(S) = C_NODE * A(S) + min over partitions {P, S\P} of C(P) + C(S\P)
 *     a singleton's C being the SAH cost already known for that subtree;
 *   - the treelet's internal nodes (R first, then the expanded nodes in
 *     expansion order) are reused for the optimal topology, depth first.
 * Leaves are never touched: slots, prim_order and the leaf block stay.
 *
 * Costs are the unnormalised SAH, C(n) = C_NODE * A(n) + C(l) + C(r) and
 * C(leaf) = C_TRI * count * A(leaf), with A the half area of the box scaled by
 * box_scale() of the root's box, so that no area overflows or underflows in
 * float32 for any finite scene. A treelet that cannot grow past two leaves
 * has one topology; the same code then only computes its cost.
 *
 * Determinism: R's result depends only on R's subtree, and ties go to the
 * first candidate in a fixed order (largest area: lowest position; partition:
 * first in the enumeration below), so the tree does not depend on which walk
 * arrives second; lbvh/restructure.py has the serial twin, which matches bit
 * for bit (FP_CONTRACT OFF, same order of operations).
 *
 * Memory ordering as refit.cl: second_arrival() fences, and every read of a
 * node or cost written by another walk goes through a volatile pointer.
 *
 * TREELET_LEAVES (define): at most 7 here; Karras & Aila use 7.
 */
#include "common.h"

#define SUBSETS (1 << TREELET_LEAVES)

typedef volatile __global float vfloat_t;
typedef volatile __global int vint_t;

inline void read_box(vfloat_t *node_floats, int node, float3 *lo, float3 *hi) {
    vfloat_t *p = node_floats + 8 * node;
    *lo = (float3)(p[0], p[1], p[2]);
    *hi = (float3)(p[4], p[5], p[6]);
}

inline int child_word(vint_t *node_words, int node, int which) {
    return node_words[8 * node + (which ? 7 : 3)];
}

inline void write_node(__global float *node_floats, int node, float3 lo, float3 hi, int a, int b) {
    __global float *p = node_floats + 8 * node;
    store_float3(p, lo);
    store_float3(p + 4, hi);
    ((__global int *)p)[3] = a;
    ((__global int *)p)[7] = b;
}

/* Index of the single set bit of a power of two (OpenCL 1.2 has no ctz). */
inline int bit_index(int single_bit) { return 31 - (int)clz((uint)single_bit); }

/* A treelet: its leaves (BVH nodes whose subtrees stay as they are) and its
 * internal nodes (the root first, then the expanded nodes in order). */
typedef struct {
    int leaf[TREELET_LEAVES];
    int inner[TREELET_LEAVES - 1];
    int num_leaves;
} treelet_t;

/* Put x's children in treelet slots a (left) and b (right), with their areas. */
inline void place_children(treelet_t *t, float *area, int x, int a, int b, vint_t *node_words,
                           vfloat_t *vnode_floats, float scale) {
    const int at[2] = {a, b};
    for (int c = 0; c < 2; ++c) {
        float3 lo, hi;
        t->leaf[at[c]] = child_word(node_words, x, c);
        read_box(vnode_floats, t->leaf[at[c]], &lo, &hi);
        area[at[c]] = scaled_half_area(lo, hi, scale);
    }
}

/* Section 4.1: from the root's two children, expand the treelet leaf of
 * largest area that is an internal node of the BVH (left child in its place,
 * right child appended; ties: the first), up to TREELET_LEAVES leaves. */
inline void form_treelet(int root, vint_t *node_words, vfloat_t *vnode_floats, float scale,
                         treelet_t *t) {
    float area[TREELET_LEAVES];
    int num_inner = 1;
    t->inner[0] = root;
    place_children(t, area, root, 0, 1, node_words, vnode_floats, scale);
    t->num_leaves = 2;
    while (t->num_leaves < TREELET_LEAVES) {
        int grow = -1;
        for (int i = 0; i < t->num_leaves; ++i) {
            const int internal = !node_is_leaf(child_word(node_words, t->leaf[i], 1));
            if (internal && (grow < 0 || area[i] > area[grow])) grow = i;
        }
        if (grow < 0) break;
        const int x = t->leaf[grow];
        t->inner[num_inner++] = x;
        place_children(t, area, x, grow, t->num_leaves, node_words, vnode_floats, scale);
        ++t->num_leaves;
    }
}

/* Section 4.2 (Algorithm 2): box, cost and best split of every subset S of
 * the leaves, in increasing order of the bit mask (every proper subset of S
 * comes before S). Partitions {S\P, P}, P a non-empty subset of S without its
 * lowest leaf, in ascending order: each unordered partition once; the first
 * of equal costs wins. */
inline void optimal_topology(const treelet_t *t, vfloat_t *vnode_floats, vfloat_t *vcost,
                             float scale, float c_node, float3 *sub_lo, float3 *sub_hi,
                             float *sub_cost, int *sub_split) {
    const int full = (1 << t->num_leaves) - 1;
    for (int s = 1; s <= full; ++s) {
        const int low = s & -s;
        const int rest = s ^ low;
        if (rest == 0) {
            const int node = t->leaf[bit_index(low)];
            read_box(vnode_floats, node, &sub_lo[s], &sub_hi[s]);
            sub_cost[s] = vcost[node];
            continue;
        }
        sub_lo[s] = min3(sub_lo[rest], sub_lo[low]);
        sub_hi[s] = max3(sub_hi[rest], sub_hi[low]);
        int best_p = rest, p = 0;
        float best = INFINITY;
        do {
            p = (p - rest) & rest;
            const float c = sub_cost[s ^ p] + sub_cost[p];
            if (c < best) {
                best = c;
                best_p = p;
            }
        } while (p != rest);
        sub_split[s] = best_p;
        sub_cost[s] = c_node * scaled_half_area(sub_lo[s], sub_hi[s], scale) + best;
    }
}

/* Rewire the treelet's internal nodes into the optimal topology, depth first
 * from the root (children: S\P left, P right), with their boxes and costs. */
inline void rebuild_treelet(const treelet_t *t, const float3 *sub_lo, const float3 *sub_hi,
                            const float *sub_cost, const int *sub_split,
                            __global float *node_floats, __global int *parent,
                            __global float *cost) {
    int stack_set[TREELET_LEAVES], stack_node[TREELET_LEAVES];
    int top = 0, next_inner = 1;
    stack_set[0] = (1 << t->num_leaves) - 1;
    stack_node[0] = t->inner[0];
    while (top >= 0) {
        const int s = stack_set[top], node = stack_node[top];
        --top;
        const int part[2] = {s ^ sub_split[s], sub_split[s]};
        int kid[2];
        for (int c = 0; c < 2; ++c) {
            if (popcount(part[c]) == 1) {
                kid[c] = t->leaf[bit_index(part[c])];
            } else {
                kid[c] = t->inner[next_inner++];
                ++top;
                stack_set[top] = part[c];
                stack_node[top] = kid[c];
            }
            parent[kid[c]] = node;
        }
        write_node(node_floats, node, sub_lo[s], sub_hi[s], kid[0], kid[1]);
        cost[node] = sub_cost[s];
    }
}

/* Rebuild the treelet rooted at internal node `root` (its cost included). */
inline void restructure_at(int root, __global float *node_floats, vfloat_t *vnode_floats,
                           vint_t *node_words, __global int *parent, __global float *cost,
                           vfloat_t *vcost, float scale, float c_node) {
    treelet_t t;
    form_treelet(root, node_words, vnode_floats, scale, &t);
    float3 sub_lo[SUBSETS], sub_hi[SUBSETS];
    float sub_cost[SUBSETS];
    int sub_split[SUBSETS];
    optimal_topology(&t, vnode_floats, vcost, scale, c_node, sub_lo, sub_hi, sub_cost, sub_split);
    rebuild_treelet(&t, sub_lo, sub_hi, sub_cost, sub_split, node_floats, parent, cost);
}

/* Only the cost of node x, whose children's costs are final: what
 * optimal_topology gives for a treelet of x's two children (the children's
 * union is x's box, as the refit and every rebuild leave it), same operations. */
inline void cost_only(int x, vfloat_t *vnode_floats, vint_t *node_words, vfloat_t *vcost,
                      float scale, float c_node) {
    float3 lo, hi;
    read_box(vnode_floats, x, &lo, &hi);
    const float below = vcost[child_word(node_words, x, 0)] + vcost[child_word(node_words, x, 1)];
    vcost[x] = c_node * scaled_half_area(lo, hi, scale) + below;
}

/* Leaves are nodes leaf_first + k (Karras numbering) or leaf_nodes[k].
 * `sizes` (scratch, an int per node) gets the number of BVH leaves below each
 * node on the way up; a node with fewer than `min_leaves` is not a treelet
 * root this round, only its cost is updated (the treelets of small subtrees
 * change little once a first round has rebuilt them: measured in
 * lbvh/builders/restructure.py round_min_leaves' commit and docs/pages/builders.md). */
__kernel void restructure_treelets(__global float4 *nodes, __global int *parent,
                                   __global float *cost, __global int *arrivals,
                                   __global int *sizes, __global const int *leaf_nodes,
                                   const int use_leaf_list, const int leaf_first,
                                   const int num_leaves, const int per_item, const int root,
                                   const float c_node, const float c_tri, const int min_leaves) {
    const int gid = get_global_id(0);
    const int first = chunk_first(gid, per_item, num_leaves);
    const int last = chunk_last(gid, per_item, num_leaves);
    __global float *node_floats = (__global float *)nodes;
    vfloat_t *vnode_floats = (vfloat_t *)nodes;
    vint_t *node_words = (vint_t *)nodes;
    const float scale = box_scale(nodes[2 * root].xyz, nodes[2 * root + 1].xyz);
    for (int k = first; k < last; ++k) {
        const int leaf = use_leaf_list ? leaf_nodes[k] : leaf_first + k;
        float3 lo, hi;
        read_box(vnode_floats, leaf, &lo, &hi);
        const float count = (float)(-child_word(node_words, leaf, 1));
        cost[leaf] = c_tri * count * scaled_half_area(lo, hi, scale);
        sizes[leaf] = 1;
    }
    vint_t *vsizes = (vint_t *)sizes;
    for (int k = first; k < last; ++k) {
        int node = use_leaf_list ? leaf_nodes[k] : leaf_first + k;
        for (;;) {
            const int p = parent[node];
            if (p < 0 || !second_arrival(arrivals, p)) break;
            const int size = vsizes[child_word(node_words, p, 0)] +
                             vsizes[child_word(node_words, p, 1)];
            vsizes[p] = size;
            if (size >= min_leaves) {
                restructure_at(p, node_floats, vnode_floats, node_words, parent, cost,
                               (vfloat_t *)cost, scale, c_node);
            } else {
                cost_only(p, vnode_floats, node_words, (vfloat_t *)cost, scale, c_node);
            }
            node = p;
        }
    }
}
