"""The entry points: ``lbvh.build``, ``lbvh.build_scene``, ``lbvh.load`` and
``lbvh.collapse_leaves``.

Each checks everything it is given (mesh, options, device) before anything
is uploaded, runs a builder (:mod:`lbvh.builders`) and wraps the tree it
returns in a :class:`lbvh.BVH`; a scene of several meshes (a ``trimesh.Scene``
or a list) becomes a :class:`lbvh.Scene` of instances.
"""
from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from . import device as dev
from .builders import pipeline, ploc, sah, sbvh, topdown
from .builders.collapse import collapse
from .builders.options import (SPLIT_BUILDERS, CollapseOptions, LBVHOptions, PLOCOptions,
                               SAHOptions, SBVHOptions, SplitOptions, make, options_from)
from .bvh import SAVE_FORMAT_VERSION, BVH
from .layout import NODE_DTYPE
from .mesh import MissingFileError, as_mesh
from .files import load_mesh
from .scene import Scene
from .tree import Mesh, Tree

#: The options objects ``lbvh.build(options=...)`` takes, one per builder.
BuildOptions = LBVHOptions | SAHOptions | SplitOptions | SBVHOptions | PLOCOptions


def build(vertices: Any, faces: Any = None, *, builder: str = "lbvh", device: Any = None,
          collapse: bool | CollapseOptions = False,
          options: BuildOptions | None = None, progress: bool | None = None,
          **fields: Any) -> BVH:
    """Build a BVH over a triangle mesh: the device LBVH, or the serial SAH reference.

    Args:
        vertices: ``(V, 3)`` float coordinates, or a ``trimesh.Trimesh`` or the path of a
            mesh file (OBJ, PLY, STL, glTF..., read with trimesh; the meshes of a file
            of several are flattened into one) (then no ``faces``).
        faces: ``(F, 3)`` integer vertex indices.
        builder: ``"lbvh"`` (device, Karras 2012), ``"sah"`` (serial full-sweep SAH on
            the host, the reference), or the course's top-down object splits on the
            host, ``"median"`` and ``"midpoint"`` (:mod:`lbvh.builders.topdown`), or
            ``"sbvh"``, spatial splits (Stich et al. 2009, :mod:`lbvh.builders.sbvh`): a
            triangle may sit in several leaves (see :class:`lbvh.SBVHOptions`), or
            ``"ploc"``: bottom-up clustering on the device (Meister & Bittner 2018,
            :mod:`lbvh.builders.ploc`; see :class:`lbvh.PLOCOptions`).
        device: a device name (see :mod:`lbvh.device`), a ``pyopencl.Device``, or
            ``None`` for ``$LBVH_DEVICE`` / PoCL's CPU device.
        collapse: ``"lbvh"`` only: ``True`` or a :class:`lbvh.CollapseOptions`: after the
            build, merge subtrees into leaves where the SAH says testing their triangles
            is cheaper (:mod:`lbvh.builders.collapse`).
        options: the builder's options as data, :class:`lbvh.LBVHOptions`,
            :class:`lbvh.SAHOptions`, :class:`lbvh.PLOCOptions`... (defaults documented
            there).
        progress: a progress bar on stderr for the long builds (the SAH reference
            over 200K triangles or more): ``None`` (default) when stderr is a
            terminal, ``True`` or ``False`` to force it (:mod:`lbvh.progress`).
        fields: the fields of the builder's options as keywords, each not given
            keeping its documented default: ``key_bits`` (30, 63 or ``"auto"``),
            ``auto_duplicate_fraction``, ``treelet_rounds``, ``treelet_leaves`` and
            ``treelet_min_leaves`` of ``LBVHOptions``; ``c_node``, ``c_tri`` and
            ``max_leaf_size`` of ``SAHOptions`` (``"sah"``) or, with ``collapse=True``,
            of ``CollapseOptions``; ``max_leaf_size`` alone: of ``SplitOptions``
            (``"median"``, ``"midpoint"``); ``rays`` (an ``(origins, directions)``
            pair or :class:`lbvh.RaySample`), ``ray_prior``, ``ray_candidates``
            (``"sah"``): splits costed by a sample of the rays the tree is for (see
            :class:`lbvh.SAHOptions`); ``radius`` of ``PLOCOptions`` (``"ploc"``).
            Any other name is refused with a ``ValueError`` naming it.

    Returns:
        :class:`lbvh.BVH` whose buffers stay on the device. ``bvh.report()``
        gives the phase timings and tree statistics. Given a ``trimesh.Scene`` or a
        list of meshes (no ``faces``): a :class:`lbvh.Scene`, see :func:`build_scene`.

    Raises:
        ValueError: bad mesh (NaN/inf, out-of-range indices, non-triangles, empty,
            wrong shape or dtype) or bad option; nothing is built.
    """
    build_options, collapse_options = options_from(builder, collapse, fields, options)
    if faces is None and (is_trimesh_scene(vertices) or isinstance(vertices, (list, tuple))):
        return build_scene(vertices, builder=builder, device=device, collapse=collapse,
                           options=options, progress=progress, **fields)
    if isinstance(vertices, (str, os.PathLike)):
        if faces is not None:
            raise ValueError(f"vertices: a path ({os.fspath(vertices)!r}) was passed together "
                             "with faces; pass the path alone")
        v, f = load_mesh(vertices)   # every mesh of the file, flattened into one, checked
    else:
        v, f = as_mesh(vertices, faces)
    ctx = dev.get_context(device)
    if builder in ("lbvh", "ploc") and not pipeline.fits(ctx, len(f)):
        # beyond the device's largest buffer: parts that fit, one scene
        return build_parts(v, f, pipeline.max_triangles(ctx), builder=builder, device=device,
                           collapse=collapse, options=options, progress=progress, **fields)
    with ctx.lock:   # one call's commands at a time on the context's queue
        t0 = time.perf_counter()
        mesh = Mesh.upload(ctx, v, f)
        ctx.queue.finish()
        upload = time.perf_counter() - t0
        if builder == "sah":
            t0 = time.perf_counter()
            untraced = build_options.rays is not None and build_options.rays.tmax is None
            build_options = _traced_ray_sample(ctx, mesh, build_options)
            traced = time.perf_counter() - t0
            tree = sah.build_tree(ctx, mesh, build_options, progress)
            # the sample's rays through the default LBVH, if traced here, are part of it
            return BVH(mesh, _with_times(tree, upload, traced if untraced else None))
        if builder == "sbvh":
            tree = sbvh.build_tree(ctx, mesh, build_options, progress)
            return BVH(mesh, _with_times(tree, upload))
        if builder in SPLIT_BUILDERS:
            tree = topdown.build_tree(ctx, mesh, builder, build_options)
            return BVH(mesh, _with_times(tree, upload))
        if builder == "ploc":
            with ctx.memory.scope() as mem:   # every buffer of the build
                tree = ploc.build_tree(ctx, mesh, build_options, mem)
                mem.close()
            return BVH(mesh, _with_times(tree, upload))
        return _build_lbvh(ctx, mesh, upload, build_options, collapse_options)


