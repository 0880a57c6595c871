"""Regenerate the reference images of tests/rendering/test_render.py with the float64 oracle.

    python tests/rendering/data/make_references.py

Each reference is a shipped scene's saved view, rendered small with
:func:`lbvh.rendering.render.render_reference` (rays against every triangle in float64,
lbvh.oracle), never with the traversal kernel, and stored as a float EXR.
"""
from __future__ import annotations

import sys
from pathlib import Path

DATA = Path(__file__).resolve().parent
REPO = DATA.parents[2]

#: (file under tests/data, scene under scenes/, mode, width, height)
REFERENCES = [
    ("teapot_depth_64x48.exr", "teapot.json", "depth", 64, 48),
    ("teapot_normals_64x48.exr", "teapot.json", "normals", 64, 48),
]


def reference_image(scene_file: str, mode: str, width: int, height: int):
    """The oracle's float image ``(H, W, C)`` of a shipped scene's camera at ``width x height``."""
    from lbvh.rendering.render import render_reference
    from lbvh.files import load_scene

    scene = load_scene(REPO / "scenes" / scene_file)
    camera = scene.camera.resized(width, height)
    return render_reference(scene.vertices, scene.faces, camera, mode)


def main() -> int:
    sys.path.insert(0, str(REPO))
    from lbvh.rendering.image import write_image

    for name, scene_file, mode, width, height in REFERENCES:
        write_image(DATA / name, reference_image(scene_file, mode, width, height))
        print(f"wrote {DATA / name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
