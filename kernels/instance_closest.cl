/* Closest points through a two-level scene of placed meshes, in world space, for
 * any invertible affine placement (lbvh/queries/instance_closest.py,
 * lbvh.Scene.closest_points).
 *
 * It follows kernels/closest.cl (best-first branch and bound, Ericson 2005,
 * Real-Time Collision Detection, 6.1, and its point-triangle test of 5.1.5
 * with the safeguards, shared through kernels/closest_point.h) through the
 * scene of kernels/instances.cl (the same buffers: a top-level tree whose
 * slots name instances through top_order; every mesh's tree in one of up to
 * four node arrays, inst_root[i] its chunk and root: kernels/scene_chunks.h).
 *
 * Per point, in world space: a best-first walk of the top level by the squared
 * distance from the point to the instances' world boxes (the nearer child
 * first, the farther pushed with its distance, compared again when popped
 * with the best so far); at an instance, a walk of its mesh's tree in which
 * each local node box is bounded in world space by the larger of two lower
 * bounds of the distance to its image: the distance to the axis-aligned box
 * of the image (centre M c + t, half-extent |M| h) and sigma_min(M) times
 * the distance in the mesh's space from the point moved there (M^-1 (p - t);
 * no linear map shrinks a vector by more than its least singular value, and
 * for a similarity this is the exact distance to the rotated box, so
 * similarities prune as in the mesh's own space), and each leaf triangle's
 * vertices are moved to world space (M v + t) before the exact
 * point-triangle distance. So distances are world distances for any affine
 * map (shears, non-uniform scales, reflections), and the barycentrics of the
 * world triangle's closest point are those of the local triangle (an affine
 * map keeps them). The best distance found in any instance bounds the walk
 * of every other.
 *
 * The placements: PLACEMENT_FLOATS = 49 floats per instance
 * (lbvh/queries/instances.py, SceneBuffers.placements): the 12 entries of
 * (M row by row, then t) rounded to float32 (hi) and the 12 float32
 * roundings of what hi left (lo); the same 24 of the inverse (M^-1 row by
 * row, then -M^-1 t); sigma_min(M)^2 rounded down. With doubles
 * (closest_point.h's `real`) the kernel uses hi + lo, the float64 transform
 * to about 2^-48 of each entry, so the world vertices are the float64
 * transform's of the float32 mesh vertices up to double rounding (without
 * doubles: hi, in float32). A bound rounded above the true distance by that
 * rounding can only cost a triangle nearer by less than the rounding.
 *
 * Results: distance, the closest point (3 floats), the triangle (prim_order's
 * numbering: within its mesh, or its face_ids number), the instance (its
 * index in the scene), barycentrics u, v on the triangle (q = (1-u-v) p0 +
 * u p1 + v p2 in its own vertex order); inf, NaN, -1, -1, 0, 0 where nothing
 * is within max_distance; flags.
 *
 * Defines:
 *   STACK_SIZE=n  entries of each level's stack; a push beyond n sets
 *                 FLAG_OVERFLOW and skips that subtree (the host raises it).
 *   POINT_ORDER=1 work-item k answers point order[k] (a permutation), which
 *                 `points` holds at k (ray_order.cl, gather_points: read as one
 *                 run, as closest.cl reads them); the answers stay in the
 *                 points' own slots.
 *   NO_FP64=1     float32 arithmetic even where the device has doubles (tests).
 */
#include "common.h"

#ifndef STACK_SIZE
#define STACK_SIZE 64
#endif

#define FLAG_OVERFLOW 1    /* a push found the stack full: a subtree was skipped */
#define FLAG_VISIT_LIMIT 2 /* more nodes visited than the tree has: not a tree */

#include "closest_point.h"
#include "scene_chunks.h"

/* An instance's placement, read from PLACEMENT_FLOATS floats (the layout of the
 * header): m = (M row by row, t) object to world, a = |M|, inv = (M^-1 row by row,
 * -M^-1 t) world to object, s2 = sigma_min(M)^2 rounded down. 35 reals: only ever
 * passed by pointer. */
#define PLACEMENT_FLOATS 49
typedef struct {
    real m[12];
    real a[9];
    real inv[12];
    real s2;
} Placement;

