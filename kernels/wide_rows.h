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
#define SQRTW sqrt4   /* common.h */
#define as_floatw as_float4
#define as_intw as_int4
#elif WIDTH == 8
typedef float8 floatw;
typedef int8 intw;
#define SQRTW sqrt8   /* common.h */
#define as_floatw as_float8
#define as_intw as_int8
#else
#error "WIDTH must be 4 or 8"
#endif
typedef union { floatw v; float s[WIDTH]; } floatw_lanes;
typedef union { intw v; int s[WIDTH]; } intw_lanes;

/* Bit c set where lane c of v is non-zero (a comparison's lanes are 0 or -1),
 * without branches: the closest-hit walk (traverse.cl) goes through the
 * lanes hit by iterating over these bits (lowest_lane) instead of testing all
 * WIDTH lanes one by one, whose branches the CPU mispredicts (measured 1-8%
 * faster, bench/README.md), and so do the closest-point and winding walks
 * (closest.cl, winding.cl). The every-hit walk (every_hit.h) takes its
 * lanes by the mask too, together with a prefetch of the records it pushes
 * (alone, the mask measured no faster there). enter_lanes, the box walk's
 * step, keeps the per-lane test. */
#ifndef CLANG_MOVMSK
#define CLANG_MOVMSK 0
#endif
inline uint lane_bits(intw v) {
#if CLANG_MOVMSK && defined(__clang__) && defined(__AVX__) && WIDTH == 8
    /* The lanes' sign bits by one vmovmskps, where the host says the compiler
     * is clang (CLANG_MOVMSK, as refit.cl's CLANG_PREFETCH: PoCL) and the
     * target has AVX (clang defines __AVX__ from the target CPU; the builtin
     * does not compile without it, and __has_builtin says yes regardless).
     * LLVM 14 does not turn the reduction below into one. A lane of 0 or -1
     * has its sign bit set exactly when it is non-zero. */
    return (uint)__builtin_ia32_movmskps256(as_float8(v));
#else
#if WIDTH == 8
    const intw b = v & (intw)(1, 2, 4, 8, 16, 32, 64, 128);
    const int4 h = b.lo | b.hi;
#else
    const int4 h = v & (int4)(1, 2, 4, 8);
#endif
    const int2 q = h.lo | h.hi;
    return (uint)(q.x | q.y);
#endif
}

/* The index of the lowest set bit of a mask m != 0 of up to 16 bits: by
 * clang's count of trailing zeros (one instruction) where the host says the
 * compiler is clang (CLANG_CTZ, as CLANG_MOVMSK: PoCL), else by bit tests
 * (PoCL calls clz out of line; OpenCL 1.2 has no ctz). */
#ifndef CLANG_CTZ
#define CLANG_CTZ 0
#endif
inline int lowest_bit16(uint m) {
#if CLANG_CTZ && defined(__clang__)
    return __builtin_ctz(m);
#else
    const uint b = m & (0u - m);
    return ((b & 0xff00u) != 0u ? 8 : 0) | ((b & 0xf0f0u) != 0u ? 4 : 0) |
           ((b & 0xccccu) != 0u ? 2 : 0) | ((b & 0xaaaau) != 0u ? 1 : 0);
#endif
}

/* The lane of the lowest set bit of a lane mask m != 0. */
inline int lowest_lane(uint m) { return lowest_bit16(m); }

/* Record q of `records` (kernels/wide.cl: 8 rows of WIDTH floats, 32 WIDTH
 * bytes) asked into the cache ahead of its visit: a walk that pushes a
 * record it will certainly visit (every hit, kernels/every_hit.h) has its
 * rows arrive while it tests the current record's leaves and pops the
 * others, where the visit would otherwise wait for them (the walk's loads
 * depend one on the last). OpenCL's prefetch() does nothing on PoCL;
 * CLANG_PREFETCH=1, which the host sets where the compiler is clang (PoCL),
 * uses clang's builtin, one cache line of 64 bytes at a time, as refit.cl. */
#ifndef CLANG_PREFETCH
#define CLANG_PREFETCH 0
#endif
inline void prefetch_record(__global const float *records, int q) {
    __global const float *r = records + 8 * WIDTH * q;
#if CLANG_PREFETCH && defined(__clang__)
    for (int line = 0; line < 8 * WIDTH; line += 16) __builtin_prefetch(r + line);
#else
    prefetch(r, 8 * WIDTH);
#endif
}

/* max_keep and min_keep lane by lane (NaN in x keeps m). */
inline floatw max_keep_w(floatw x, floatw m) { return x > m ? x : m; }
inline floatw min_keep_w(floatw x, floatw m) { return x < m ? x : m; }

/* A step of a walk that enters every lane set in *lanes (box queries,
 * overlap.cl): the first such lane's reference becomes (*x, *y), from rows 6-7 of the
 * record (`ref`), and 1 is returned (0 for no lane); the others' references
 * are pushed on (stack_x, stack_y) of `capacity` entries, and a push beyond
 * it drops that lane and sets `overflow` in *flag. */
inline int enter_lanes(const intw_lanes *lanes, __global const int *ref, int *stack_x,
                       int *stack_y, int capacity, int *top, int *flag, int overflow, int *x,
                       int *y) {
    int next = -1;
    for (int c = 0; c < WIDTH; ++c) {
        if (!lanes->s[c]) continue;
        if (next < 0) {
            next = c;
        } else if (*top < capacity) {
            stack_x[*top] = ref[c];
            stack_y[*top] = ref[WIDTH + c];
            ++*top;
        } else {
            *flag |= overflow;
        }
    }
    if (next < 0) return 0;
    *x = ref[next];
    *y = ref[WIDTH + next];
    return 1;
}

/* The walk's next reference from the stack into (*x, *y): 0 when it is empty. */
inline int pop_lane(const int *stack_x, const int *stack_y, int *top, int *x, int *y) {
    if (*top == 0) return 0;
    --*top;
    *x = stack_x[*top];
    *y = stack_y[*top];
    return 1;
}

#endif
