"""lbvh command line: render a scene, report its BVH, list the OpenCL devices.

``lbvh render SCENE -o image.png`` renders a scene; ``lbvh info SCENE`` prints
the build report of its BVH; ``lbvh devices`` lists the OpenCL devices;
``lbvh check`` runs the hard-case suite (:mod:`lbvh.check`) and exits 1 if a
case fails.

Errors (bad files, bad meshes, bad options, device problems) end the program
with a one-line message on stderr and exit status 2, not a traceback.
"""
from __future__ import annotations

import argparse
import json
import re
import sys
import time
from pathlib import Path

from .api import build
from .builders.options import BUILDERS
from .device import DeviceError, all_devices, describe, find_device, get_context, pocl_target
from .rendering.camera import DEFAULT_SIZE, MAX_SIDE, frame_bounds
from .rendering.image import image_kind
from .rendering.render import AO_SAMPLES, MODES, check_mode, render
from .rendering.scene import load_scene
from .verification import selftest
from .verification.check import add_arguments as add_check_arguments
from .verification.check import cmd_check as run_checks


class UsageError(ValueError):
    """A bad command line; reported in one line like every other error."""


class _Parser(argparse.ArgumentParser):
    # argparse prints the usage and exits on a bad option; we want the same
    # one-line error as for every other problem, and main() to return the status.
    def error(self, message: str) -> None:  # type: ignore[override]
        raise UsageError(f"{message} (see {self.prog} --help)")


SIZE_PATTERN = re.compile(r"^\s*(\d+)\s*[xX]\s*(\d+)\s*$")


def parse_size(text: str) -> tuple[int, int]:
    """``"WxH"`` -> ``(W, H)``; ``ValueError`` naming the text otherwise."""
    match = SIZE_PATTERN.match(text)
    if not match:
        raise ValueError(f"--size: {text!r} is not WIDTHxHEIGHT (e.g. 640x480)")
    width, height = int(match.group(1)), int(match.group(2))
    if not (1 <= width <= MAX_SIDE and 1 <= height <= MAX_SIDE):
        raise ValueError(f"--size: {text!r}: each side must be 1 to {MAX_SIDE} pixels")
    return width, height


def _add_build_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--builder", choices=BUILDERS, default="lbvh",
                   help="lbvh: device Karras build (default); sah: serial SAH reference")
    p.add_argument("--collapse", action="store_true",
                   help="lbvh only: merge subtrees into leaves where the SAH says so (device pass)")
    p.add_argument("--treelets", type=int, default=0, metavar="ROUNDS",
                   help="lbvh only: rounds of treelet restructuring (Karras & Aila 2013) for a "
                        "tree of lower SAH cost; 1-2 is typical (default 0)")
    p.add_argument("--keys", choices=["auto", "30", "63"], default="auto",
                   help="Morton key width (default: auto, chosen from the scene)")
    p.add_argument("--device", default=None,
                   help="OpenCL device name substring (default: $LBVH_DEVICE or PoCL's CPU)")


def _build(scene, args: argparse.Namespace):
    """The tree the build options ask for."""
    return build(scene.vertices, scene.faces, builder=args.builder, collapse=args.collapse,
                 treelet_rounds=args.treelets, key_bits=args.keys, device=args.device)


def cmd_info(args: argparse.Namespace) -> int:
    scene = load_scene(args.scene)
    bvh = _build(scene, args)
    if args.validate:
        bvh.validate()
    report = bvh.report()
    if args.json:
        print(json.dumps(report.as_dict(), indent=2))
    else:
        print(f"scene:       {args.scene}")
        print(report)
        if args.validate:
            print("validate:    ok")
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    # Everything the user typed is checked before the (slow) build starts.
    image_kind(args.output)
    folder = Path(args.output).resolve().parent
    if not folder.is_dir():
        raise ValueError(f"{args.output}: cannot write, the folder {folder} does not exist")
    check_mode(args.mode)
    size = parse_size(args.size) if args.size is not None else None
    if args.ao_samples < 1:
        raise ValueError(f"--ao-samples: {args.ao_samples}, expected at least 1")
    scene = load_scene(args.scene)
    if scene.camera is not None:
        camera = scene.camera.resized(*size) if size else scene.camera
    else:
        camera = frame_bounds(scene.vertices.min(axis=0), scene.vertices.max(axis=0),
                              *(size or DEFAULT_SIZE))
    start = time.perf_counter()
    bvh = _build(scene, args)
    build_seconds = time.perf_counter() - start
    result = render(bvh, camera, args.mode, ao_samples=args.ao_samples,
                    triangle_test=args.triangle_test)
    result.save(args.output)
    report = bvh.report()
    device_time = f" (device {report.device_seconds * 1e3:.1f} ms)" if report.device_seconds else ""
    hits = int((result.primary_hits.prim >= 0).sum())
    print(f"scene:     {args.scene}: {bvh.num_prims:,} triangles")
    print(f"device:    {bvh.ctx.name}")
    print(f"build:     {args.builder} in {build_seconds * 1e3:.1f} ms{device_time}, "
          f"depth {report.depth}")
    print(f"render:    {args.mode} {camera.width}x{camera.height} ({args.triangle_test}) in "
          f"{result.total_seconds * 1e3:.1f} ms, of which first calls (kernel compile) "
          f"{result.warmup_seconds * 1e3:.1f} ms")
    print(f"rays:      {result.rays:,} in {result.trace_seconds * 1e3:.1f} ms = "
          f"{result.rays_per_second / 1e6:.2f} Mrays/s")
    print(f"hits:      {hits:,} of {camera.num_pixels:,} pixels")
    print(f"overflow:  {result.overflow_count} stack overflows")
    if args.mode == "heatmap":
        cost = result.image[:, :, 0]
        print(f"cost:      nodes visited + triangles tested per ray: mean {cost.mean():.1f}, "
              f"max {cost.max():.0f}")
    print(f"wrote:     {args.output}")
    return 0