/* Entry k of the 12 of a (hi, lo) pair of float32 rows: hi + lo with doubles. */
inline real pair_entry(__global const float *f, int k) {
#if defined(cl_khr_fp64) && !defined(NO_FP64)
    return (real)f[k] + (real)f[12 + k];
#else
    return f[k];
#endif
}

inline void load_placement(__global const float *placements, int inst, Placement *x) {
    __global const float *f = placements + PLACEMENT_FLOATS * inst;
    for (int k = 0; k < 12; ++k) {
        x->m[k] = pair_entry(f, k);
        x->inv[k] = pair_entry(f + 24, k);
    }
    for (int k = 0; k < 9; ++k) x->a[k] = fabs(x->m[k]);
    x->s2 = f[48];
}

/* m v + t of the 12 entries m (M row by row, t) */
inline real3 affine(const real *m, real3 v) {
    return (real3)(m[0] * v.x + m[1] * v.y + m[2] * v.z + m[9],
                   m[3] * v.x + m[4] * v.y + m[5] * v.z + m[10],
                   m[6] * v.x + m[7] * v.y + m[8] * v.z + m[11]);
}

/* M v + t */
inline real3 to_world(const Placement *x, real3 v) { return affine(x->m, v); }

/* A lower bound of the squared world distance from the world point p (local_p: moved
 * into the mesh's space) to the image of local node `node`'s box: the larger of two,
 * the squared distance to the axis-aligned box of the image (centre M c + t,
 * half-extent |M| h) and sigma_min(M)^2 times the squared distance in the mesh's
 * space (no map shrinks a vector by more than its least singular value; for a
 * similarity this is the exact distance to the image of the box). */
inline real world_box_distance2(const Placement *x, real3 p, real3 local_p,
                                __global const float4 *nodes, int node) {
    const real one_half = (real)0.5f;   /* exact: no double constant without fp64 */
    const float3 flo = nodes[2 * node].xyz, fhi = nodes[2 * node + 1].xyz;
    const real3 lo = to_real3(flo), hi = to_real3(fhi);
    const real3 c = lo * one_half + hi * one_half, h = hi * one_half - lo * one_half;
    const real3 wc = to_world(x, c);
    const real *a = x->a;
    const real3 wh = (real3)(a[0] * h.x + a[1] * h.y + a[2] * h.z,
                             a[3] * h.x + a[4] * h.y + a[5] * h.z,
                             a[6] * h.x + a[7] * h.y + a[8] * h.z);
    const real world = real_box_distance2(p, wc - wh, wc + wh);
    const real in_mesh = x->s2 * box_distance2(local_p, flo, fhi);
    return world > in_mesh ? world : in_mesh;
}

/* The world vertices of slot s's triangle. */
inline void world_triangle(const Placement *x, __global const float *vertices,
                           __global const uint *slot_faces, int s, real3 *p0, real3 *p1,
                           real3 *p2) {
    *p0 = to_world(x, to_real3(load_float3(vertices, slot_faces[3 * s])));
    *p1 = to_world(x, to_real3(load_float3(vertices, slot_faces[3 * s + 1])));
    *p2 = to_world(x, to_real3(load_float3(vertices, slot_faces[3 * s + 2])));
}

/* The running answer of one point: shared by every instance's walk. */
typedef struct {
    real best2, v, w;
    int slot, inst, flag;
} Best;

/* The best-first walk of instance `inst`'s mesh tree (root `root`) for the world
 * point p, improving *best. */
inline void walk_instance(__global const float4 *nodes, __global const float *vertices,
                          __global const uint *slot_faces, int root, int num_nodes,
                          const Placement *x, int inst, real3 p, Best *best) {
    int stack_node[STACK_SIZE];
    real stack_d2[STACK_SIZE];
    int top = 0, node = root, visits = 0;
    const real3 local_p = affine(x->inv, p);
    real node_d2 = world_box_distance2(x, p, local_p, nodes, root);
    for (;;) {
        if (node >= 0 && node_d2 <= best->best2) {
            if (visits++ >= num_nodes) {
                best->flag |= FLAG_VISIT_LIMIT;
                return;
            }
            const int a = as_int(nodes[2 * node].w), b = as_int(nodes[2 * node + 1].w);
            if (node_is_leaf(b)) {
                for (int s = a; s < a - b; ++s) {
                    real3 p0, p1, p2;
                    world_triangle(x, vertices, slot_faces, s, &p0, &p1, &p2);
                    real v, w;
                    const real d2 = closest_sorted(p, p0, p1, p2, &v, &w);
                    if (d2 < best->best2 || (best->slot < 0 && d2 <= best->best2)) {
                        best->best2 = d2; best->slot = s; best->inst = inst;
                        best->v = v; best->w = w;
                    }
                }
                node = -1;
            } else {
                nearer_child(a, b, world_box_distance2(x, p, local_p, nodes, a),
                             world_box_distance2(x, p, local_p, nodes, b), best->best2, stack_node,
                             stack_d2, &top, &best->flag, &node, &node_d2);
            }
            continue;
        }
        if (top == 0) return;
        --top;
        node = stack_node[top];
        node_d2 = stack_d2[top];
    }
}

