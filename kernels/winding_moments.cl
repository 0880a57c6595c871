/* The moments of the winding numbers' far-node expansion (Barill, Dickson,
 * Schmidt, Levin & Jacobson 2018, "Fast winding numbers for soups and
 * clouds", sections 3.1-3.2), made on the device in double: what
 * kernels/winding.cl reads of each node or wide-record lane.
 *
 * Twin: lbvh/queries/winding_moments.py node_moments (and wide_moments for
 * the records' rows), the same float64 operations in the same order, so the
 * float32 results are the same bit for bit (no contraction: common.h).
 *
 * moments: one walk per leaf, bottom-up (Karras 2012, section 4, as
 * refit.cl; the leaves are leaf_nodes[k], or leaf_first + k in a Karras
 * tree, and a work-item walks per_item of them): a leaf sums its triangles'
 * terms slot by slot; the second walk to reach an internal node adds
 * left + right and goes on. The sums are taken in double about the centre
 * `shift` of the mesh's box, so that a mesh far from the origin loses no
 * digits, with every length times `scale` (a power of two: winding.cl scales
 * its differences by the same, winding_moments.py winding_scale), TERMS of
 * them (the columns of the twin's _triangle_terms):
 *   [0] area, [1:4] area * centroid, [4:7] the vector area a,
 *   [7:16] B = a c^T row by row, and with ORDER=2 [16:34] a_i Q_jk for
 *   i = x, y, z within each pair jk of (xx, yy, zz, xy, xz, yz),
 *   Q = (sum_v v v^T + 9 c c^T) / 12, the mean of x x^T over the triangle.
 * As soon as a node's sums are known its ROWS floats are written from them
 * and its box, each a coefficient of winding.cl's FAR_TERM: the centre p (at
 * the mesh's unit size, as every length: p + shift * scale), R^2,
 * N, of M = B - N p^T its trace and -3 times its symmetric pairs (M_jj,
 * M_jk + M_kj), and with ORDER=2 H_ijk = sum a_i Q_jk - B_ij p_k - B_ik p_j +
 * N_i p_j p_k contracted (g = -3/2 (2 u + t), u_k = H_iik, t_i = H_ijj; then the
 * cubic 15/2 H_ijk r_i r_j r_k by its ten monomials), and last the far floor
 * A R^3 / far_divisor, A the node's triangle area (winding.cl: a node is far
 * only where r^5 is at least that; far_divisor = 4 pi times the error allowed
 * per node, winding_moments.py NODE_ERROR).
 *
 * Defines: ORDER (1 or 2, default 2); WIDE_OUT (0 or 1): the rows go into
 * wide records (records, RECORD_ROWS, WIDTH), each node to the lane that holds
 * it (lane_slots), instead of one row of ROWS floats per node; WIDTH (4 or 8)
 * with WIDE_OUT. A record's rows are the ROWS of its lanes' moments, then
 * CORNER_ROWS: the corners of the first triangle of each leaf lane (x, y, z
 * of its first corner, then the second, the third, from the least corner on
 * (common.h least_corner); the float32 vertices times the scale), zeros in
 * the other lanes, which winding.cl sums lane by lane
 * where the leaf is near (winding_moments.py lane_corners).
 */
#include "common.h"

/* Doubles only: the host makes the moments here only where the device has them
 * (winding_moments.py device_can_make); elsewhere this file holds no kernel. */
#if defined(cl_khr_fp64)
#pragma OPENCL EXTENSION cl_khr_fp64 : enable

#ifndef ORDER
#define ORDER 2
#endif
#if ORDER == 2
#define TERMS 34
#define ROWS 28
#elif ORDER == 1
#define TERMS 16
#define ROWS 15
#else
#error "ORDER must be 1 or 2"
#endif
#ifndef WIDE_OUT
#define WIDE_OUT 0
#endif
#define CORNER_ROWS 9
#define RECORD_ROWS (ROWS + CORNER_ROWS)
#ifndef WIDTH
#define WIDTH 8
#endif

/* Pair m of the symmetric second moments: (xx, yy, zz, xy, xz, yz). */
__constant int PAIR_J[6] = {0, 1, 2, 0, 0, 1};
__constant int PAIR_K[6] = {0, 1, 2, 1, 2, 2};
/* The cubic's monomials r_a r_b r_c, a <= b <= c (winding_moments.py CUBIC_MONOMIALS):
 * xxx, yyy, zzz, xxy, xxz, xyy, yyz, xzz, yzz, xyz. */
