"""lbvh: bounding volume hierarchies over triangle meshes, built by OpenCL kernels.

Entry points:
    lbvh.build(vertices, faces, key_bits="auto", device=None) -> lbvh.BVH
    lbvh.load(path) -> lbvh.BVH
The tree layout is documented in docs/layout.md.
"""
from .build import build
from .bvh import BVH, load
from .device import DeviceError, find_device, get_context
from .layout import NODE_DTYPE
from .validate import BVHValidationError

__all__ = ["build", "load", "BVH", "NODE_DTYPE", "BVHValidationError", "DeviceError",
           "find_device", "get_context"]
__version__ = "0.1.0"
