"""lbvh command line: render a scene, report its BVH, list the OpenCL devices.

``lbvh render SCENE -o image.png`` renders a scene; ``lbvh info SCENE`` prints
the build report of its BVH; ``lbvh devices`` lists the OpenCL devices;
``lbvh query KIND SCENE INPUT`` answers a point query (``closest``,
``signed-distance``, ``contains``) or a ray query (``closest-hit``, ``any-hit``,
``count-hits``, ``all-hits``)
for every point or ray of a file (through the instances of a file that places
several meshes, naming the instance of each answer); ``lbvh check`` runs the
hard-case suite (:mod:`lbvh.verification.check`) and exits 1 if a case fails;
``lbvh --version`` prints the version.

Where a command takes a scene it also takes the name of a mesh that ships with
the package (``lbvh render teapot -o teapot.png``, :mod:`lbvh.data`); a file of
that name wins. ``lbvh render`` takes a camera (``--eye``, ``--target``,
``--up``, ``--fov``, or ``--view NAME`` from a views file) and prints which it
used on its ``camera:`` line.

Errors (bad files, bad meshes, bad options, device problems) end the program
with a one-line message on stderr and exit status 2, not a traceback.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import re
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from .api import build
from .builders.options import BUILDERS
from .builders.restructure import TREELET_LEAVES, TREELET_MIN_LEAVES
from .device import DeviceError, all_devices, describe, find_device, get_context, pocl_target
from .data import MESHES
from .mesh import MissingFileError
from .camera import (DEFAULT_FOV, DEFAULT_SIZE, MAX_SIDE, Camera, frame_bounds, view_camera,
                               views_name)
from .rendering.image import image_kind
from .rendering.render import AO_SAMPLES, MODES, check_mode, render
from .files import SceneFile, find_scene, load_scene
from .scene import Scene
from .verification import selftest
from .verification.check import add_arguments as add_check_arguments
from .verification.check import cmd_check as run_checks
from .version import __version__


class UsageError(ValueError):
    """A bad command line; reported in one line like every other error."""


class _Parser(argparse.ArgumentParser):
    # argparse prints the usage and exits on a bad option; we want the same
    # one-line error as for every other problem, and main() to return the status.
    def error(self, message: str) -> None:  # type: ignore[override]
        vector = re.match(r"argument (--eye|--target|--up): expected one argument", message)
        if vector:   # argparse takes "-1,2,3" for an option
            message += f" (write {vector.group(1)}=-1,2,3 for one that starts with a minus)"
        raise UsageError(f"{message} (see {self.prog} --help)")


SIZE_PATTERN = re.compile(r"^\s*(\d+)\s*[xX]\s*(\d+)\s*$")


def parse_size(text: str, option: str = "--size") -> tuple[int, int]:
    """``"WxH"`` -> ``(W, H)``; ``ValueError`` naming the option and the text otherwise."""
    match = SIZE_PATTERN.match(text)
    if not match:
        raise ValueError(f"{option}: {text!r} is not WIDTHxHEIGHT (e.g. 640x480)")
    width, height = int(match.group(1)), int(match.group(2))
    if not (1 <= width <= MAX_SIDE and 1 <= height <= MAX_SIDE):
        raise ValueError(f"{option}: {text!r}: each side must be 1 to {MAX_SIDE} pixels")
    return width, height


VECTOR_SEPARATOR = re.compile(r"[,\s]+")


def parse_vector(option: str, text: str) -> tuple[float, float, float]:
    """``"X,Y,Z"`` (commas or spaces) -> three finite floats; ``ValueError`` naming
    ``option`` and the text otherwise."""
    parts = [part for part in VECTOR_SEPARATOR.split(text.strip()) if part]
    try:
        values = tuple(float(part) for part in parts)
    except ValueError:
        values = ()
    if len(values) != 3:
        raise ValueError(f"{option}: {text!r} is not X,Y,Z (three numbers, e.g. {option}=0,1,5)")
    if not all(math.isfinite(value) for value in values):
        raise ValueError(f"{option}: {text!r} has a NaN or infinite number")
    return values  # type: ignore[return-value]


def choose_camera(args: argparse.Namespace, scene: SceneFile,
                  size: tuple[int, int] | None) -> tuple[Camera, str]:
    """The camera ``lbvh render`` uses, and where it comes from (its ``camera:`` line).

    The base camera is ``--view`` (from ``--views`` or the shipped views file),
    else ``--eye`` with ``--target`` (up ``0,1,0`` and fov 45 unless given), else the
    scene file's camera, else one framed from the scene's bounds (with ``--fov``);
    then each of ``--eye``, ``--target``, ``--up``, ``--fov`` given replaces that
    part of it. ``--size`` gives the image size in every case.
    """
    given: dict[str, Any] = {name: parse_vector(f"--{name}", getattr(args, name))
                             for name in ("eye", "target", "up") if getattr(args, name) is not None}
    if args.fov is not None:
        if not 0.0 < args.fov < 180.0:   # NaN fails too
            raise ValueError(f"--fov: {args.fov!r} degrees, expected more than 0 and less than 180")
        given["fov"] = args.fov
    if args.views is not None and args.view is None:
        raise ValueError(f"--views {args.views}: give --view NAME, the view to use from it")
    if args.view is not None:
        camera = view_camera(args.view, args.views, size)
        source = f"--view {args.view} from {views_name(args.views)}"
    elif "eye" in given and "target" in given:
        source = "from " + "/".join(f"--{name}" for name in given)
        camera = Camera(given.pop("eye"), given.pop("target"), given.pop("up", (0.0, 1.0, 0.0)),
                        given.pop("fov", DEFAULT_FOV), *(size or DEFAULT_SIZE))
    elif scene.camera is not None:
        camera = scene.camera.resized(*size) if size else scene.camera
        source = "from the scene file"
    else:
        camera = frame_bounds(scene.vertices.min(axis=0), scene.vertices.max(axis=0),
                              *(size or DEFAULT_SIZE), fov=given.get("fov", DEFAULT_FOV))
        source = "framed automatically"
    fields = {"eye": "position", "target": "target", "up": "up", "fov": "fov"}
    if given:
        camera = dataclasses.replace(camera, **{fields[name]: value for name, value in given.items()})
        source += ", with " + ", ".join(f"--{name}" for name in given)
    return camera, source


def describe_camera(camera: Camera) -> str:
    """The camera as the options that give it again."""
    def vector(values: Any) -> str:
        return ",".join(f"{float(value):.6g}" for value in values)
    return (f"--eye={vector(camera.position)} --target={vector(camera.target)} "
            f"--up={vector(camera.up)} --fov={camera.fov:.6g} --size={camera.width}x{camera.height}")


def _add_build_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--builder", choices=BUILDERS, default="lbvh",
                   help="lbvh: device Karras build (default); sah: serial SAH reference")
    p.add_argument("--collapse", action="store_true",
                   help="lbvh only: merge subtrees into leaves where the SAH says so (device pass)")
    p.add_argument("--treelets", type=int, default=0, metavar="ROUNDS",
                   help="lbvh only: rounds of treelet restructuring (Karras & Aila 2013) for a "
                        "tree of lower SAH cost; 1-2 is typical (default 0)")
    p.add_argument("--treelet-leaves", type=int, default=TREELET_LEAVES, metavar="N",
                   help="lbvh only: leaves per treelet, 3-7; 5 costs about a third of 7 per "
                        f"round (default {TREELET_LEAVES})")
    p.add_argument("--treelet-min-leaves", type=int, default=TREELET_MIN_LEAVES, metavar="N",
                   help="lbvh only: after the first round, restructure only subtrees of at least "
                        "N leaves, 2N in the third round...; 0: every subtree in every round "
                        f"(default {TREELET_MIN_LEAVES})")
    p.add_argument("--keys", choices=["auto", "30", "63"], default="auto",
                   help="Morton key width (default: auto, chosen from the scene)")
    p.add_argument("--device", default=None,
                   help="OpenCL device name substring (default: $LBVH_DEVICE or PoCL's CPU)")


def _first_use_notice(device_name: str | None) -> None:
    """On stderr, before the first build on a device: the wait that follows is the
    one-time self-test and compile (:func:`lbvh.verification.selftest.pending`)."""
    try:
        device = find_device(device_name)
    except (DeviceError, ValueError):
        return   # the build names the problem
    if selftest.pending(device):
        print(f"lbvh: first use of {describe(device)}: compiling the kernels and running the "
              "self-test (once; later runs reuse the answer)", file=sys.stderr, flush=True)


def _build(scene, args: argparse.Namespace, **extra: Any):
    """The tree the build options ask for; for a file that places several meshes, an
    :class:`lbvh.Scene` of its instances (each mesh built once with those options).
    ``extra``: more options of :func:`lbvh.build`."""
    options = dict(builder=args.builder, collapse=args.collapse, treelet_rounds=args.treelets,
                   treelet_leaves=args.treelet_leaves, treelet_min_leaves=args.treelet_min_leaves,
                   key_bits=args.keys, device=args.device, **extra)
    _first_use_notice(args.device)
    source = scene.extras.get("instances")
    if source is not None:
        return build(source, **options)
    return build(scene.vertices, scene.faces, **options)


def _scene_name(text: str) -> str:
    """The scene as typed, with the file read when it is a shipped mesh's name."""
    file = find_scene(text)
    return text if str(file) == text else f"{text} (shipped with lbvh: {file})"