__constant int CUBE_A[10] = {0, 1, 2, 0, 0, 0, 1, 0, 1, 0};
__constant int CUBE_B[10] = {0, 1, 2, 0, 0, 1, 1, 2, 2, 1};
__constant int CUBE_C[10] = {0, 1, 2, 1, 2, 1, 2, 2, 2, 2};

/* Vertex v in double, less the shift, times the scale (a power of two). */
inline void corner(__global const float *vertices, uint v, const double *shift, double scale,
                   double *x) {
    for (int j = 0; j < 3; ++j) x[j] = ((double)vertices[3 * v + j] - shift[j]) * scale;
}

/* Which corner of triangle t its walk starts from: its least (common.h
 * least_corner), 0 where two corners are one point (a triangle of no area,
 * whose terms are 0 from any corner). */
inline int first_corner(__global const float *vertices, __global const uint *faces, int t) {
    const int least = least_corner(load_float3(vertices, faces[3 * t]),
                                   load_float3(vertices, faces[3 * t + 1]),
                                   load_float3(vertices, faces[3 * t + 2]));
    return least < 0 ? 0 : least;
}

/* The TERMS terms of triangle t, into out (winding_moments.py _triangle_terms),
 * its corners read from the least on, and the centroid and Q summed symmetric
 * in the last two: the same doubles for any corner the mesh lists first, the
 * vector area (and so every term but the area's) negated exactly for the
 * winding reversed. */
inline void triangle_terms(__global const float *vertices, __global const uint *faces, int t,
                           const double *shift, double scale, double *out) {
    double x[3][3];
    const int first = first_corner(vertices, faces, t);
    for (int k = 0; k < 3; ++k)
        corner(vertices, faces[3 * t + (first + k) % 3], shift, scale, x[k]);
    double e1[3], e2[3], a[3], c[3];
    for (int j = 0; j < 3; ++j) {
        e1[j] = x[1][j] - x[0][j];
        e2[j] = x[2][j] - x[0][j];
        c[j] = (x[0][j] + (x[1][j] + x[2][j])) / 3.0;
    }
    a[0] = 0.5 * (e1[1] * e2[2] - e1[2] * e2[1]);
    a[1] = 0.5 * (e1[2] * e2[0] - e1[0] * e2[2]);
    a[2] = 0.5 * (e1[0] * e2[1] - e1[1] * e2[0]);
    const double area = sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]);
    out[0] = area;
    for (int j = 0; j < 3; ++j) {
        out[1 + j] = area * c[j];
        out[4 + j] = a[j];
        for (int k = 0; k < 3; ++k) out[7 + 3 * j + k] = a[j] * c[k];
    }
#if ORDER == 2
    for (int m = 0; m < 6; ++m) {
        const int j = PAIR_J[m], k = PAIR_K[m];
        const double q = ((x[0][j] * x[0][k] + (x[1][j] * x[1][k] + x[2][j] * x[2][k]))
                          + 9.0 * c[j] * c[k]) / 12.0;
        for (int i = 0; i < 3; ++i) out[16 + 3 * m + i] = a[i] * q;
    }
#endif
}

/* The sums of a leaf's triangles, slot by slot from its first (the twin's order). */
inline void leaf_sums(__global const float *vertices, __global const uint *faces,
                      __global const int *prim_order, int first, int count,
                      const double *shift, double scale, double *s) {
    double t[TERMS];
    for (int i = 0; i < TERMS; ++i) s[i] = 0.0;
    for (int k = 0; k < count; ++k) {
        triangle_terms(vertices, faces, prim_order[first + k], shift, scale, t);
        if (k == 0) {
            for (int i = 0; i < TERMS; ++i) s[i] = t[i];
        } else {
            for (int i = 0; i < TERMS; ++i) s[i] += t[i];
        }
    }
}

inline double max_d(double a, double b) { return a > b ? a : b; }

/* h[jk]_i of pair m (j <= k): sum a_i Q_jk - B_ij p_k - B_ik p_j + N_i p_j p_k. */
inline double h_of(const double *s, const double *p, int m, int i) {
    const int j = PAIR_J[m], k = PAIR_K[m];
    return s[16 + 3 * m + i] - s[7 + 3 * i + j] * p[k] - s[7 + 3 * i + k] * p[j]
           + s[4 + i] * (p[j] * p[k]);
}

/* The pair index of (j, k) in either order. */
inline int pair_of(int j, int k) {
    if (j == k) return j;
    return j + k + 2;   /* (0,1) -> 3, (0,2) -> 4, (1,2) -> 5 */
}

