/* Every hit along each ray, and the hit counts (lbvh/queries/all_hits.py).
 *
 * A depth-first traversal of the binary nodes (docs/layout.md) enters every
 * node whose box the ray's [tmin, tmax] enters, by the slab test of
 * kernels/ray_triangle.h, and tests every triangle of every such leaf with
 * the watertight test (Woop, Benthin, Wald 2013) under EDGE_RULE: a ray
 * through an edge or a vertex shared by several triangles hits exactly one of
 * them where it crosses the surface (simulation of simplicity, see
 * ray_triangle.h), so a crossing counts once. A hit counts only where the ray
 * enters the triangle's own box (accept_hit), so the set of hits does not
 * depend on the tree: every node holding such a triangle holds its box.
 *
 * Two passes over the same traversal: COUNT=1 writes how many hits each ray
 * has in [tmin, tmax]; COUNT=0 writes them into [offsets[i], offsets[i + 1])
 * (the host's prefix sum of the counts, each capped at the caller's
 * max_hits): t, u, v and the triangle in the caller's numbering, unsorted
 * while they fit; past the cap a hit replaces the farthest kept one when it is
 * nearer (by t, then triangle index), so the nearest ones are kept.
 *
 * Defines:
 *   STACK_SIZE=n  stack entries; a push beyond n sets FLAG_OVERFLOW and skips
 *                 that subtree (the host sizes it from the tree's depth).
 *   COUNT=0|1     the pass.
 *   COUNTERS=1    (with COUNT=1) also write per ray the internal nodes and the
 *                 leaves entered and the triangles tested: with tmax at the
 *                 closest hit, the work any traversal must do for that ray
 *                 (the ray-sampled cost of lbvh/verification/quality.py).
 *   SLAB_PAD, NO_FP64: kernels/ray_triangle.h.
 */
#include "common.h"

#ifndef STACK_SIZE
#define STACK_SIZE 64
#endif
#ifndef COUNT
#define COUNT 1
#endif
#ifndef COUNTERS
#define COUNTERS 0
#endif
#if COUNTERS && !COUNT
#error "COUNTERS goes with the counting pass"
#endif
#if defined(TRIANGLE_TEST) && TRIANGLE_TEST != 0
#error "all_hits.cl counts crossings with the watertight test only"
#endif
#define EDGE_RULE 1

#include "ray_triangle.h"

/* (t, prim) ordering: nearer first, then the lower triangle index. */
inline int before(float ta, int pa, float tb, int pb) { return ta < tb || (ta == tb && pa < pb); }

__kernel void all_hits(__global const float4 *nodes, __global const int *prim_order,
                       __global const float *vertices, __global const uint *slot_faces,
                       const int root, const int num_nodes,
                       __global const float *origins, __global const float *directions,
                       __global const float *tmins, __global const float *tmaxs,
                       const int interval_stride, const int count,
                       __global const long *offsets, __global int *counts,
                       __global float *out_t, __global float *out_u, __global float *out_v,
                       __global int *out_prim, __global int *flags, __global int4 *work) {
    const int i = get_global_id(0);
    if (i >= count) return;
    Ray ray;
    make_ray(&ray, origins + 3 * i, directions + 3 * i, tmins[i * interval_stride],
             tmaxs[i * interval_stride]);
#if !COUNT
    const long first = offsets[i];
    const int cap = (int)(offsets[i + 1] - first);
#endif
    int found = 0, flag = 0;
    const int nan_ray = ray.ox != ray.ox || ray.oy != ray.oy || ray.oz != ray.oz ||
                        ray.dx != ray.dx || ray.dy != ray.dy || ray.dz != ray.dz ||
                        ray.tmin != ray.tmin || ray.tmax != ray.tmax;   /* isnan */
    if (nan_ray) flag |= FLAG_NAN_RAY;
    float entry, leave;
    int node = !nan_ray && slab((__global const float *)(nodes + 2 * root), &ray, ray.tmax,
                                &entry, &leave) ? root : -1;
    int stack[STACK_SIZE];
    int top = 0, visits = 0, leaves = 0, tested = 0;
    for (;;) {
        if (node >= 0) {
            if (++visits > num_nodes) {
                flag |= FLAG_VISIT_LIMIT;
                break;
            }
            const int a = as_int(nodes[2 * node].w), b = as_int(nodes[2 * node + 1].w);
            if (node_is_leaf(b)) {
                ++leaves;
                tested -= b;
                for (int s = a; s < a - b; ++s) {
                    float t = INFINITY, u = 0.0f, v = 0.0f;
                    if (!hit_triangle(vertices, 3 * (int)slot_faces[3 * s],
                                      3 * (int)slot_faces[3 * s + 1],
                                      3 * (int)slot_faces[3 * s + 2], &ray, -1.0f, &t, &u, &v))
                        continue;
#if !COUNT
                    /* t along d * 2^-texp (make_ray) back to d; + 0.0f: no -0.0 */
                    if (ray.texp != 0) t = ldexp(t, -ray.texp);
                    t += 0.0f;
                    const int prim = prim_order[s];
                    long slot = -1;
                    if (found < cap) {
                        slot = first + found;
                    } else if (cap > 0) {
                        /* full: replace the farthest kept hit if this one is nearer */
                        long far = first;
                        for (long k = first + 1; k < first + cap; ++k)
                            if (before(out_t[far], out_prim[far], out_t[k], out_prim[k])) far = k;
                        if (before(t, prim, out_t[far], out_prim[far])) slot = far;
                    }
                    if (slot >= 0) {
                        out_t[slot] = t;
                        out_u[slot] = u;
                        out_v[slot] = v;
                        out_prim[slot] = prim;
                    }
#endif
                    ++found;
                }
                node = -1;
            } else {
                float ea, eb;
                const int in_a = slab((__global const float *)(nodes + 2 * a), &ray, ray.tmax,
                                      &ea, &leave);
                const int in_b = slab((__global const float *)(nodes + 2 * b), &ray, ray.tmax,
                                      &eb, &leave);
                if (in_a && in_b) {
                    if (top < STACK_SIZE) stack[top++] = b;
                    else flag |= FLAG_OVERFLOW;
                }
                node = in_a ? a : (in_b ? b : -1);
            }
            continue;
        }
        if (top == 0) break;
        node = stack[--top];
    }
#if COUNT
    counts[i] = found;
#endif
#if COUNTERS
    work[i] = (int4)(visits - leaves, leaves, tested, 0);
#endif
    flags[i] = flag;
}