def cmd_info(args: argparse.Namespace) -> int:
    scene = load_scene(args.scene)
    bvh = _build(scene, args)
    if isinstance(bvh, Scene):
        return _info_scene(args, bvh)
    if args.validate:
        bvh.validate()
    report = bvh.report()
    if args.json:
        print(json.dumps(report.as_dict(), indent=2))
    else:
        print(f"scene:       {_scene_name(args.scene)}")
        print(report)
        if args.validate:
            print("validate:    ok")
    return 0


def _info_scene(args: argparse.Namespace, scene) -> int:
    """``lbvh info`` of a file placing several meshes: its instances and meshes."""
    if args.validate:
        for m in scene.meshes:
            m.validate()
        scene.top.validate()
    meshes = [{"triangles": m.mesh.num_prims, "nodes": m.tree.num_nodes, "builder": m.tree.builder,
               "depth": m.report().depth} for m in scene.meshes]
    summary = {"scene": _scene_name(args.scene), "instances": scene.num_instances,
               "meshes": meshes, "triangles_in_world": scene.num_triangles,
               "instance_names": scene.names, "instance_mesh": scene.mesh_of.tolist()}
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    print(f"scene:       {summary['scene']}")
    print(f"instances:   {scene.num_instances} of {len(meshes)} meshes, "
          f"{scene.num_triangles:,} triangles in world space")
    for k, m in enumerate(meshes):
        placed = [n for n, i in zip(scene.names, scene.mesh_of) if i == k]
        print(f"mesh {k}:      {m['triangles']:,} triangles, {m['nodes']:,} nodes, depth "
              f"{m['depth']} ({m['builder']}), placed as {', '.join(placed)}")
    if args.validate:
        print("validate:    ok")
    return 0