/* Node `node`'s ROWS floats, from its sums s and its box, at o[r * stride]. */
inline void write_rows(__global const float *nodes, int node, const double *s,
                       const double *shift, double scale, double far_divisor,
                       __global float *o, int stride) {
    double lo[3], hi[3], p[3];
    for (int j = 0; j < 3; ++j) {
        lo[j] = ((double)nodes[8 * node + j] - shift[j]) * scale;
        hi[j] = ((double)nodes[8 * node + 4 + j] - shift[j]) * scale;
    }
    const double area = s[0];
    for (int j = 0; j < 3; ++j) p[j] = area > 0.0 ? s[1 + j] / area : 0.5 * (lo[j] + hi[j]);
    double r2 = 0.0;
    for (int j = 0; j < 3; ++j) {
        const double far = max_d(fabs(hi[j] - p[j]), fabs(p[j] - lo[j]));
        r2 = j == 0 ? far * far : r2 + far * far;
    }
    for (int j = 0; j < 3; ++j) o[j * stride] = (float)(p[j] + shift[j] * scale);
    o[3 * stride] = (float)r2;
    o[(ROWS - 1) * stride] = (float)(area * r2 * sqrt(r2) / far_divisor);
    double m[3][3];   /* M = B - N p^T */
    for (int i = 0; i < 3; ++i) {
        o[(4 + i) * stride] = (float)s[4 + i];
        for (int j = 0; j < 3; ++j) m[i][j] = s[7 + 3 * i + j] - s[4 + i] * p[j];
    }
    o[7 * stride] = (float)((m[0][0] + m[1][1]) + m[2][2]);
    for (int q = 0; q < 6; ++q) {
        const int j = PAIR_J[q], k = PAIR_K[q];
        o[(8 + q) * stride] = (float)(-3.0 * (j == k ? m[j][j] : m[j][k] + m[k][j]));
    }
#if ORDER == 2
    for (int k = 0; k < 3; ++k) {
        double u = 0.0, t = 0.0;   /* u_k = H_iik, t_k = H_kjj, summed from 0 in order */
        for (int i = 0; i < 3; ++i) {
            u = u + h_of(s, p, pair_of(i, k), i);
            t = t + h_of(s, p, i, k);
        }
        o[(14 + k) * stride] = (float)(-1.5 * (2.0 * u + t));
    }
    /* the cubic's coefficient of each monomial r_a r_b r_c: over each distinct factor
     * i of it, 15/2 H_ijk (jk the other two), doubled where j != k */
    for (int c = 0; c < 10; ++c) {
        const int f[3] = {CUBE_A[c], CUBE_B[c], CUBE_C[c]};
        double coefficient = 0.0;
        for (int n = 0; n < 3; ++n) {
            if ((n > 0 && f[n] == f[0]) || (n > 1 && f[n] == f[1])) continue;
            const int j = f[n == 0 ? 1 : 0], k = f[n == 2 ? 1 : 2];
            const double term = (j == k ? 7.5 : 15.0) * h_of(s, p, pair_of(j, k), f[n]);
            coefficient = n == 0 ? term : coefficient + term;
        }
        o[(17 + c) * stride] = (float)coefficient;
    }
#endif
}

/* Node `node`'s rows into `out`, where they go: its own row of ROWS floats, or
 * with WIDE_OUT the lane of the record that holds it (slot[node] - 1; 0: no
 * lane holds it, as a record's own binary node). */
inline void store_rows(__global const float *nodes, __global const int *slot, int node,
                       const double *s, const double *shift, double scale, double far_divisor,
                       __global float *out) {
#if WIDE_OUT
    const int item = slot[node] - 1;
    if (item < 0) return;
    write_rows(nodes, node, s, shift, scale, far_divisor,
               out + (long)(item / WIDTH) * RECORD_ROWS * WIDTH + item % WIDTH, WIDTH);
#else
    write_rows(nodes, node, s, shift, scale, far_divisor, out + (long)ROWS * node, 1);
#endif
}

/* WIDE_OUT: the corner rows of node `node`'s lane, if a lane holds it: the
 * corners of the triangle in slot `first` for a leaf (first >= 0), zeros for
 * an internal node (first < 0). */