def _traced_ray_sample(ctx: dev.Context, mesh: Mesh, options: SAHOptions) -> SAHOptions:
    """``options`` whose ray sample (if any) ends at each ray's closest hit: rays not
    traced yet go through the mesh's default LBVH first (dropped after)."""
    sample = options.rays
    if sample is None or sample.tmax is not None:
        return options
    first = _build_lbvh(ctx, mesh, 0.0, LBVHOptions(), None)
    hits = first.intersect(sample.origins, sample.directions)
    return dataclasses.replace(options, rays=sample.ended_at(hits.t))


def is_trimesh_scene(value: Any) -> bool:
    """Whether ``value`` is a ``trimesh.Scene`` (a graph of placed geometries)."""
    return hasattr(value, "graph") and isinstance(getattr(value, "geometry", None), dict)


def build_scene(source: Any, **options: Any) -> Scene:
    """A :class:`lbvh.Scene` of instances from a ``trimesh.Scene`` or a list of meshes.

    ``trimesh.Scene``: every node of its graph that places a triangle mesh becomes an
    instance with the node's world transform; a geometry placed several times is
    built once (geometry without triangles, points or paths, is left out). A list:
    each item a ``trimesh.Trimesh`` or a ``(vertices, faces)`` pair, each placed once
    where it is (the identity). ``options`` go to :func:`build` for every mesh.
    The instances' ``names`` are the graph's node names (a list: ``"0"``, ``"1"``...).
    """
    if is_trimesh_scene(source):
        names, geometry_of, transforms = [], [], []
        for node in source.graph.nodes_geometry:
            matrix, geometry = source.graph[node]
            mesh = source.geometry.get(geometry)
            if mesh is None or len(getattr(mesh, "faces", ())) == 0:
                continue
            names.append(str(node))
            geometry_of.append(geometry)
            transforms.append(np.asarray(matrix, np.float64))
        if not names:
            raise ValueError("source: a trimesh.Scene without triangle meshes in its graph")
        keys = sorted(set(geometry_of), key=geometry_of.index)
        meshes = [build(source.geometry[k], **options) for k in keys]
        mesh_of = [keys.index(g) for g in geometry_of]
        return Scene(meshes, mesh_of, np.stack(transforms), names=names)
    items = list(source)
    if not items:
        raise ValueError("source: an empty list of meshes")
    meshes = []
    for k, item in enumerate(items):
        if isinstance(item, (tuple, list)) and len(item) == 2:
            meshes.append(build(item[0], item[1], **options))
        elif hasattr(item, "vertices") and hasattr(item, "faces"):
            meshes.append(build(item, **options))
        else:
            raise ValueError(f"source: item {k} is a {type(item).__name__}; expected a "
                             "trimesh.Trimesh or a (vertices, faces) pair")
    eye = np.tile(np.eye(3, 4), (len(meshes), 1, 1))
    return Scene(meshes, np.arange(len(meshes)), eye, names=[str(k) for k in range(len(meshes))])