def _read_rows(path: str, what: str) -> np.ndarray:
    """A 2-d array from a ``.npy`` file (or ``.txt``/``.csv``: numbers in rows)."""
    file = Path(path)
    if not file.is_file():
        raise MissingFileError(f"{path}: no such file")
    try:
        if file.suffix.lower() == ".npy":
            rows = np.load(file, allow_pickle=False)
        else:
            rows = np.loadtxt(file, delimiter="," if file.suffix.lower() == ".csv" else None,
                              ndmin=2)
    except (ValueError, OSError) as exc:
        raise ValueError(f"{path}: cannot read {what} ({exc})") from None
    return rows


def _read_points(path: str) -> np.ndarray:
    """``(N, 3)`` points from a ``.npy`` file (or ``.txt``/``.csv``: three numbers a row)."""
    return _read_rows(path, "points")


def _read_rays(path: str) -> tuple[np.ndarray, np.ndarray]:
    """Origins and directions from an ``(N, 6)`` array: ``ox oy oz dx dy dz`` a row."""
    rows = _read_rows(path, "rays")
    if rows.ndim != 2 or rows.shape[1] != 6:
        raise ValueError(f"{path}: rays of shape {rows.shape}, expected (N, 6): "
                         "ox oy oz dx dy dz a row")
    return rows[:, :3], rows[:, 3:]


#: ``lbvh query`` kinds: what each reads, and the arrays it writes for one mesh (a file of
#: placed meshes adds ``instance``).
QUERY_KINDS = {
    "closest": ("points", "distance, points, prim, u, v, found"),
    "signed-distance": ("points", "signed_distance"),
    "contains": ("points", "contains, winding"),
    "closest-hit": ("rays", "t, prim, u, v, hit"),
    "any-hit": ("rays", "hit"),
    "count-hits": ("rays", "counts"),
    "all-hits": ("rays", "offsets, t, prim, u, v, total"),
}