inline void store_corners(__global const float *vertices, __global const uint *faces,
                          __global const int *prim_order, __global const int *slot, int node,
                          int first, float scale, __global float *out) {
#if WIDE_OUT
    const int item = slot[node] - 1;
    if (item < 0) return;
    __global float *o =
        out + (long)(item / WIDTH) * RECORD_ROWS * WIDTH + ROWS * WIDTH + item % WIDTH;
    if (first < 0) {
        for (int r = 0; r < CORNER_ROWS; ++r) o[r * WIDTH] = 0.0f;
        return;
    }
    const int t = prim_order[first];
    const float3 p0 = load_float3(vertices, faces[3 * t]);
    const float3 p1 = load_float3(vertices, faces[3 * t + 1]);
    const float3 p2 = load_float3(vertices, faces[3 * t + 2]);
    const int least = least_corner(p0, p1, p2);
    for (int k = 0; k < 3; ++k) {
        /* from the least corner on; a triangle with two corners at one point: its
         * first corner three times (whose solid angle is 0 exactly) */
        const uint v = faces[3 * t + (least < 0 ? 0 : (least + k) % 3)];
        for (int j = 0; j < 3; ++j) o[(3 * k + j) * WIDTH] = vertices[3 * v + j] * scale;
    }
#endif
}

/* WIDE_OUT: where each node's rows go (slot[node] = its lane's index + 1, the
 * slots zeroed before), and the rows of the empty lanes: zeros, and R^2 and
 * the far floor -1, so that winding.cl takes them for far and adds nothing. */
__kernel void lane_slots(__global const int *lanes, __global int *slot, __global float *out,
                         const int count, const int per_item) {
    const int gid = get_global_id(0);
    const int last = chunk_last(gid, per_item, count);
    for (int item = chunk_first(gid, per_item, count); item < last; ++item) {
        const int node = lanes[item];
        if (node >= 0) {
            slot[node] = item + 1;
        } else {
            __global float *o = out + (long)(item / WIDTH) * RECORD_ROWS * WIDTH + item % WIDTH;
            for (int r = 0; r < RECORD_ROWS; ++r)
                o[r * WIDTH] = r == 3 || r == ROWS - 1 ? -1.0f : 0.0f;
        }
    }
}

/* The walks: a leaf's sums, then up the tree as far as this walk is the
 * second to arrive, each node's rows stored as soon as its sums are known.
 * Only internal nodes keep their sums in `sums` (for their parent); a leaf's
 * are summed again where its sibling needs them (a few triangles' terms cost
 * less than the memory: in a Karras tree, whose leaves are the upper half of
 * the nodes, half the array is never touched). */
__kernel void moments(__global const float *vertices, __global const uint *faces,
                      __global const int *prim_order, __global const float *nodes,
                      __global const int *parent, __global int *arrivals,
                      __global const int *leaf_nodes, const int use_leaf_list,
                      const int leaf_first, const int num_leaves, __global double *sums,
                      __global const int *slot, __global float *out, const double sx,
                      const double sy, const double sz, const double scale,
                      const double far_divisor, const int per_item) {
    const int gid = get_global_id(0);
    const double shift[3] = {sx, sy, sz};
    const int last = chunk_last(gid, per_item, num_leaves);
    __global const int *words = (__global const int *)nodes;
    for (int k = chunk_first(gid, per_item, num_leaves); k < last; ++k) {
        int at = use_leaf_list ? leaf_nodes[k] : leaf_first + k;
        double s[TERMS], o[TERMS];
        leaf_sums(vertices, faces, prim_order, words[8 * at + 3], -words[8 * at + 7], shift,
                  scale, s);
        store_rows(nodes, slot, at, s, shift, scale, far_divisor, out);
        store_corners(vertices, faces, prim_order, slot, at, words[8 * at + 3], (float)scale,
                      out);
        for (;;) {
            const int p = parent[at];
            if (p < 0) break;
            if (!second_arrival(arrivals, p)) break;
            const int left = words[8 * p + 3];
            const int sibling = left == at ? words[8 * p + 7] : left;
            const int sb = words[8 * sibling + 7];
            if (node_is_leaf(sb)) {
                leaf_sums(vertices, faces, prim_order, words[8 * sibling + 3], -sb, shift, scale,
                          o);
            } else {
                volatile __global const double *q = sums + (long)TERMS * sibling;
                for (int i = 0; i < TERMS; ++i) o[i] = q[i];
            }
            if (left == at) {
                for (int i = 0; i < TERMS; ++i) s[i] = s[i] + o[i];
            } else {
                for (int i = 0; i < TERMS; ++i) s[i] = o[i] + s[i];
            }
            for (int i = 0; i < TERMS; ++i) sums[(long)TERMS * p + i] = s[i];
            store_rows(nodes, slot, p, s, shift, scale, far_divisor, out);
            store_corners(vertices, faces, prim_order, slot, p, -1, (float)scale, out);
            at = p;
        }
    }
}

#endif /* cl_khr_fp64 */
