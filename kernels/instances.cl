/* Rays through a two-level scene: a top-level tree over instances, each a
 * mesh's tree placed by a transform (lbvh/queries/instances.py, lbvh.Scene).
 *
 * The top level is an LBVH over the instances' world boxes (docs/pages/layout.md;
 * its slots name instances through top_order). The meshes' trees sit one
 * after the other in up to four node arrays (nodes, nodes1..3: chunks of the
 * device's largest allocation, kernels/instance_ray.h), one prim_order and
 * one slot_faces (the faces in slot order, vertex indices into one vertex
 * array), their child indices offset within their chunk and slot indices
 * offset by the host; inst_root[i] names the chunk and the root node of
 * instance i's mesh (chunk_nodes, chunk_root).
 *
 * Per ray: an ordered traversal of the top level with the world ray (the
 * nearer child first, the other pushed with its entry distance, popped only
 * before the closest hit so far); at an instance, the ray moved into the
 * mesh's space, o' = M o + c and d' = M d with (M, c) the inverse of the
 * instance's transform (12 floats, M row by row, then c), which keeps the
 * ray parameter t: a point o' + t d' is the world point o + t d moved. The
 * mesh's tree is then traversed as kernels/traverse.cl does through binary
 * nodes (WIDE=0), with the same ray and triangle tests (ray_triangle.h),
 * limited to t below the closest hit found in any instance.
 *
 * Results: five planes of `count` floats: t, u, v, as_float(prim) (the
 * triangle within its mesh), as_float(instance) (its index in the scene), -1
 * and t = inf for a miss.
 *
 * Defines:
 *   ANY_HIT=1        stop at the first hit (occlusion)
 *   COUNTERS=1       write per ray the nodes visited (both levels) and the
 *                    triangles tested
 *   STACK_SIZE=n     entries of each level's stack; a push beyond n sets
 *                    FLAG_OVERFLOW and drops that subtree
 *   EXACT_LEAVES=0   some mesh has spatial splits (see kernels/traverse.cl)
 *   TRIANGLE_TEST, SLAB_PAD, NO_FP64: kernels/ray_triangle.h
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
#ifndef EXACT_LEAVES
#define EXACT_LEAVES 1
#endif

#include "ray_triangle.h"
#include "instance_ray.h"

/* One ordered step: of node x's two children, whether the ray enters them
 * before `limit`, the nearer first (equal entries: the nearer exit; equal
 * again: the right child). Pushes the farther of two; *next is the nearer or
 * the only one, -1 for none. */
inline void children(__global const float4 *nodes, int x, const Ray *ray, float limit, int *stack,
                     float *stack_entry, int *sp, int *flag, int *next, float *next_entry) {
    const int a = as_int(nodes[2 * x].w), b = as_int(nodes[2 * x + 1].w);
    float e0, x0, e1, x1;
    const int h0 = slab((__global const float *)(nodes + 2 * a), ray, limit, &e0, &x0);
    const int h1 = slab((__global const float *)(nodes + 2 * b), ray, limit, &e1, &x1);
    *next = -1;
    if (h0 && h1) {
        const int left_first = e0 < e1 || (e0 == e1 && x0 < x1);
        *next = left_first ? a : b;
        *next_entry = left_first ? e0 : e1;
        if (*sp < STACK_SIZE) {
            stack[*sp] = left_first ? b : a;
            stack_entry[*sp] = left_first ? e1 : e0;
            ++*sp;
        } else {
            *flag |= FLAG_OVERFLOW;
        }
    } else if (h0 || h1) {
        *next = h0 ? a : b;
        *next_entry = h0 ? e0 : e1;
    }
}

/* The next node to visit after a leaf or a node with no child entered: the top
 * of the stack, dropping entries beyond `cut`; -1 when none is left. */
inline int pop(int *stack, float *stack_entry, int *sp, float cut, float *entry) {
    while (*sp > 0 && stack_entry[*sp - 1] > cut) --*sp;
    if (*sp == 0) return -1;
    --*sp;
    *entry = stack_entry[*sp];
    return stack[*sp];
}

/* A world t (along d as given) along make_ray's d * 2^-texp. */
inline float along(const Ray *ray, float t) { return ray->texp != 0 ? ldexp(t, ray->texp) : t; }

/* The closest hit (any hit with ANY_HIT) of *ray in the mesh tree at `root`:
 * returns whether one was found, with its t (along the ray as make_ray scaled
 * it), barycentrics and slot. */