#: What ``-o`` writes, by the file's suffix.
OUTPUT_SUFFIXES = (".npz", ".csv", ".txt")


def plural(count: int, noun: str) -> str:
    """``"1 ray"``, ``"2 rays"``, ``"1,024 points"``."""
    return f"{count:,} {noun}{'' if count == 1 else 's'}"


def rate(count: int, seconds: float, noun: str) -> str:
    """``count`` per second in the unit that reads best: ``"12.3 M rays/s"``,
    ``"456 k points/s"``, ``"7 rays/s"``."""
    per = count / max(seconds, 1e-9)
    for scale, unit in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if per >= scale:
            return f"{per / scale:.3g} {unit} {noun}s/s"
    return f"{per:.3g} {noun}s/s"


def _stats(name: str, values: np.ndarray) -> dict[str, float | None]:
    return {f"{name}_min": float(values.min()) if len(values) else None,
            f"{name}_median": float(np.median(values)) if len(values) else None,
            f"{name}_max": float(values.max()) if len(values) else None}


def _run_query(bvh: Any, kind: str, data: Any, args: argparse.Namespace
               ) -> tuple[dict[str, np.ndarray], dict[str, Any], list[str]]:
    """The query's arrays (for OUT.npz), its summary fields and its summary lines. A
    file of placed meshes is asked through its :class:`lbvh.Scene` (the instance of each
    answer in an ``instance`` array; what a scene refuses is refused with the scene's
    message)."""
    scene = isinstance(bvh, Scene)
    if kind == "closest":
        if scene:
            got = bvh.closest_points(data, max_distance=args.max_distance)
            arrays = {"distance": got.distance, "points": got.points, "prim": got.prim,
                      "u": got.u, "v": got.v, "instance": got.instance, "found": got.found}
        else:
            got = bvh.closest_points(data, max_distance=args.max_distance)
            arrays = {"distance": got.distance, "points": got.points, "prim": got.prim,
                      "u": got.u, "v": got.v, "found": got.found}
        found = arrays["distance"][arrays["found"]]
        summary = {"found": int(arrays["found"].sum()), **_stats("distance", found),
                   **({} if scene else {"overflow": got.overflow_count})}
        lines = [f"found:     {summary['found']:,} with a triangle within {args.max_distance:g}"]
        if len(found):
            lines.append(f"distance:  min {summary['distance_min']:.6g}, median "
                         f"{summary['distance_median']:.6g}, max {summary['distance_max']:.6g}")
        return arrays, summary, lines
    if kind == "signed-distance":
        sd = bvh.signed_distance(data)
        summary = {"inside": int((sd < 0).sum()), **_stats("signed_distance", sd)}
        return ({"signed_distance": sd}, summary,
                [f"inside:    {summary['inside']:,} (negative distance)",
                 f"distance:  min {summary['signed_distance_min']:.6g}, median "
                 f"{summary['signed_distance_median']:.6g}, max "
                 f"{summary['signed_distance_max']:.6g}"] if len(sd) else [])
    if kind == "contains":
        w = bvh.winding_numbers(data)
        inside = w > 0.5
        summary = {"inside": int(inside.sum())}
        return ({"contains": inside, "winding": w}, summary,
                [f"inside:    {summary['inside']:,} (winding number > 1/2)"])
    origins, directions = data
    if kind in ("closest-hit", "any-hit"):
        got = (bvh.intersect(origins, directions) if kind == "closest-hit"
               else bvh.occluded(origins, directions, return_hits=True))
        hit = got.mask
        arrays = ({"t": got.t, "prim": got.prim, **({"instance": got.instance} if scene else {}),
                   "u": got.u, "v": got.v, "hit": hit} if kind == "closest-hit" else {"hit": hit})
        summary = {"rays_hit": int(hit.sum()), **_stats("t", got.t[hit]),
                   "overflow": int(got.overflow_count)}
        lines = [f"hit:       {plural(summary['rays_hit'], 'ray')} of {len(hit):,}"]
        if kind == "closest-hit" and hit.any():
            lines.append(f"t:         min {summary['t_min']:.6g}, median {summary['t_median']:.6g}, "
                         f"max {summary['t_max']:.6g}")
        if kind == "any-hit":
            summary = {k: summary[k] for k in ("rays_hit", "overflow")}
        return arrays, summary, lines
    if kind == "count-hits" and args.signed:
        if scene:
            raise ValueError("--signed: a file of placed meshes is counted unsigned only; "
                             "count one mesh")
        counts = bvh.count_hits(origins, directions, signed=True)
        summary = {"signed_sum": int(counts.sum()), "rays_positive": int((counts > 0).sum()),
                   "rays_negative": int((counts < 0).sum())}
        return ({"counts": counts}, summary,
                [f"signed:    {summary['signed_sum']:,} in all (+1 leaving by a front, -1 "
                 f"entering); {plural(summary['rays_positive'], 'ray')} above 0, "
                 f"{summary['rays_negative']:,} below"])
    if kind == "count-hits":
        counts = bvh.count_hits(origins, directions)
        summary = {"hits": int(counts.sum()), "rays_hit": int((counts > 0).sum()),
                   "most_hits": int(counts.max()) if len(counts) else 0}
        return ({"counts": counts}, summary,
                [f"hits:      {summary['hits']:,} in all; {plural(summary['rays_hit'], 'ray')} "
                 f"hit, at most {plural(summary['most_hits'], 'time')}"])
    got = bvh.all_hits(origins, directions, max_hits=args.max_hits)
    summary = {"hits": len(got.t), "rays_hit": int((got.total > 0).sum()),
               "truncated": int(got.truncated.sum())}
    lines = [f"hits:      {summary['hits']:,} kept; {plural(summary['rays_hit'], 'ray')} hit"
             + (f", {summary['truncated']:,} past --max-hits" if summary["truncated"] else "")]
    arrays = {"offsets": got.offsets, "t": got.t, "prim": got.prim,
              **({"instance": got.instance} if scene else {}), "u": got.u, "v": got.v,
              "total": got.total}
    if scene:
        summary["instances_hit"] = int(len(np.unique(got.instance)))
        lines.append(f"instances: {summary['instances_hit']:,} of {bvh.num_instances:,} hit")
    return arrays, summary, lines


