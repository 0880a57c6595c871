"""lbvh: bounding volume hierarchies over triangle meshes, built by OpenCL kernels.

Entry points:
    lbvh.build(vertices, faces, builder="lbvh"|"sah", key_bits="auto", device=None) -> lbvh.BVH
    bvh.intersect(origins, directions) / bvh.occluded(...)  (ray queries)
    lbvh.load(path) -> lbvh.BVH
    lbvh.render(bvh, camera, mode)
The tree layout is documented in docs/layout.md.
"""
from . import traverse
from .build import build
from .bvh import BVH, load
from .camera import Camera, frame_bounds
from .collapse import collapse_leaves
from .device import DeviceError, find_device, get_context
from .layout import NODE_DTYPE
from .quality import sah_cost, tree_quality
from .render import render
from .scene import load_scene
from .traverse import Hits
from .validate import BVHValidationError

__all__ = ["build", "load", "BVH", "NODE_DTYPE", "BVHValidationError", "DeviceError",
           "find_device", "get_context", "collapse_leaves", "sah_cost", "tree_quality",
           "Camera", "frame_bounds", "render", "load_scene", "Hits", "traverse"]
__version__ = "0.1.0"
