/* Generalised winding numbers of query points (lbvh/queries/winding.py).
 *
 * w(q) = sum over triangles of the solid angle they subtend at q, over 4 pi
 * (Jacobson, Kavan & Sorkine-Hornung 2013): 1 inside a closed, outward-facing
 * mesh, 0 outside, and a smooth value in between near the holes of an open
 * one. Near triangles are summed exactly, with the solid angle of Van
 * Oosterom & Strackee 1983:
 *   tan(omega / 2) = a . (b x c) / (|a||b||c| + (a.b)|c| + (a.c)|b| + (b.c)|a|)
 * for a, b, c the corners minus q. A node far enough from q is replaced by
 * the Taylor expansion of its triangles' solid angle about its area-weighted
 * centroid p (Barill, Dickson, Schmidt, Levin & Jacobson 2018, "Fast winding
 * numbers for soups and clouds", with the terms up to their first order):
 *   omega ~ N . r / |r|^3 + tr(M) / |r|^3 - 3 r^T M r / |r|^5,   r = p - q,
 * N = sum of the triangles' vector areas a_t, M = sum of a_t (c_t - p)^T with
 * c_t the centroids. "Far enough" is |r| > beta * R, R the distance from p to
 * the farthest corner of the node's box (every triangle of the node lies
 * within R of p).
 *
 * Moments, 16 floats per node (the host computes them, winding.py):
 *   [0..2] p, [3] R^2, [4..6] N, [7..15] M row by row (M[j][k] = m[7 + 3j + k]).
 * beta2 is beta^2.
 *
 * Defines:
 *   STACK_SIZE=n  stack entries; a push beyond n sets FLAG_OVERFLOW and skips
 *                 that subtree (the host sizes it from the tree's depth).
 */
#include "common.h"

#ifndef STACK_SIZE
#define STACK_SIZE 64
#endif

#define FLAG_OVERFLOW 1

/* The solid angle of triangle (p0, p1, p2) at q (signed: positive where q sees
 * the triangle's back, its vertices counterclockwise around the outward normal). */
inline float solid_angle(float3 q, float3 p0, float3 p1, float3 p2) {
    const float3 a = p0 - q, b = p1 - q, c = p2 - q;
    const float la = sqrt(dot(a, a)), lb = sqrt(dot(b, b)), lc = sqrt(dot(c, c));
    const float num = dot(a, cross(b, c));
    const float den = la * lb * lc + dot(a, b) * lc + dot(a, c) * lb + dot(b, c) * la;
    return 2.0f * atan2(num, den);
}

__kernel void winding_numbers(__global const float4 *nodes, __global const float *moments,
                              __global const float *vertices, __global const uint *slot_faces,
                              const int root, const int num_nodes,
                              __global const float *points, const int count,
                              const float beta2,
                              __global float *winding, __global int *flags) {
    const int i = get_global_id(0);
    if (i >= count) return;
    const float3 q = load_float3(points, i);
    float w = 0.0f;
    int flag = 0;
    int stack[STACK_SIZE];
    int top = 0, visits = 0;
    int node = root;
    for (;;) {
        if (node >= 0 && visits++ < num_nodes) {
            __global const float *m = moments + 16 * node;
            const float3 r = (float3)(m[0], m[1], m[2]) - q;
            const float r2 = dot(r, r);
            const int a = as_int(nodes[2 * node].w), b = as_int(nodes[2 * node + 1].w);
            if (r2 > beta2 * m[3]) {
                /* far: the expansion (Barill et al. 2018, up to first order) */
                const float inv = 1.0f / sqrt(r2);
                const float inv3 = inv * inv * inv;
                const float3 n = (float3)(m[4], m[5], m[6]);
                const float3 mr = (float3)(m[7] * r.x + m[8] * r.y + m[9] * r.z,
                                           m[10] * r.x + m[11] * r.y + m[12] * r.z,
                                           m[13] * r.x + m[14] * r.y + m[15] * r.z);
                w += dot(n, r) * inv3 + (m[7] + m[11] + m[15]) * inv3 -
                     3.0f * dot(r, mr) * inv3 * inv * inv;
                node = -1;
            } else if (node_is_leaf(b)) {
                for (int s = a; s < a - b; ++s)
                    w += solid_angle(q, load_float3(vertices, slot_faces[3 * s]),
                                     load_float3(vertices, slot_faces[3 * s + 1]),
                                     load_float3(vertices, slot_faces[3 * s + 2]));
                node = -1;
            } else {
                if (top < STACK_SIZE) stack[top++] = b;
                else flag |= FLAG_OVERFLOW;
                node = a;
            }
            continue;
        }
        if (top == 0) break;
        node = stack[--top];
    }
    winding[i] = w * (0.25f * M_1_PI_F);
    flags[i] = flag;
}