__kernel void instance_closest(__global const float4 *top_nodes, __global const int *top_order,
                               const int top_root, const int top_num_nodes,
                               __global const float *placements, __global const int *inst_root,
                               __global const float4 *nodes, __global const float4 *nodes1,
                               __global const float4 *nodes2, __global const float4 *nodes3,
                               const int num_nodes,
                               __global const int *prim_order, __global const float *vertices,
                               __global const uint *slot_faces,
                               __global const float *points, __global const int *order,
                               const float max_distance, const int count,
                               __global float *distance, __global float *closest,
                               __global int *prim, __global int *instance, __global float *bary,
                               __global int *flags) {
    const int k = get_global_id(0);
    if (k >= count) return;
    const int i = point_index(order, k);
    const real3 p = to_real3(load_float3(points, k));
    Best best;
    best.best2 = (real)max_distance * (real)max_distance;
    best.v = 0; best.w = 0;
    best.slot = -1; best.inst = -1; best.flag = 0;

    int stack_node[STACK_SIZE];
    real stack_d2[STACK_SIZE];
    int top = 0, node = top_root, visits = 0;
    real node_d2 = box_distance2(p, top_nodes[2 * top_root].xyz, top_nodes[2 * top_root + 1].xyz);
    for (;;) {
        if (node >= 0 && node_d2 <= best.best2) {
            if (visits++ >= top_num_nodes) {
                best.flag |= FLAG_VISIT_LIMIT;
                break;
            }
            const int a = as_int(top_nodes[2 * node].w), b = as_int(top_nodes[2 * node + 1].w);
            if (node_is_leaf(b)) {
                for (int s = a; s < a - b; ++s) {
                    const int inst = top_order[s];
                    Placement x;
                    load_placement(placements, inst, &x);
                    const int r = inst_root[inst];
                    walk_instance(chunk_nodes(r, nodes, nodes1, nodes2, nodes3), vertices,
                                  slot_faces, chunk_root(r), num_nodes, &x, inst, p, &best);
                }
                node = -1;
            } else {
                nearer_child(a, b,
                             box_distance2(p, top_nodes[2 * a].xyz, top_nodes[2 * a + 1].xyz),
                             box_distance2(p, top_nodes[2 * b].xyz, top_nodes[2 * b + 1].xyz),
                             best.best2, stack_node, stack_d2, &top, &best.flag, &node, &node_d2);
            }
            continue;
        }
        if (top == 0) break;
        --top;
        node = stack_node[top];
        node_d2 = stack_d2[top];
    }

    if (best.slot >= 0) {
        Placement x;
        load_placement(placements, best.inst, &x);
        real3 p0, p1, p2;
        world_triangle(&x, vertices, slot_faces, best.slot, &p0, &p1, &p2);
        real u1, u2;
        const real3 q = point_of_sorted(p0, p1, p2, best.v, best.w, &u1, &u2);
        distance[i] = (float)sqrt(best.best2);
        closest[3 * i] = (float)q.x;
        closest[3 * i + 1] = (float)q.y;
        closest[3 * i + 2] = (float)q.z;
        prim[i] = prim_order[best.slot];
        instance[i] = best.inst;
        bary[2 * i] = (float)u1;
        bary[2 * i + 1] = (float)u2;
    } else {
        distance[i] = INFINITY;
        store_float3(closest + 3 * i, (float3)(NAN, NAN, NAN));
        prim[i] = -1;
        instance[i] = -1;
        bary[2 * i] = 0.0f;
        bary[2 * i + 1] = 0.0f;
    }
    flags[i] = best.flag;
}
