/* Shared definitions of the lbvh kernels: the node layout and the triangle box.
 *
 * Node layout (docs/pages/layout.md): a node is 32 bytes, two float4.
 *   node[2*i]   = (lower.x, lower.y, lower.z, as_float(a))
 *   node[2*i+1] = (upper.x, upper.y, upper.z, as_float(b))
 *   internal node: a = left child, b = right child (both >= 0)
 *   leaf:          a = first primitive (index into prim_order), b = -count (< 0)
 */
#ifndef LBVH_COMMON_H
#define LBVH_COMMON_H

/* Every kernel must give the same float results as its numpy twin: no fused
 * multiply-add contraction behind our back. */
#pragma OPENCL FP_CONTRACT OFF

inline int node_is_leaf(int b) { return b < 0; }

/* Square roots written so that PoCL 3 keeps them inline: it calls the OpenCL
 * builtin out of line (a call around one vsqrtps, with the caller's vector
 * registers spilled around it). The host defines INLINE_SQRT=1 where the
 * compiler is clang's (Context.compiler_is_clang: PoCL), as refit.cl's
 * CLANG_PREFETCH: __builtin_sqrtf is the same correctly rounded IEEE square
 * root, inline; elsewhere the OpenCL builtin. */
#ifndef INLINE_SQRT
#define INLINE_SQRT 0
#endif
#if INLINE_SQRT
inline float sqrt1(float x) { return __builtin_sqrtf(x); }
inline float4 sqrt4(float4 v) {
    return (float4)(__builtin_sqrtf(v.x), __builtin_sqrtf(v.y), __builtin_sqrtf(v.z),
                    __builtin_sqrtf(v.w));
}
inline float8 sqrt8(float8 v) { return (float8)(sqrt4(v.lo), sqrt4(v.hi)); }
#else
inline float sqrt1(float x) { return sqrt(x); }
inline float4 sqrt4(float4 v) { return sqrt(v); }
inline float8 sqrt8(float8 v) { return sqrt(v); }
#endif

/* A triangle's box PREFETCH_AHEAD slots ahead asked into the cache (refit.cl,
 * ploc.cl: boxes gathered in slot order, randomly in memory when the mesh's
 * triangles are not in spatial order). OpenCL's prefetch() does nothing on PoCL;
 * CLANG_PREFETCH=1, which the host sets where the compiler is clang (PoCL), uses
 * clang's builtin. */
#ifndef CLANG_PREFETCH
#define CLANG_PREFETCH 0
#endif
#define PREFETCH_AHEAD 32
#if CLANG_PREFETCH
#define PREFETCH_BOX(p) __builtin_prefetch(p)
#else
#define PREFETCH_BOX(p) prefetch(p, 2)
#endif

/* The chunk [first, last) of `count` items that work-item `gid` loops over;
 * one item per work-item on a GPU, a long contiguous run on a CPU. */
inline int chunk_first(int gid, int per_item, int count) {
    long f = (long)gid * per_item;
    return f < count ? (int)f : count;
}
inline int chunk_last(int gid, int per_item, int count) {
    long l = ((long)gid + 1) * per_item;
    return l < count ? (int)l : count;
}

/* A fence over the whole device's global memory. OpenCL 1.2's mem_fence
 * orders a work-item's accesses as seen from its own work-group only: enough
 * on a CPU, whose memory is coherent, but on NVIDIA's GPUs it is a work-group
 * fence. DEVICE_FENCE, set by the host for every kernel
 * (lbvh.device.programs.device_fence):
 *   0  mem_fence (CPUs)
 *   1  PTX's membar.gl (NVIDIA)
 *   2  OpenCL C 2.0/3.0's fence at device scope (other GPUs that have it;
 *      the host then compiles as OpenCL C 2.0 or 3.0). */
#ifndef DEVICE_FENCE
#define DEVICE_FENCE 0
#endif
inline void device_fence(void) {
#if DEVICE_FENCE == 1
    __asm__ volatile("membar.gl;" ::: "memory");
#elif DEVICE_FENCE == 2
    atomic_work_item_fence(CLK_GLOBAL_MEM_FENCE, memory_order_acq_rel, memory_scope_device);
#else
    mem_fence(CLK_GLOBAL_MEM_FENCE);
#endif
}

/* Bottom-up walks (Karras 2012, section 4): each walk that reaches parent p
 * bumps p's arrival counter; only the second arrival goes on, knowing that the
 * sibling's results are written. The fence before the atomic publishes this
 * walk's stores (release), the fence after it orders the sibling reads that
 * follow (acquire); OpenCL 1.2 atomics alone do not order plain memory, and
 * the walks of a node's two children may run in different work-groups, hence
 * a device-wide fence. */
inline int second_arrival(__global int *arrivals, int p) {
    device_fence();
    const int second = atomic_inc(&arrivals[p]) != 0;
    device_fence();
    return second;
}