inline int trace_mesh(__global const float4 *nodes, __global const float *vertices,
                      __global const uint *slot_faces, int root, int num_nodes, const Ray *ray,
                      float *t, float *bu, float *bv, int *slot, int *flag, int *visited,
                      int *tested) {
    int stack[STACK_SIZE];
    float stack_entry[STACK_SIZE];
    int sp = 0, found = 0, steps = 0;
    float best = INFINITY, entry, leave;
    if (!slab((__global const float *)(nodes + 2 * root), ray, ray->tmax, &entry, &leave)) return 0;
    int x = root;
    while (x >= 0) {
        ++*visited;
        if (++steps > num_nodes) {
            *flag |= FLAG_VISIT_LIMIT;
            break;
        }
        const int a = as_int(nodes[2 * x].w), b = as_int(nodes[2 * x + 1].w);
        int next = -1;
        float next_entry = 0.0f;
        if (node_is_leaf(b)) {
            /* a leaf of one triangle is the triangle's own box (accept_hit) */
            const float own = EXACT_LEAVES && b == -1 ? entry : -1.0f;
            for (int s = a; s < a - b; ++s) {
                ++*tested;
                if (hit_triangle(vertices, 3 * (int)slot_faces[3 * s], 3 * (int)slot_faces[3 * s + 1],
                                 3 * (int)slot_faces[3 * s + 2], ray, own, &best, bu, bv)) {
                    *slot = s;
                    found = 1;
#if ANY_HIT
                    *t = best;
                    return 1;
#endif
                }
            }
        } else {
            children(nodes, x, ray, min_keep(best, ray->tmax), stack, stack_entry, &sp, flag,
                     &next, &next_entry);
        }
        if (next < 0)
            next = pop(stack, stack_entry, &sp, min_keep(best, ray->tmax) * SLAB_PAD, &next_entry);
        x = next;
        entry = next_entry;
    }
    *t = best;
    return found;
}

__kernel void trace_instances(__global const float4 *top_nodes, __global const int *top_order,
                              const int top_root, const int top_num_nodes,
                              __global const float *inverse, __global const int *inst_root,
                              __global const float4 *nodes, __global const float4 *nodes1,
                              __global const float4 *nodes2, __global const float4 *nodes3,
                              const int num_nodes,
                              __global const int *prim_order, __global const float *vertices,
                              __global const uint *slot_faces,
                              __global const float *origins, __global const float *directions,
                              __global const float *tmins, __global const float *tmaxs,
                              const int interval_stride, __global float *hits,
                              __global int *flags, __global int2 *counters, const int count) {
    const int i = get_global_id(0);
    if (i >= count) return;
    Ray ray;
    make_ray(&ray, origins + 3 * i, directions + 3 * i, tmins[i * interval_stride],
             tmaxs[i * interval_stride]);
    const float tmin = tmins[i * interval_stride], tmax = tmaxs[i * interval_stride];
    float w[6];   /* the world ray as given (make_ray may have scaled its copy) */
    const int nan_ray = world_ray(origins, directions, i, tmin, tmax, w);
    float best = INFINITY, bu = 0.0f, bv = 0.0f;   /* best: world t along d as given */
    int best_slot = -1, best_inst = -1, flag = 0, visited = 1, tested = 0;
    if (nan_ray) flag |= FLAG_NAN_RAY;
    int stack[STACK_SIZE];
    float stack_entry[STACK_SIZE];
    int sp = 0, steps = 0;
    float entry, leave;
    /* top-level distances are along make_ray's d * 2^-texp: best scaled the same way */
    int x = !nan_ray && slab((__global const float *)(top_nodes + 2 * top_root), &ray, ray.tmax,
                             &entry, &leave) ? top_root : -1;
    while (x >= 0) {
        if (++steps > top_num_nodes) {
            flag |= FLAG_VISIT_LIMIT;
            break;
        }
        const int a = as_int(top_nodes[2 * x].w), b = as_int(top_nodes[2 * x + 1].w);
        int next = -1;
        float next_entry = 0.0f;
        if (node_is_leaf(b)) {
            for (int s = a; s < a - b; ++s) {
                const int inst = top_order[s];
                Ray moved;
                if (!move_ray(inverse + 12 * inst, w, tmin, min_keep(best, tmax), &moved))
                    continue;
                float t, u, v;
                int slot = -1;
                const int r = inst_root[inst];
                if (trace_mesh(chunk_nodes(r, nodes, nodes1, nodes2, nodes3), vertices, slot_faces,
                               chunk_root(r), num_nodes, &moved, &t,
                               &u, &v, &slot, &flag, &visited, &tested)) {
                    if (moved.texp != 0) t = ldexp(t, -moved.texp);
                    if (t < best || best_slot < 0) {
                        best = t;
                        bu = u;
                        bv = v;
                        best_slot = slot;
                        best_inst = inst;
                    }
#if ANY_HIT
                    break;
#endif
                }
            }
#if ANY_HIT
            if (best_slot >= 0) break;
#endif
        } else {
            ++visited;
            children(top_nodes, x, &ray, min_keep(along(&ray, best), ray.tmax), stack,
                     stack_entry, &sp, &flag, &next, &next_entry);
        }
        if (next < 0) {
            const float cut = min_keep(along(&ray, best), ray.tmax);
            next = pop(stack, stack_entry, &sp, cut * SLAB_PAD, &next_entry);
        }
        x = next;
        entry = next_entry;
    }
    hits[i] = best + 0.0f;
    hits[count + i] = bu;
    hits[2 * count + i] = bv;
    hits[3 * count + i] = as_float(best_slot >= 0 ? prim_order[best_slot] : -1);
    hits[4 * count + i] = as_float(best_inst);
    flags[i] = flag;
#if COUNTERS
    counters[i] = (int2)(visited, tested);
#endif
}