def answer_table(arrays: dict[str, np.ndarray]) -> tuple[list[str], list[np.ndarray]]:
    """The answers as columns of one table: a row per point or ray (an ``(N, 3)`` array
    in three columns, ``name_x``, ``name_y``, ``name_z``; booleans as 0 and 1), or for
    every hit (``all-hits``: its ray's index, then the hit's fields; ``offsets`` and
    ``total`` are what the rows say)."""
    if "offsets" in arrays:
        offsets = arrays["offsets"]
        ray = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
        arrays = {"ray": ray, **{k: a for k, a in arrays.items() if k not in ("offsets", "total")}}
    names, columns = [], []
    for name, a in arrays.items():
        a = a.astype(np.int64) if a.dtype == bool else a
        if a.ndim == 2:
            names += [f"{name}_{axis}" for axis in "xyz"[:a.shape[1]]]
            columns += [a[:, k] for k in range(a.shape[1])]
        else:
            names.append(name)
            columns.append(a)
    return names, columns


def write_answers(path: str, arrays: dict[str, np.ndarray]) -> None:
    """Write the answers where ``path``'s suffix says: ``.npz`` (every array by name,
    ``numpy.load`` reads it), ``.csv`` (a header row, comma-separated) or ``.txt`` (a
    ``#`` header, space-separated): :func:`answer_table`'s rows, floats to the digits
    that read back the same float32 (9 significant)."""
    suffix = Path(path).suffix.lower()
    if suffix == ".npz":
        with open(path, "wb") as out:   # the name as given, no suffix added
            np.savez(out, **arrays)
        return
    names, columns = answer_table(arrays)
    fmt = ["%.9g" if c.dtype.kind == "f" else "%d" for c in columns]
    table = np.column_stack([c.astype(np.float64) for c in columns])   # int64 up to 2^53 exact
    if suffix == ".csv":
        np.savetxt(path, table, fmt=fmt, delimiter=",", header=",".join(names), comments="")
    else:
        np.savetxt(path, table, fmt=fmt, delimiter=" ", header=" ".join(names))


