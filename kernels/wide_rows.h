/* A wide record's rows (kernels/wide.cl: 8 rows of WIDTH 32-bit words, rows
 * 0-5 the lanes' lower.x, upper.x, lower.y, upper.y, lower.z, upper.z, rows
 * 6-7 their references) as OpenCL vectors, and as lanes: what the kernels
 * that walk wide records share (traverse.cl and every_hit.h through
 * wide_slab.h, overlap.cl).
 *
 * Defines: WIDTH (4 or 8, default 8).
 */
#ifndef LBVH_WIDE_ROWS_H
#define LBVH_WIDE_ROWS_H

#ifndef WIDTH
#define WIDTH 8
#endif

#if WIDTH == 4
typedef float4 floatw;
typedef int4 intw;
#elif WIDTH == 8
typedef float8 floatw;
typedef int8 intw;
#else
#error "WIDTH must be 4 or 8"
#endif
typedef union { floatw v; float s[WIDTH]; } floatw_lanes;
typedef union { intw v; int s[WIDTH]; } intw_lanes;

/* max_keep and min_keep lane by lane (NaN in x keeps m). */
inline floatw max_keep_w(floatw x, floatw m) { return x > m ? x : m; }
inline floatw min_keep_w(floatw x, floatw m) { return x < m ? x : m; }

#endif
