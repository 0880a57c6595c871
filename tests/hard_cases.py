"""The named generators of hard scenes now live in the package (``lbvh.hard_cases``),
so that ``lbvh check`` works from an installed wheel; this module re-exports them
for the tests and the bench."""
from lbvh.hard_cases import (CASES, ISSUE_CASE, Case, axis_rays_at, cube_mesh,  # noqa: F401
                             grid_mesh, make, make_case, rays_at)