/* min and max by plain comparisons: PoCL 3.0 calls fmin, fmax and vload3
 * out of line, which cost a third of the time of the kernels using them. The
 * inputs here are never NaN (the host rejects NaN coordinates), where these
 * agree with fmin/fmax and with numpy's minimum/maximum. */
inline float3 min3(float3 a, float3 b) {
    return (float3)(a.x < b.x ? a.x : b.x, a.y < b.y ? a.y : b.y, a.z < b.z ? a.z : b.z);
}
inline float3 max3(float3 a, float3 b) {
    return (float3)(a.x > b.x ? a.x : b.x, a.y > b.y ? a.y : b.y, a.z > b.z ? a.z : b.z);
}

/* |x| by clearing the sign bit: fabs exactly (NaN stays NaN), inline, where
 * PoCL 3.0 calls fabs out of line. */
inline float abs_bits(float x) { return as_float(as_uint(x) & 0x7fffffffu); }

inline float3 load_float3(__global const float *p, uint i) {
    return (float3)(p[3 * i], p[3 * i + 1], p[3 * i + 2]);
}

/* Which corner of a triangle is its least, ascending by x, then y, then z
 * (0, 1 or 2), or -1 where two corners are the same point (equal coordinates,
 * 0 and -0 alike). A triangle read from that corner on, in the mesh's cyclic
 * order, is the same whatever corner the mesh lists first, and its mirror
 * (winding reversed) differs only by its last two corners' swap: the winding
 * walks (winding.cl, winding_moments.cl) read triangles so, with formulas
 * symmetric in those two corners, so that a winding number does not depend on
 * how the faces are written (and a face flipped negates its share exactly). */
inline int float_corner_before(float3 a, float3 b) {
    return a.x < b.x || (a.x == b.x && (a.y < b.y || (a.y == b.y && a.z < b.z)));
}
inline int float_corner_same(float3 a, float3 b) {
    return a.x == b.x && a.y == b.y && a.z == b.z;
}
inline int least_corner(float3 a, float3 b, float3 c) {
    if (float_corner_same(a, b) || float_corner_same(b, c) || float_corner_same(a, c))
        return -1;
    if (float_corner_before(b, a) && float_corner_before(b, c)) return 1;
    if (float_corner_before(c, a) && float_corner_before(c, b)) return 2;
    return 0;
}

inline void store_float3(__global float *p, float3 v) {
    p[0] = v.x;
    p[1] = v.y;
    p[2] = v.z;
}

/* Axis-aligned box of triangle t: min and max of its three vertices (exact). */
inline void triangle_box(__global const float *vertices, __global const uint *faces,
                         int t, float3 *lo, float3 *hi) {
    const uint fa = faces[3 * t], fb = faces[3 * t + 1], fc = faces[3 * t + 2];
    float3 a = load_float3(vertices, fa);
    float3 b = load_float3(vertices, fb);
    float3 c = load_float3(vertices, fc);
    *lo = min3(min3(a, b), c);
    *hi = max3(max3(a, b), c);
}

/* The point a triangle is sorted by: the centre of its box. */
/* Halves first so that boxes near the float32 limit do not overflow. */
inline float3 box_centre(float3 lo, float3 hi) { return lo * 0.5f + hi * 0.5f; }

/* Surface areas for the SAH without overflow or underflow: boxes scaled by
 * 2^-e, e the exponent of the largest |coordinate| of a reference box,
 * clamped to [-126, 126] so the factor is a normal float (built from its
 * bits). Scaling by a power of two is exact. The largest |coordinate| is
 * taken on the bits (a float's magnitude orders as its bits without the sign;
 * a NaN orders above infinity, as numpy's maximum propagates it in the twin):
 * fmax, fabs and clamp, which PoCL 3 calls out of line, made the collapse's
 * cost pass 1.24-1.30x slower (bench/README.md). */
inline uint max_bits(uint m, float x) {
    const uint b = as_uint(x) & 0x7fffffffu;
    return b > m ? b : m;
}
inline float box_scale(float3 lo, float3 hi) {
    uint m = as_uint(lo.x) & 0x7fffffffu;
    m = max_bits(m, lo.y); m = max_bits(m, lo.z);
    m = max_bits(m, hi.x); m = max_bits(m, hi.y); m = max_bits(m, hi.z);
    int e = (int)(m >> 23) - 126;
    e = e < -126 ? -126 : (e > 126 ? 126 : e);
    return as_float((uint)(127 - e) << 23);
}

/* Half the surface area of a box with its coordinates scaled by s. */
inline float scaled_half_area(float3 lo, float3 hi, float s) {
    float3 d = hi * s - lo * s;
    return d.x * d.y + d.y * d.z + d.z * d.x;
}

/* The query point a work-item k answers: order[k] where the points are answered
 * in the Morton order of their cells (POINT_ORDER=1: ray_order.cl's point_keys,
 * closest.cl, instance_closest.cl, winding.cl), else k. */
#ifndef POINT_ORDER
#define POINT_ORDER 0
#endif
inline int point_index(__global const int *order, int k) { return POINT_ORDER ? order[k] : k; }

#endif