def cmd_query(args: argparse.Namespace) -> int:
    """``lbvh query KIND SCENE INPUT [-o OUT]``: a point or ray query on the mesh, or
    through the instances of a file of placed meshes; a summary on stdout (or JSON),
    every answer in OUT (.npz, .csv or .txt: :func:`write_answers`)."""
    if args.output is not None:
        folder = Path(args.output).resolve().parent
        if not folder.is_dir():
            raise ValueError(f"{args.output}: cannot write, the folder {folder} does not exist")
        suffix = Path(args.output).suffix.lower()
        if suffix not in OUTPUT_SUFFIXES:
            raise ValueError(f"{args.output}: no output format for {suffix or 'a name without a suffix'}"
                             f"; name the file {', '.join(OUTPUT_SUFFIXES[:-1])} or "
                             f"{OUTPUT_SUFFIXES[-1]}")
    if args.signed and args.kind != "count-hits":
        raise ValueError(f"--signed: only for count-hits, not {args.kind}")
    reads = QUERY_KINDS[args.kind][0]
    data = _read_points(args.input) if reads == "points" else _read_rays(args.input)
    scene = load_scene(args.scene)
    bvh = _build(scene, args)   # a file of placed meshes: an lbvh.Scene of its instances
    start = time.perf_counter()
    arrays, fields, lines = _run_query(bvh, args.kind, data, args)
    seconds = time.perf_counter() - start
    count = len(data) if reads == "points" else len(data[0])
    if args.output is not None:
        write_answers(args.output, arrays)
    summary = {"scene": _scene_name(args.scene), "query": args.kind,
               **({"instances": bvh.num_instances} if isinstance(bvh, Scene) else {}),
               reads: count, "seconds": seconds, **fields, "output": args.output}
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        placed = (f": {bvh.num_instances} instances of {len(bvh.meshes)} meshes"
                  if isinstance(bvh, Scene) else "")
        print(f"scene:     {summary['scene']}{placed}")
        print(f"{reads + ':':<10} {count:,} from {args.input}")
        for line in lines:
            print(line)
        print(f"query:     {seconds * 1e3:.1f} ms ({rate(count, seconds, reads[:-1])})")
        if args.output is not None:
            print(f"wrote:     {args.output} ({', '.join(arrays)})")
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
    extra = {}
    if args.ray_sample is not None:
        if args.builder != "sah":
            raise ValueError(f"--ray-sample: for --builder sah only (not {args.builder})")
        sample_size = parse_size(args.ray_sample, "--ray-sample")
    scene = load_scene(args.scene)
    camera, camera_source = choose_camera(args, scene, size)
    if args.ray_sample is not None:
        extra["rays"] = camera.resized(*sample_size).rays()
    start = time.perf_counter()
    bvh = _build(scene, args, **extra)
    build_seconds = time.perf_counter() - start
    result = render(bvh, camera, args.mode, ao_samples=args.ao_samples,
                    triangle_test=args.triangle_test, order=args.order)
    result.save(args.output)
    hits = int((result.primary_hits.prim >= 0).sum())
    if isinstance(bvh, Scene):
        print(f"scene:     {_scene_name(args.scene)}: {bvh.num_instances} instances of "
              f"{len(bvh.meshes)} meshes, {bvh.num_triangles:,} triangles in world space")
        built = f"{len(bvh.meshes)} meshes and the top level"
    else:
        report = bvh.report()
        device_time = f" (device {report.device_seconds * 1e3:.1f} ms)" if report.device_seconds else ""
        print(f"scene:     {_scene_name(args.scene)}: {bvh.mesh.num_prims:,} triangles")
        built = f"depth {report.depth}"
    print(f"camera:    {camera_source}: {describe_camera(camera)}")
    print(f"device:    {bvh.ctx.name}")
    sampled = "" if args.ray_sample is None else f" (splits by {args.ray_sample} camera rays)"
    print(f"build:     {args.builder}{sampled} in {build_seconds * 1e3:.1f} ms"
          f"{device_time if not isinstance(bvh, Scene) else ''}, {built}")
    order = "" if args.order == "ordered" else f", {args.order} order"
    print(f"render:    {args.mode} {camera.width}x{camera.height} ({args.triangle_test}{order}) in "
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


SCENE_HELP = ("mesh file (OBJ, PLY, STL, GLB/GLTF, OFF), scene description (.json), or the name "
              f"of a mesh that ships with lbvh ({', '.join(MESHES)}; a file of that name wins)")


def _add_camera_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group(
        "camera", "Default: the scene file's camera, else one framed from the scene's bounds. "
        "--view takes a saved view; --eye with --target places a camera; each of --eye, --target, "
        "--up, --fov also changes that part of the camera it is given with. The output's camera: "
        "line says which was used. Write a vector that starts with a minus as --eye=-1,2,3.")
    g.add_argument("--eye", metavar="X,Y,Z", help="camera position")
    g.add_argument("--target", metavar="X,Y,Z", help="the point the camera looks at")
    g.add_argument("--up", metavar="X,Y,Z",
                   help="the camera's up direction (with --eye and --target: default 0,1,0)")
    g.add_argument("--fov", type=float, metavar="DEG",
                   help=f"vertical field of view in degrees (with --eye and --target, or framed "
                        f"automatically: default {DEFAULT_FOV:g})")
    g.add_argument("--view", metavar="NAME",
                   help="a named view from the views file (e.g. teapot, sponza-atrium)")
    g.add_argument("--views", metavar="FILE",
                   help="views file: a JSON object of named cameras, each "
                        '{"position": [x, y, z], "target": [x, y, z], "up": [x, y, z], "fov": deg} '
                        "(default: the one that ships with lbvh, the benchmark scenes' views, "
                        "as lbvh/data/cameras.json)")


def make_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="lbvh", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"lbvh {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("info", help="build a scene's BVH and print the report")
    p.add_argument("scene", help=SCENE_HELP)
    _add_build_options(p)
    p.add_argument("--validate", action="store_true", help="also run the tree validator")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=cmd_info)
    p = sub.add_parser("render", help="render a scene to an image file")
    p.add_argument("scene", help=SCENE_HELP)
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
    p.add_argument("--order", default="ordered", choices=["ordered", "global"],
                   help="closest-hit traversal: ordered depth first (default) or global, the "
                        "nearest pending node first (Kay & Kajiya); the same image")
    p.add_argument("--ray-sample", default=None, metavar="WxH",
                   help="--builder sah only: cost its splits by a WxH grid of this camera's "
                        "rays instead of areas (ray-sampled SAH, Nabata et al. 2013); a tree "
                        "for this view (e.g. 64x48)")
    _add_camera_options(p)
    _add_build_options(p)
    p.set_defaults(func=cmd_render)
    p = sub.add_parser("query", help="point and ray queries on a scene's mesh, or through the "
                                     "instances of a file of placed meshes")
    p.add_argument("kind", choices=list(QUERY_KINDS),
                   help="closest: the nearest point of the mesh; signed-distance: the distance, "
                        "negative inside; contains: inside or not (winding number); closest-hit: "
                        "each ray's first hit; any-hit: whether each ray hits; count-hits: how "
                        "often each ray crosses the mesh; all-hits: every hit of each ray")
    p.add_argument("scene", help=SCENE_HELP)
    p.add_argument("input", help="query points (closest, signed-distance, contains): a .npy of "
                                 "shape (N, 3), or a .txt/.csv of three numbers a row; rays "
                                 "(closest-hit, any-hit, count-hits, all-hits): shape (N, 6), "
                                 "ox oy oz dx dy dz a row")
    p.add_argument("-o", "--output", default=None, metavar="OUT",
                   help="write every answer to this file, in the format its suffix names: .npz "
                        "(the arrays the summary's wrote: line lists), .csv or .txt (a row per "
                        "point or ray, a row per hit for all-hits, with a header)")
    p.add_argument("--max-distance", type=float, default=float("inf"), metavar="R",
                   help="closest: search radius, beyond it a point finds nothing (default: none)")
    p.add_argument("--max-hits", type=int, default=None, metavar="K",
                   help="all-hits: keep the K nearest hits of each ray (default: all)")
    p.add_argument("--signed", action="store_true",
                   help="count-hits: count each crossing +1 where the ray leaves a triangle by "
                        "its front, -1 where it enters (from 0 to infinity on a closed mesh: the "
                        "winding number of the ray's origin)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    _add_build_options(p)
    p.set_defaults(func=cmd_query)
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
        try:
            args = parser.parse_args(argv)
        except SystemExit as exc:   # --help and --version print and exit 0
            return exc.code if isinstance(exc.code, int) else 0
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
