/* Exact signs of short polynomials in float32 inputs, in double: the last
 * stage of the adaptive predicates of kernels/ray_triangle.h (Shewchuk 1997,
 * "Adaptive Precision Floating-Point Arithmetic and Fast Robust Geometric
 * Predicates", DCG 18: expansions, Two-Sum, Grow-Expansion with zero
 * elimination, section 2).
 *
 * A product of two floats is exact in double (48 significant bits, exponents
 * within 2^-298 .. 2^256); a product of three is exact as two doubles, the
 * rounded product and its error by fma (Two-Product, Shewchuk section 2.6),
 * since no such product or error comes near double's underflow (2^-447 times
 * 2^-53 is far above 2^-1022). A sum of such terms is then exact as an
 * expansion: nonoverlapping doubles in increasing magnitude, whose sign is the
 * sign of the largest (its last component).
 *
 * Only where the fp64 extension is there (EXACT_FP64, ray_triangle.h); every
 * value crossing a function is a scalar or a pointer. Twin:
 * lbvh.queries.exact (Python's integers and fractions, exact by construction).
 */
#ifndef LBVH_EXACT_H
#define LBVH_EXACT_H

/* The most terms one expansion takes: orient3d's 24 triple products, two
 * doubles each. */
#define EXPANSION_TERMS 48

/* h[0 .. *m) += x (Grow-Expansion, Shewchuk section 2.5, with zero
 * elimination): Two-Sum of x through the components, from the smallest. */
inline void expansion_add(double *h, int *m, double x) {
    int k = 0;
    double q = x;
    const int n = *m;
    for (int j = 0; j < n; ++j) {
        const double hj = h[j];
        const double s = q + hj;
        const double bv = s - q;
        const double err = (q - (s - bv)) + (hj - bv);
        q = s;
        if (err != 0.0) h[k++] = err;
    }
    if (q != 0.0) h[k++] = q;
    *m = k;
}

/* The sign of an expansion: of its largest component (0 for none). */
inline int expansion_sign(const double *h, int m) {
    return m == 0 ? 0 : (h[m - 1] > 0.0 ? 1 : -1);
}

/* h += s x y z for floats x, y, z and s = +-1, exactly (Two-Product by fma). */
inline void expansion_add_product3(double *h, int *m, double s, float x, float y, float z) {
    const double p = (double)y * (double)z;   /* exact */
    const double hi = p * (double)x;
    const double lo = fma(p, (double)x, -hi);   /* the error of hi, exact */
    expansion_add(h, m, s * hi);
    expansion_add(h, m, s * lo);
}

/* h += s det[x, y, z] (rows x, y, z), six triple products. */
inline void expansion_add_det3(double *h, int *m, double s, float x0, float x1, float x2,
                               float y0, float y1, float y2, float z0, float z1, float z2) {
    expansion_add_product3(h, m, s, x0, y1, z2);
    expansion_add_product3(h, m, -s, x0, y2, z1);
    expansion_add_product3(h, m, -s, x1, y0, z2);
    expansion_add_product3(h, m, s, x1, y2, z0);
    expansion_add_product3(h, m, s, x2, y0, z1);
    expansion_add_product3(h, m, -s, x2, y1, z0);
}

/* The exact sign of a b + c d + e f + g k, four products of two floats (a
 * caller negates an input for a difference: negation is exact). */
inline int exact_sign4(float a, float b, float c, float d, float e, float f, float g, float k) {
    double h[4];
    int m = 0;
    expansion_add(h, &m, (double)a * (double)b);
    expansion_add(h, &m, (double)c * (double)d);
    expansion_add(h, &m, (double)e * (double)f);
    expansion_add(h, &m, (double)g * (double)k);
    return expansion_sign(h, m);
}

/* Whether the exact 2D orientation of (a, b, c) is zero: (b - a) x (c - a),
 * expanded so that every term is a product of two input floats:
 * bx cy - bx ay - ax cy - by cx + by ax + ay cx. */
inline int orient2d_is_zero(float ax, float ay, float bx, float by, float cx, float cy) {
    double h[6];
    int m = 0;
    expansion_add(h, &m, (double)bx * (double)cy);
    expansion_add(h, &m, -((double)bx * (double)ay));
    expansion_add(h, &m, -((double)ax * (double)cy));
    expansion_add(h, &m, -((double)by * (double)cx));
    expansion_add(h, &m, (double)by * (double)ax);
    expansion_add(h, &m, (double)ay * (double)cx);
    return m == 0;
}

#endif
