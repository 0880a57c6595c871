"""Image files through OpenImageIO: 8-bit for display, float for measurements.

The file extension chooses the format: ``.png``, ``.jpg``/``.jpeg`` store 8 bits
per channel; ``.exr``, ``.tif``/``.tiff`` store 32-bit floats. Pixels are numpy
arrays ``(height, width)`` or ``(height, width, channels)`` with row 0 at the top.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

#: Extensions of files written with 8 bits per channel, and with 32-bit floats.
EIGHT_BIT_SUFFIXES = (".png", ".jpg", ".jpeg")
FLOAT_SUFFIXES = (".exr", ".tif", ".tiff")


def image_kind(path: str | os.PathLike) -> str:
    """``"8bit"`` or ``"float"``: what a file named ``path`` stores; ``ValueError`` otherwise."""
    suffix = Path(path).suffix.lower()
    if suffix in EIGHT_BIT_SUFFIXES:
        return "8bit"
    if suffix in FLOAT_SUFFIXES:
        return "float"
    known = ", ".join(EIGHT_BIT_SUFFIXES + FLOAT_SUFFIXES)
    raise ValueError(f"{path}: unknown image format {suffix or '(no extension)'!r} "
                     f"(expected one of {known})")


def to_8bit(pixels: np.ndarray) -> np.ndarray:
    """``uint8`` of the same shape: values in [0, 1] scaled to [0, 255], rounded; NaN -> 0."""
    values = np.nan_to_num(np.asarray(pixels, dtype=np.float64), nan=0.0, posinf=1.0, neginf=0.0)
    return np.rint(np.clip(values, 0.0, 1.0) * 255.0).astype(np.uint8)


def _as_hwc(pixels: Any) -> np.ndarray:
    arr = np.asarray(pixels)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    # No alpha channel: OpenImageIO would treat a second or fourth channel as
    # premultiplied alpha and change the colour values on the way to and from a PNG.
    if arr.ndim != 3 or arr.shape[2] not in (1, 3) or arr.shape[0] == 0 or arr.shape[1] == 0:
        raise ValueError(f"pixels: shape {arr.shape}, expected (height, width) or "
                         "(height, width, channels) with 1 (grey) or 3 (RGB) channels")
    if not (np.issubdtype(arr.dtype, np.floating) or arr.dtype == np.uint8):
        raise ValueError(f"pixels: dtype {arr.dtype}, expected uint8 or a float type")
    return arr


def write_image(path: str | os.PathLike, pixels: Any) -> None:
    """Write ``pixels`` to ``path`` in the format its extension names.

    ``pixels``: ``uint8`` or float, ``(H, W)`` or ``(H, W, C)`` with ``C`` 1 or 3.
    An 8-bit file takes float pixels as values in [0, 1] (clipped); a float file
    takes ``uint8`` pixels as ``value / 255``. Infinities and NaN survive in float files.

    Raises:
        ValueError: unknown extension, bad pixel array, or a path that cannot be
            written (missing folder, no permission), naming the path.
    """
    import OpenImageIO as oiio

    kind = image_kind(path)
    arr = _as_hwc(pixels)
    if kind == "8bit":
        data, fmt = (arr if arr.dtype == np.uint8 else to_8bit(arr)), oiio.UINT8
    else:
        data = arr.astype(np.float32) / 255.0 if arr.dtype == np.uint8 else arr.astype(np.float32)
        fmt = oiio.FLOAT
    data = np.ascontiguousarray(data)
    height, width, channels = data.shape
    out = oiio.ImageOutput.create(str(path))
    if out is None:
        raise ValueError(f"{path}: OpenImageIO cannot write this format ({oiio.geterror()})")
    spec = oiio.ImageSpec(width, height, channels, fmt)
    if not out.open(str(path), spec):
        raise ValueError(f"{path}: cannot write ({out.geterror() or 'cannot open the file'})")
    ok = out.write_image(data)
    error = out.geterror() if not ok else ""
    out.close()
    if not ok:
        raise ValueError(f"{path}: writing failed ({error})")


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read an image: ``(H, W, C)``, ``uint8`` from an 8-bit file, ``float32`` from a float file."""
    import OpenImageIO as oiio

    kind = image_kind(path)
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise ValueError(f"{path}: cannot read image ({oiio.geterror()})")
    try:
        data = inp.read_image(oiio.UINT8 if kind == "8bit" else oiio.FLOAT)
        error = inp.geterror() if data is None else ""
    finally:
        inp.close()
    if data is None:
        raise ValueError(f"{path}: cannot read image ({error})")
    data = np.asarray(data)
    return data[:, :, None] if data.ndim == 2 else data


# Control points of the heat colour ramp (our own): deep blue, purple, red,
# orange, pale yellow; low cost is dark so that expensive regions stand out.
_HEAT_STOPS = np.array([0.0, 0.25, 0.5, 0.75, 1.0])
_HEAT_COLOURS = np.array([[0.02, 0.02, 0.20],
                          [0.40, 0.05, 0.55],
                          [0.85, 0.15, 0.30],
                          [0.99, 0.55, 0.08],
                          [1.00, 0.97, 0.65]])


def heat_colours(values: np.ndarray, vmax: float | None = None) -> np.ndarray:
    """Map non-negative ``values`` (any shape) to colours ``float32 (..., 3)`` in [0, 1].

    ``vmax`` is the value drawn at the top of the ramp (default: the largest
    finite value); larger values are clipped to it.
    """
    values = np.asarray(values, dtype=np.float64)
    finite = values[np.isfinite(values)]
    if vmax is None:
        vmax = float(finite.max()) if finite.size else 1.0
    scaled = np.clip(np.nan_to_num(values, nan=0.0, posinf=vmax) / (vmax if vmax > 0 else 1.0), 0.0, 1.0)
    rgb = np.stack([np.interp(scaled, _HEAT_STOPS, _HEAT_COLOURS[:, c]) for c in range(3)], axis=-1)
    return rgb.astype(np.float32)
