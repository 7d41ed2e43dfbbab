"""Image files: PNG (8/16-bit, libpng through imagecodecs) and OpenEXR (linear float, the
`OpenEXR` package), written atomically.

EXR files hold named layers: `RGB` `(H, W, 3)` for colour, single-channel layers `(H, W)` by
name (`ps`, `status`, ...) and `A` for coverage. Other tools read them as they are
(OpenImageIO, Blender, Nuke, `OpenEXR.File`).
"""

from __future__ import annotations

import os
import tempfile

import imagecodecs
import numpy as np

from .io import atomic_write

__all__ = ["read_image", "write_png", "write_exr", "read_exr"]

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


# -- images ------------------------------------------------------------------------------


def _read_png(path) -> tuple[np.ndarray, int]:
    """`(H, W, C)` unsigned codes and the top code, decoded by libpng (imagecodecs).

    Any PNG: 8/16-bit grey, grey+alpha, RGB, RGBA, interlaced or not; palette images
    come back as RGB(A) and 1/2/4-bit grey as 8-bit. Pillow and imageio read 16-bit
    colour as 8 bits, hence imagecodecs.
    """
    with open(path, "rb") as fh:
        data = fh.read()
    if not data.startswith(_PNG_SIGNATURE):
        raise ValueError("not a PNG file")
    try:
        codes = imagecodecs.png_decode(data)
    except imagecodecs.PngError as exc:
        raise ValueError(f"corrupt PNG ({exc})") from None
    codes = codes[..., None] if codes.ndim == 2 else codes
    return codes, int(np.iinfo(codes.dtype).max)


def read_image(path) -> tuple[np.ndarray, int | None]:
    """An image file as `(H, W, C)` float64 and its top code.

    PNG (8- or 16-bit): codes divided by the top code, so values lie in [0, 1];
    returns `(values, top_code)`. `.npy` and `.exr` (OpenEXR, half or float): linear values as
    they are, shape `(H, W)` or `(H, W, C)` (EXR: the `RGB` or `Y` layer, alpha ignored);
    returns `(values, None)`. Raises `ValueError`.
    """
    path = os.fspath(path)
    if path.lower().endswith(".npy"):
        arr = np.load(path, allow_pickle=False)
        if arr.dtype.kind not in "fiu" or arr.ndim not in (2, 3):
            raise ValueError(f"must be an (H, W) or (H, W, C) numeric array, got {arr.dtype} {arr.shape}")
        arr = arr.astype(np.float64)
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{int(np.count_nonzero(~np.isfinite(arr)))} non-finite pixel value(s)")
        return (arr if arr.ndim == 3 else arr[..., None]), None
    if path.lower().endswith(".exr"):
        layers = read_exr(path)
        arr = layers.get("RGB", layers.get("Y"))
        if arr is None:
            raise ValueError(f"EXR without an RGB or Y layer (layers: {sorted(layers)})")
        arr = np.asarray(arr, dtype=np.float64)
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{int(np.count_nonzero(~np.isfinite(arr)))} non-finite pixel value(s)")
        return (arr if arr.ndim == 3 else arr[..., None]), None
    if path.lower().endswith(".png"):
        codes, top = _read_png(path)
        return codes.astype(np.float64) / top, top
    raise ValueError("unsupported image type: use .png (8/16-bit), .exr or .npy (linear float)")


def write_png(path, image: np.ndarray) -> None:
    """Write a uint8 or uint16 image `(H, W)` or `(H, W, C)`, C in 1..4, as PNG atomically.

    Encoded by libpng (imagecodecs), which writes 16-bit colour (Pillow cannot).
    """
    img = np.asarray(image)
    if img.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"write_png: image must be uint8 or uint16, got {img.dtype}")
    img = img[..., None] if img.ndim == 2 else img
    if img.ndim != 3 or img.shape[2] not in (1, 2, 3, 4) or 0 in img.shape:
        raise ValueError(f"write_png: image must be (H, W) or (H, W, 1..4), got {np.shape(image)}")
    png = imagecodecs.png_encode(np.ascontiguousarray(img if img.shape[2] > 1 else img[..., 0]))
    atomic_write(path, lambda fh: fh.write(png))


def write_exr(path, layers: dict) -> None:
    """Write `layers` (name -> `(H, W)` or `(H, W, 3)` array, one size; `RGB` for colour) as a
    float32 OpenEXR file, ZIP-compressed, atomically. NaN stays NaN (EXR keeps it: "no value")."""
    import OpenEXR

    arrays = {k: np.ascontiguousarray(np.asarray(v, dtype=np.float32)) for k, v in layers.items()}
    shapes = {a.shape[:2] for a in arrays.values()}
    if not arrays or len(shapes) != 1 or any(a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in (3, 4))
                                            for a in arrays.values()):
        raise ValueError(f"write_exr: layers must be (H, W) or (H, W, 3|4) arrays of one size, got "
                         f"{ {k: a.shape for k, a in arrays.items()} }")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}

    with tempfile.TemporaryDirectory() as folder:  # OpenEXR writes by file name
        tmp = os.path.join(folder, "image.exr")
        with OpenEXR.File(header, arrays) as f:
            f.write(tmp)
        with open(tmp, "rb") as src:
            data = src.read()
    atomic_write(path, lambda fh: fh.write(data))


def read_exr(path) -> dict:
    """The layers of an OpenEXR file: name -> `(H, W)` or `(H, W, C)` float32 array (an `RGBA`
    layer, as OpenEXR groups R, G, B and A, comes back as `RGB` and `A`)."""
    import OpenEXR

    try:
        with OpenEXR.File(os.fspath(path)) as f:
            layers = {name: np.asarray(ch.pixels, dtype=np.float32) for name, ch in f.channels().items()}
    except (RuntimeError, OSError) as exc:
        raise ValueError(f"not a readable EXR file ({exc})") from None
    if "RGBA" in layers and "RGB" not in layers and "A" not in layers:
        rgba = layers.pop("RGBA")
        layers["RGB"], layers["A"] = rgba[..., :3], rgba[..., 3]
    return layers
