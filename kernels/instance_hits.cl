/* Every hit along each ray through a two-level scene, and the hit counts
 * (lbvh/queries/instance_hits.py, lbvh.Scene.count_hits and all_hits).
 *
 * It follows kernels/all_hits.cl through the scene of kernels/instances.cl
 * (the same buffers: a top-level tree whose slots name instances through
 * top_order; every mesh's tree in one node array, inst_root[i] the root of
 * instance i's mesh; the inverse transforms): a depth-first walk of every
 * top-level node whose box the world ray's [tmin, tmax] enters; at each
 * instance, the ray moved into its mesh's space (kernels/instance_ray.h,
 * t kept) and every hit in [tmin, tmax] of the mesh's tree counted or kept
 * by the walk of kernels/every_hit.h (watertight, with the edge rule: a
 * crossing through a shared edge or vertex of a mesh counts once).
 *
 * Two passes, as all_hits.cl's: COUNT=1 writes how many hits each ray has;
 * COUNT=0 writes that count too, and the hits into [offsets[i], offsets[i + 1]):
 * t (along the world direction as given), u, v, the triangle (prim_order's
 * numbering: within its mesh, or the mesh's face_ids) and the instance; past
 * the slots (SLOTS_ONLY=0) a hit replaces
 * the farthest kept one when it is nearer (by t, instance, triangle); then the
 * ray's kept hits are sorted in that order (sort_kept, every_hit.h).
 *
 * Defines:
 *   STACK_SIZE=n  entries of each level's stack; a push beyond n sets
 *                 FLAG_OVERFLOW and skips that subtree (the host raises or
 *                 reports it, never drops it silently).
 *   COUNT=0|1     the pass.
 *   SLOTS_ONLY=1  as all_hits.cl's.
 *   SLAB_PAD, NO_FP64: kernels/ray_triangle.h.
 * (`work` is all_hits.cl's counters argument, kept so that one host loop
 * drives both kernels; never written here.)
 */
#include "common.h"

#define HIT_INSTANCE 1
#include "every_hit.h"
#include "instance_ray.h"

__kernel void instance_hits(__global const float4 *top_nodes, __global const int *top_order,
                            const int top_root, const int top_num_nodes,
                            __global const float *inverse, __global const int *inst_root,
                            __global const float4 *nodes, __global const float4 *nodes1,
                            __global const float4 *nodes2, __global const float4 *nodes3,
                            const int num_nodes,
                            __global const int *prim_order, __global const float *vertices,
                            __global const uint *slot_faces,
                            __global const float *origins, __global const float *directions,
                            __global const float *tmins, __global const float *tmaxs,
                            const int interval_stride, const int count,
                            __global const long *offsets, __global int *counts,
                            __global float *out_t, __global float *out_u, __global float *out_v,
                            __global int *out_prim, __global int *out_inst, __global int *flags,
                            __global int4 *work) {
    const int i = get_global_id(0);
    if (i >= count) return;
    const float tmin = tmins[i * interval_stride], tmax = tmaxs[i * interval_stride];
    float w[6];
    const int nan_ray = world_ray(origins, directions, i, tmin, tmax, w);
    long first;
    const int cap = kept_slots(offsets, i, &first);
    int found = 0, flag = nan_ray ? FLAG_NAN_RAY : 0, visits = 0, leaves = 0, tested = 0;
    Ray ray;   /* the world ray, for the top level's boxes */
    make_ray(&ray, origins + 3 * i, directions + 3 * i, tmin, tmax);
    float entry, leave;
    int node = !nan_ray && slab((__global const float *)(top_nodes + 2 * top_root), &ray,
                                ray.tmax, &entry, &leave) ? top_root : -1;
    int stack[STACK_SIZE];
    int top = 0, steps = 0;
    for (;;) {
        if (node >= 0) {
            if (++steps > top_num_nodes) {
                flag |= FLAG_VISIT_LIMIT;
                break;
            }
            const int a = as_int(top_nodes[2 * node].w), b = as_int(top_nodes[2 * node + 1].w);
            if (node_is_leaf(b)) {
                for (int s = a; s < a - b; ++s) {
                    const int inst = top_order[s];
                    Ray moved;
                    if (move_ray(inverse + 12 * inst, w, tmin, tmax, &moved))
                        tree_hits(chunk_nodes(inst_root[inst], nodes, nodes1, nodes2, nodes3),
                                  prim_order, vertices, slot_faces, chunk_root(inst_root[inst]),
                                  num_nodes, &moved, inst, first, cap, out_t, out_u, out_v,
                                  out_prim, out_inst, &found, &flag, &visits, &leaves, &tested);
                }
                node = -1;
            } else {
                node = enter_children(top_nodes, a, b, &ray, stack, &top, &flag);
            }
            continue;
        }
        if (top == 0) break;
        node = stack[--top];
    }
    /* every hit counted in both passes: the collecting pass's count tells the host
     * whether the ray's slots held all it keeps (lbvh/queries/all_hits.py) */
    counts[i] = found;
#if !COUNT
    if (!SLOTS_ONLY || found <= cap)   /* else traced again */
        sort_kept(first, min(found, cap), out_t, out_u, out_v, out_prim, out_inst);
#endif
    flags[i] = flag;
}
