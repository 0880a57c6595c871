"""What a build reports: phase timings from OpenCL event profiling, key choice, tree statistics."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from .layout import is_leaf, node_depths, prim_range_of

#: Phases of the device build, in pipeline order.
PHASES = ("bounds", "morton", "sort", "emit", "refit")


@dataclass
class BuildReport:
    """Figures of one build. Times are seconds; ``phase_seconds`` come from event profiling."""
    device: str
    builder: str
    num_triangles: int
    #: Bits of the Morton codes, as ``lbvh.build(key_bits=...)`` takes them: 30 or 63.
    key_bits: int | None = None
    key_choice: str = ""
    duplicate_codes: int | None = None
    phase_seconds: dict[str, float] = field(default_factory=dict)
    device_seconds: float = 0.0
    wall_seconds: float = 0.0
    upload_seconds: float = 0.0
    sort_passes: int | None = None
    peak_device_bytes: int = 0
    input_bytes: int = 0
    num_nodes: int | None = None
    num_leaves: int | None = None
    depth: int | None = None
    mean_leaf_depth: float | None = None
    leaf_size_histogram: dict[int, int] = field(default_factory=dict)

    @property
    def bytes_per_triangle(self) -> float:
        """Peak device memory beyond the input mesh, per triangle."""
        return self.peak_device_bytes / max(self.num_triangles, 1)

    @property
    def mtris_per_second(self) -> float:
        return self.num_triangles / self.device_seconds * 1e-6 if self.device_seconds else float("nan")

    def update_stats(self, stats: dict) -> None:
        for key, value in stats.items():
            setattr(self, key, value)

    def as_dict(self) -> dict:
        out = asdict(self)
        out["bytes_per_triangle"] = self.bytes_per_triangle
        out["mtris_per_second"] = self.mtris_per_second
        out["leaf_size_histogram"] = {str(k): v for k, v in self.leaf_size_histogram.items()}
        return out

    def __str__(self) -> str:
        lines = [f"device:      {self.device}",
                 f"builder:     {self.builder}",
                 f"triangles:   {self.num_triangles:,}"]
        if self.key_bits is not None:
            lines.append(f"morton keys: {self.key_bits}-bit "
                         f"({self.key_choice}); duplicate codes: {self.duplicate_codes:,}")
        if self.phase_seconds:
            phases = "  ".join(f"{k} {v * 1e3:.2f}" for k, v in self.phase_seconds.items())
            lines.append(f"phases (ms): {phases}")
            lines.append(f"device time: {self.device_seconds * 1e3:.2f} ms "
                         f"({self.mtris_per_second:.1f} Mtris/s); wall {self.wall_seconds * 1e3:.2f} ms "
                         f"(+ upload {self.upload_seconds * 1e3:.2f} ms)")
        elif self.wall_seconds:
            lines.append(f"build time:  {self.wall_seconds * 1e3:.2f} ms on the host"
                         + (f" (+ upload {self.upload_seconds * 1e3:.2f} ms)" if self.upload_seconds else ""))
        if self.sort_passes is not None:
            lines.append(f"sort passes: {self.sort_passes}")
        if self.peak_device_bytes:
            lines.append(f"device memory beyond the input: peak {self.peak_device_bytes / 2**20:.1f} MiB "
                         f"({self.bytes_per_triangle:.1f} B/triangle)")
        if self.num_nodes is not None:
            hist = ", ".join(f"{k}: {v}" for k, v in sorted(self.leaf_size_histogram.items()))
            lines.append(f"tree:        {self.num_nodes:,} nodes, {self.num_leaves:,} leaves, depth "
                         f"{self.depth} (mean leaf depth {self.mean_leaf_depth:.1f}); leaf sizes {{{hist}}}")
        return "\n".join(lines)


def tree_statistics(nodes: np.ndarray, parent: np.ndarray, root: int) -> dict:
    """Depth, node and leaf counts and the leaf-size histogram of a tree."""
    depth = node_depths(parent, root)
    leaf = is_leaf(nodes)
    sizes = prim_range_of(nodes)[leaf, 1]
    values, counts = np.unique(sizes, return_counts=True)
    return {"num_nodes": int(len(nodes)), "num_leaves": int(leaf.sum()),
            "depth": int(depth.max()), "mean_leaf_depth": float(depth[leaf].mean()),
            "leaf_size_histogram": {int(v): int(c) for v, c in zip(values, counts)}}