def cmd_devices(args: argparse.Namespace) -> int:
    default = find_device(args.device)
    failed = False
    for label, dev in all_devices():
        mark = "*" if dev.int_ptr == default.int_ptr else " "
        status = "not run (--no-self-test)"
        if not args.no_self_test and not selftest.enabled():
            status = f"skipped ({selftest.ENV_SELF_TEST}=0)"
        elif not args.no_self_test:
            key = selftest.device_key(dev)
            try:
                get_context(dev)
            except DeviceError as exc:
                if key not in selftest.results():
                    status = f"unusable: {exc}"
            if key in selftest.results():
                status = selftest.results()[key].summary()
            failed = failed or not status.startswith("passed")
        print(f"{mark} {label}  ({dev.version.strip()})")
        target = pocl_target.target_cpu(dev)
        if target and target[0] != target[1]:
            print(f"    compiled for: {target[1]} (PoCL's LLVM names this CPU {target[0]!r})")
        print(f"    self-test: {status}")
    print(f"default: {describe(default)}")
    return 1 if failed else 0


def cmd_check(args: argparse.Namespace) -> int:
    return run_checks(args)


def make_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="lbvh", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("info", help="build a scene's BVH and print the report")
    p.add_argument("scene", help="mesh file (OBJ, PLY, STL, GLB/GLTF, OFF) or scene description")
    _add_build_options(p)
    p.add_argument("--validate", action="store_true", help="also run the tree validator")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=cmd_info)
    p = sub.add_parser("render", help="render a scene to an image file")
    p.add_argument("scene", help="mesh file (OBJ, PLY, STL, GLB/GLTF, OFF) or scene description (.json)")
    p.add_argument("-o", "--output", required=True,
                   help="image file: .png/.jpg (8-bit picture) or .exr/.tif (float values)")
    p.add_argument("--mode", default="normals", choices=MODES,
                   help="what to draw (default: normals)")
    p.add_argument("--size", default=None, metavar="WxH",
                   help="image size (default: the scene's camera, else 640x480)")
    p.add_argument("--ao-samples", type=int, default=AO_SAMPLES, metavar="N",
                   help=f"ambient occlusion rays per pixel (default {AO_SAMPLES})")
    p.add_argument("--triangle-test", default="watertight", choices=["watertight", "moller"],
                   help="ray/triangle test (default: watertight)")
    _add_build_options(p)
    p.set_defaults(func=cmd_render)
    p = sub.add_parser("check", help="run the hard-case suite with every builder and report")
    add_check_arguments(p)
    p.set_defaults(func=cmd_check)
    p = sub.add_parser("devices", help="list the OpenCL devices and their self-test results")
    p.add_argument("--no-self-test", action="store_true",
                   help="list only: do not run each device's known-answer test")
    p.add_argument("--device", default=None)
    p.set_defaults(func=cmd_devices)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = make_parser()
    try:
        args = parser.parse_args(argv)
        return args.func(args)
    except KeyboardInterrupt:
        print("lbvh: interrupted", file=sys.stderr)
        return 130
    except MemoryError:
        print("lbvh: error: out of memory (try a smaller scene or --size)", file=sys.stderr)
        return 2
    except (ValueError, OSError, DeviceError) as exc:
        message = str(exc).removeprefix("lbvh: ")
        # A device error keeps its further lines (the devices available, a build log).
        if not isinstance(exc, DeviceError):
            message = message.splitlines()[0] if message else type(exc).__name__
        print(f"lbvh: error: {message}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
