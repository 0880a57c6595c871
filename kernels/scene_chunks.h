/* Where a scene's kernels find each instance's tree (kernels/instances.cl,
 * instance_hits.cl, instance_closest.cl; lbvh/queries/instances.py). */
#ifndef LBVH_SCENE_CHUNKS_H
#define LBVH_SCENE_CHUNKS_H

/* The meshes' trees sit in up to four node buffers ("chunks"), each within the
 * device's largest allocation (a mesh in parts passes it; lbvh/scene.py):
 * inst_root[i] holds instance i's chunk in its bits ROOT_BITS.. and the root
 * node within that chunk below them. */
#define ROOT_BITS 28

inline __global const float4 *chunk_nodes(int r, __global const float4 *n0,
                                          __global const float4 *n1, __global const float4 *n2,
                                          __global const float4 *n3) {
    const int c = r >> ROOT_BITS;
    return c == 0 ? n0 : (c == 1 ? n1 : (c == 2 ? n2 : n3));
}

inline int chunk_root(int r) { return r & ((1 << ROOT_BITS) - 1); }

#endif
