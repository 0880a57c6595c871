"""Command line: ``lbvh info SCENE`` prints the build report of a scene's BVH.

Errors (bad files, bad meshes, bad options, device problems) end the program
with a one-line message and a non-zero exit status, not a traceback.
"""
from __future__ import annotations

import argparse
import json
import sys

from .build import BUILDERS, build
from .device import DeviceError, describe, find_device


def _add_build_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--builder", choices=BUILDERS, default="lbvh",
                   help="lbvh: device Karras build (default); sah: serial SAH reference")
    p.add_argument("--keys", choices=["auto", "30", "63"], default="auto",
                   help="Morton key width (default: auto, chosen from the scene)")
    p.add_argument("--device", default=None,
                   help="OpenCL device name substring (default: $LBVH_DEVICE or PoCL's CPU)")


def cmd_info(args: argparse.Namespace) -> int:
    from .scene import load_scene

    scene = load_scene(args.scene)
    bvh = build(scene.vertices, scene.faces, builder=args.builder,
                          key_bits=args.keys, device=args.device)
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


def cmd_devices(args: argparse.Namespace) -> int:
    from .device import _all_devices

    default = find_device(args.device)
    for label, dev in _all_devices():
        mark = "*" if dev.int_ptr == default.int_ptr else " "
        print(f"{mark} {label}  ({dev.version.strip()})")
    print(f"default: {describe(default)}")
    return 0


def make_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="lbvh", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("info", help="build a scene's BVH and print the report")
    p.add_argument("scene", help="mesh file (OBJ, PLY, STL, GLB/GLTF, OFF) or scene description")
    _add_build_options(p)
    p.add_argument("--validate", action="store_true", help="also run the tree validator")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=cmd_info)
    p = sub.add_parser("devices", help="list the OpenCL devices")
    p.add_argument("--device", default=None)
    p.set_defaults(func=cmd_devices)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = make_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, OSError, DeviceError) as exc:
        print(f"lbvh: error: {exc}".splitlines()[0] if not isinstance(exc, DeviceError)
              else f"lbvh: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