def morton_parts(vertices: np.ndarray, faces: np.ndarray, part_triangles: int) -> list[np.ndarray]:
    """The triangles cut into parts of at most ``part_triangles``, consecutive in the
    Morton order of their centres (30-bit codes over the mesh's box, on the host): each
    part compact in space. ``int64`` triangle indices per part."""
    p = vertices.astype(np.float64)[faces]
    centre = p.mean(axis=1)
    lo, hi = centre.min(axis=0), centre.max(axis=0)
    cell = np.clip(((centre - lo) / np.where(hi > lo, hi - lo, 1) * 1024).astype(np.int64), 0, 1023)
    code = np.zeros(len(faces), np.int64)
    for bit in range(10):
        for axis in range(3):
            code |= ((cell[:, axis] >> bit) & 1) << (3 * bit + 2 - axis)
    order = np.argsort(code, kind="stable")
    count = -(-len(faces) // part_triangles)
    return np.array_split(order, count)


def build_parts(vertices: Any, faces: Any = None, part_triangles: int = 1 << 24,
                **options: Any) -> Scene:
    """One mesh as a :class:`lbvh.Scene` of parts of at most ``part_triangles`` triangles
    (consecutive in Morton order, :func:`morton_parts`), each built by :func:`build` with
    ``options`` and placed by the identity; hits name the mesh's own triangles
    (``Scene.face_ids``) and ``instance`` the part. :func:`build` does this by itself
    for a mesh whose node buffer would pass the device's largest allocation."""
    if isinstance(part_triangles, bool) or not isinstance(part_triangles, (int, np.integer)) \
            or part_triangles < 1:
        raise ValueError(f"part_triangles: {part_triangles!r}; expected a positive integer")
    if isinstance(vertices, (str, os.PathLike)):
        v, f = load_mesh(vertices)
    else:
        v, f = as_mesh(vertices, faces)
    parts, meshes = morton_parts(v, f, int(part_triangles)), []
    local = np.empty(len(v), np.int64)
    for part in parts:
        corners = f[part]
        used = np.flatnonzero(np.bincount(corners.ravel(), minlength=len(v)))   # ascending
        local[used] = np.arange(len(used))    # the part's own vertex numbering
        meshes.append(build(v[used], local[corners].astype(np.uint32), **options))
    eye = np.tile(np.eye(3, 4), (len(parts), 1, 1))
    return Scene(meshes, np.arange(len(parts)), eye, names=[f"part {k}" for k in range(len(parts))],
                 face_ids=[p.astype(np.int32) for p in parts])


def _with_times(tree: Tree, upload: float, traced: float | None = None) -> Tree:
    """``tree`` with a report of its own: the builder's figures, plus this call's
    mesh upload and, for an SAH build from rays not traced yet, the ``traced``
    seconds of their trace (a phase of the build). The builder's report is left as
    it made it."""
    rep = tree.report
    phases = dict(rep.phase_seconds)
    wall = rep.wall_seconds
    if traced is not None:
        phases["trace ray sample"] = traced
        wall += traced
    return dataclasses.replace(tree, report=dataclasses.replace(
        rep, upload_seconds=rep.upload_seconds + upload, wall_seconds=wall,
        phase_seconds=phases))


def _build_lbvh(ctx: dev.Context, mesh: Mesh, upload: float, options: LBVHOptions,
                collapse_options: CollapseOptions | None) -> BVH:
    with ctx.memory.scope() as mem:   # every buffer of the build, the collapse's too
        tree = _with_times(pipeline.build_tree(ctx, mesh, options, mem), upload)
        if collapse_options is not None:
            built = tree
            tree = collapse(built, collapse_options, mem)
            ctx.memory.give_back(built.buffers())   # the uncollapsed tree is not kept
        mem.close()
    return BVH(mesh, tree)


def collapse_leaves(bvh: BVH, **options: Any) -> BVH:
    """A new BVH whose leaves are the subtrees of ``bvh`` that the SAH prefers as leaves.

    ``options``: the fields of :class:`~lbvh.builders.options.CollapseOptions`
    (``c_node``, ``c_tri``, ``max_leaf_size``). ``bvh`` is not modified; the
    new tree shares its mesh, its builder is ``"<builder>+collapse"`` and its
    report adds a ``collapse`` phase. Raises ``ValueError`` on a bad or
    unknown option.
    """
    opts = make(CollapseOptions, options, "the leaf collapse")
    with bvh.ctx.lock:
        return BVH(bvh.mesh, collapse(bvh.tree, opts))


def load(path: str | os.PathLike, device: Any = None) -> BVH:
    """Read a tree written by :meth:`BVH.save` and upload it to the device.

    Raises ``FileNotFoundError`` (:class:`lbvh.mesh.MissingFileError`, also a
    ``ValueError``) for a missing file, ``ValueError`` for a file that is not
    a saved tree or holds a broken one.
    """
    path = Path(path)
    if not path.is_file():
        raise MissingFileError(f"{path}: no such file" + (" (a folder)" if path.is_dir() else ""))
    with open(path, "rb") as head:
        magic = head.read(4)
    if magic not in (b"PK\x03\x04", b"PK\x05\x06"):   # a zip archive's first entry, or empty
        raise ValueError(f"{path}: not a saved lbvh BVH (not an .npz archive: "
                         f"it starts with {magic!r}, not a zip file's b'PK')")
    try:
        data = np.load(path, allow_pickle=False)
    except Exception as exc:  # OSError, ValueError, zipfile.BadZipFile, EOFError...
        raise ValueError(f"{path}: not a saved lbvh BVH ({type(exc).__name__}: {exc})") from None
    with data:
        missing = {"format_version", "nodes", "prim_order", "root", "vertices", "faces"} - set(data.files)
        if missing:
            raise ValueError(f"{path}: not a saved lbvh BVH (missing {sorted(missing)})")
        if int(data["format_version"]) != SAVE_FORMAT_VERSION:
            raise ValueError(f"{path}: format version {int(data['format_version'])}, "
                             f"this lbvh reads {SAVE_FORMAT_VERSION}")
        nodes = data["nodes"]
        if nodes.dtype != NODE_DTYPE:
            raise ValueError(f"{path}: nodes have dtype {nodes.dtype}, expected {NODE_DTYPE}")
        builder = str(data["builder"]) if "builder" in data.files else "loaded"
        try:
            bvh = BVH.from_arrays(nodes, data["prim_order"], int(data["root"]), data["vertices"],
                                  data["faces"], builder=builder, device=device)
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None
    return bvh


__all__ = ["build", "load", "collapse_leaves", "LBVHOptions", "SAHOptions", "CollapseOptions"]
