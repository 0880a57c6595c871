"""No kernel reads device memory that no command wrote (issue 14).

Oclgrind's uninitialised-value checker cannot run on Debian's Oclgrind 21.10
(tests/verification/test_second_implementation.py says why), so this is the check on PoCL:
every buffer the package hands out uninitialised, fresh or from its pool, is
first filled with a byte (``LBVH_POISON_BYTE``), and the same workload (every
builder, refit, the wide records, closest and any hit with counters, every hit
and the hit counts, an AO render, the ray order) must give the same answers for 0x00, 0xff and 0x7f as
without the fill. A read of unwritten memory would see the byte.
"""
from __future__ import annotations

import os
import subprocess
import sys

from conftest import REPO

SCRIPT = r"""
import hashlib, sys
import numpy as np
import lbvh
from lbvh.camera import frame_bounds
from lbvh.queries import ray_order
from lbvh.queries import wide
sys.path.insert(0, "tests")
from conftest import random_soup, shipped_mesh

def digest(*arrays):
    h = hashlib.sha1()
    for a in arrays:
        a = np.asarray(a)
        h.update(np.ascontiguousarray(a + 0.0 if a.dtype.kind == "f" else a).tobytes())
    return h.hexdigest()[:16]

ray_order.MIN_RAYS, ray_order.MIN_NODES = 1, 1   # the ray order on small batches too
v, f = shipped_mesh("teapot.obj")
sv, sf = random_soup(3000, seed=4)
rng = np.random.default_rng(2)
o = (rng.normal(size=(5000, 3)) * 3).astype(np.float32)
d = (-o + rng.normal(size=o.shape) * 0.5).astype(np.float32)
out = []
for mesh, kw in (((v, f), {}), ((sv, sf), {"key_bits": 63}), ((sv, sf), {"collapse": True}),
                 ((sv, sf), {"treelet_rounds": 2}), ((sv, sf), {"treelet_rounds": 1, "collapse": True}),
                 ((sv[:900], sf[:300]), {"builder": "sah"})):
    for _ in range(2):   # the second build takes the first one's buffers from the pool
        b = lbvh.build(*mesh, **kw)
    n = b.nodes
    h = b.intersect(o * 40 if mesh[0] is v else o, d, counters=True)
    a = b.occluded(o, d, tmax=0.7, return_hits=True)
    e = b.all_hits(o, d)
    out.append(digest(*(n[k] for k in n.dtype.names), b.tree.read("parent"), b.prim_order,
                      h.t, h.prim, h.u, h.v, h.nodes_visited, h.tris_tested, a.hit,
                      e.offsets, e.t, e.prim))
    b.refit(mesh[0] * 1.5)
    out.append(digest(b.nodes["lower"], b.nodes["upper"], b.intersect(o, d).t, b.count_hits(o, d)))
camera = frame_bounds(v.min(axis=0), v.max(axis=0), 40, 30)
out.append(digest(lbvh.render(lbvh.build(v, f), camera, "ao", ao_samples=2).image))
print("digests", " ".join(out))
"""


def _digests(poison: str | None) -> list[str]:
    env = dict(os.environ)
    env.pop("LBVH_POISON_BYTE", None)
    if poison is not None:
        env["LBVH_POISON_BYTE"] = poison
    proc = subprocess.run([sys.executable, "-c", SCRIPT], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return next(l for l in proc.stdout.splitlines() if l.startswith("digests")).split()[1:]


def test_no_kernel_reads_memory_no_command_wrote():
    clean = _digests(None)
    for byte in ("0x00", "0xff", "0x7f"):
        got = _digests(byte)
        differ = [k for k, (a, b) in enumerate(zip(clean, got)) if a != b]
        assert not differ, f"with every new buffer filled with {byte}, answers {differ} differ"
