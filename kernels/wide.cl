/* Wide records for the traversal, driven by lbvh/wide.py: any binary tree of
 * the layout (docs/pages/layout.md) collapsed into nodes of up to WIDTH children,
 * each record holding its children's boxes in SIMD-friendly rows, so that one
 * vector slab test covers all children of a node (Wald, Benthin, Boulos 2008,
 * "Getting Rid of Packets: Efficient SIMD Single-Ray Traversal using
 * Multi-branching BVHs"; Dammertz, Hanika, Keller 2008, "Shallow Bounding
 * Volume Hierarchies for Fast SIMD Ray Tracing of Incoherent Rays").
 *
 * A record starts from a binary internal node with its two children as lanes
 * and opens, while it has fewer than WIDTH lanes, the internal lane of largest
 * surface area into its two children, in place (the children keep the tree's
 * left-to-right order). Opening the largest box first is the greedy SAH
 * choice: it is the child most rays enter. Every internal lane that remains
 * becomes a record of its own.
 *
 * Two kernels:
 *   wide_level    one level of records: opens the nodes of records
 *                 [begin, end) and appends their internal lanes as new
 *                 records (an atomic counter hands out the indices), so the
 *                 host calls it once per level until no record is added;
 *   wide_records  writes every record's rows from its lanes, in one launch
 *                 (again after a refit: the lanes do not change).
 *
 * Record q, WIDTH lanes per row, 8 rows of WIDTH 32-bit words:
 *   rows 0-5  lower.x, upper.x, lower.y, upper.y, lower.z, upper.z
 *   rows 6-7  the lane's reference (x, y): a leaf child keeps its node words
 *             (x = first slot, y = -count < 0); an internal child is
 *             x = its record's index, y = 0.
 * An empty lane (a record with fewer than WIDTH children) has lower = +inf,
 * upper = -inf: every slab test of it fails, for any ray without NaN, so its
 * reference (0, 0) is never followed.
 */
#include "common.h"

#ifndef WIDTH
#define WIDTH 8
#endif

/* Surface area up to the factor 2, in float32 with no contraction, of the box
 * with its coordinates times `scale` (common.h scaled_half_area; the host's
 * box_scale of the root's box, a power of two): no area underflows or
 * overflows, and a scene at any power-of-two scale opens the same lanes (a
 * tiny scene's areas, underflowing to ties, opened others). The numpy twin
 * computes the same bits, so both open the same lanes. */
inline float half_area(__global const float *node, float scale) {
    return scaled_half_area((float3)(node[0], node[1], node[2]),
                            (float3)(node[4], node[5], node[6]), scale);
}

/* counters[0]: records so far; counters[1]: the deepest stack the traversal
 * can need (the most entries that the records along one root-to-record path
 * push, WIDTH children minus the one followed per record); counters[2]: the
 * least binary node with a child index outside [0, num_nodes), or with more
 * records than `capacity` (not a tree: a cycle or a shared child). */
__kernel void wide_level(__global const float *nodes, const int num_nodes,
                         const int begin, const int end, const int capacity, const int per_item,
                         const float scale,
                         __global int *record_node, __global int *record_need,
                         __global int *record_base, __global int *lanes,
                         __global int *counters) {
    __global const int *words = (__global const int *)nodes;
    const int gid = get_global_id(0);
    const int count = end - begin;
    const int last = begin + chunk_last(gid, per_item, count);
    for (int q = begin + chunk_first(gid, per_item, count); q < last; ++q) {
        const int n = record_node[q];
        int lane[WIDTH];
        int used = 0, bad = 0;
        lane[used++] = words[8 * n + 3];
        lane[used++] = words[8 * n + 7];
        bad = (uint)lane[0] >= (uint)num_nodes || (uint)lane[1] >= (uint)num_nodes;
        int opened = n;
        while (!bad && used < WIDTH) {
            int pick = -1;
            float pick_area = -1.0f;
            for (int c = 0; c < used; ++c) {
                const int m = lane[c];
                if (node_is_leaf(words[8 * m + 7])) continue;
                const float area = half_area(nodes + 8 * m, scale);
                if (area > pick_area) { pick = c; pick_area = area; }
            }
            if (pick < 0) break;
            opened = lane[pick];
            const int left = words[8 * opened + 3], right = words[8 * opened + 7];
            if ((uint)left >= (uint)num_nodes || (uint)right >= (uint)num_nodes) { bad = 1; break; }
            for (int c = used; c > pick + 1; --c) lane[c] = lane[c - 1];
            lane[pick] = left;
            lane[pick + 1] = right;
            ++used;
        }
        if (bad) {
            atomic_min(&counters[2], opened);
            used = 0;
        }
        int internal = 0;
        for (int c = 0; c < used; ++c) internal += !node_is_leaf(words[8 * lane[c] + 7]);
        const int base = internal ? atomic_add(&counters[0], internal) : 0;
        if (base + internal > capacity) {
            atomic_min(&counters[2], n);
            used = internal = 0;
        }
        const int need = record_need[q] + (used > 0 ? used - 1 : 0);
        atomic_max(&counters[1], need);
        record_base[q] = base;
        for (int c = 0, j = 0; c < WIDTH; ++c) {
            const int m = c < used ? lane[c] : -1;
            lanes[WIDTH * q + c] = m;
            if (m >= 0 && !node_is_leaf(words[8 * m + 7])) {
                record_node[base + j] = m;
                record_need[base + j] = need;
                ++j;
            }
        }
    }
}

__kernel void wide_records(__global const float *nodes, const int num_records, const int per_item,
                           __global const int *record_base, __global const int *lanes,
                           __global float *records) {
    __global const int *words = (__global const int *)nodes;
    __global int *record_words = (__global int *)records;
    const int gid = get_global_id(0);
    const int last = chunk_last(gid, per_item, num_records);
    for (int q = chunk_first(gid, per_item, num_records); q < last; ++q) {
        __global float *r = records + 8 * WIDTH * q;
        __global int *rw = record_words + 8 * WIDTH * q;
        int next = record_base[q];
        for (int c = 0; c < WIDTH; ++c) {
            const int m = lanes[WIDTH * q + c];
            if (m < 0) {
                r[c] = INFINITY; r[WIDTH + c] = -INFINITY;
                r[2 * WIDTH + c] = INFINITY; r[3 * WIDTH + c] = -INFINITY;
                r[4 * WIDTH + c] = INFINITY; r[5 * WIDTH + c] = -INFINITY;
                rw[6 * WIDTH + c] = 0; rw[7 * WIDTH + c] = 0;
                continue;
            }
            __global const float *box = nodes + 8 * m;
            r[c] = box[0]; r[WIDTH + c] = box[4];
            r[2 * WIDTH + c] = box[1]; r[3 * WIDTH + c] = box[5];
            r[4 * WIDTH + c] = box[2]; r[5 * WIDTH + c] = box[6];
            const int y = words[8 * m + 7];
            const int leaf = node_is_leaf(y);
            rw[6 * WIDTH + c] = leaf ? words[8 * m + 3] : next++;
            rw[7 * WIDTH + c] = leaf ? y : 0;
        }
    }
}
