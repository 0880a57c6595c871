"""lbvh: bounding volume hierarchies over triangle meshes, built by OpenCL kernels.

Entry points:
    lbvh.build(vertices, faces, builder="lbvh"|"sah"|"median"|"midpoint"|"sbvh", device=None,
               collapse=False, options=None | lbvh.LBVHOptions | lbvh.SAHOptions
               | lbvh.SplitOptions, **fields) -> lbvh.BVH
    bvh.intersect(origins, directions) / bvh.occluded(...)  (ray queries) -> lbvh.Hits
    bvh.count_hits(origins, directions) -> int32, bvh.all_hits(...) -> lbvh.AllHits
    bvh.closest_points(points, max_distance=inf)  (point queries) -> lbvh.Closest
    bvh.contains(points), bvh.winding_numbers(points), bvh.signed_distance(points)
    bvh.overlapping(lower, upper)  (box queries) -> lbvh.Overlaps
    lbvh.load(path) -> lbvh.BVH
    lbvh.render(bvh, lbvh.Camera(...), mode)
    lbvh.sah_cost(bvh), lbvh.tree_quality(bvh)  (the tree's quality)
Devices are chosen by name (``device=`` or ``$LBVH_DEVICE``, :mod:`lbvh.device`).
The tree layout is documented in docs/pages/layout.md.

The package, in layers (a folder or module imports only from layers above it in this
list; tests/test_layers.py checks it folder by folder):

=======================  ============================================================
``layout``, ``mesh``,    the node record; mesh checks; the version; progress bars;
``version``,             contexts, programs, device memory, launches, the radix sort
``progress``, ``device/``
``data/``, ``report``    the shipped meshes and views; the build report
``camera``,              cameras; a tree's measures (cost model, validator, quality,
``metrics/``, ``tree``   error bound); the values builders take and return
``files``, ``builders/`` reading mesh and scene files; the options, the stages, the
                         optimisers, the device pipeline, the host builders
``queries/``             query data, rays, wide records, ray order, the traversal,
                         every hit, closest points, winding numbers, box overlaps
``bvh``, ``scene``       the public :class:`BVH`, facade over mesh, tree and query
                         data; the :class:`Scene` of instances
``api``, ``dask``        ``build``, ``load``, ``collapse_leaves``; dask arrays
``verification/``,       what runs builds to check them: the oracle, hard cases,
``trimesh``              ``lbvh check``, the self-test, the kernel variants; trimesh
``rendering/``           shading, images
``cli``                  the ``lbvh`` command
=======================  ============================================================
"""
from . import data, layout
from .api import build, build_parts, build_scene, load
from .builders.options import (CollapseOptions, LBVHOptions, PLOCOptions, SAHOptions,
                               SBVHOptions, SplitOptions)
from .builders.ray_sampled import RaySample
from .bvh import BVH
from .scene import Scene
from .device import CONTEXT_CHECKS, DeviceError
from .queries.all_hits import AllHits
from .queries.closest import Closest
from .queries.options import QueryOptions
from .queries.overlap import Overlaps
from .queries.traverse import Hits
from .camera import Camera
from .rendering.render import render
from .files import load_scene
from .metrics.quality import sah_cost, tree_quality
from .metrics.validate import BVHValidationError
from .verification.selftest import require as _self_test
from .version import __version__

# Every context get_context hands out has passed the self-test (the device
# layer knows nothing of builds; the check is registered here, above them all).
if _self_test not in CONTEXT_CHECKS:
    CONTEXT_CHECKS.append(_self_test)

__all__ = ["build", "build_parts", "build_scene", "load", "BVH", "Scene", "Hits", "AllHits", "Closest", "Overlaps", "LBVHOptions",
           "SAHOptions", "SplitOptions", "SBVHOptions", "PLOCOptions", "CollapseOptions", "QueryOptions", "RaySample",
           "render", "Camera", "load_scene", "sah_cost", "tree_quality", "BVHValidationError",
           "DeviceError", "data", "layout", "__version__"]
