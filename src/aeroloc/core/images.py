"""Reading and writing images with clear errors; writes are atomic (aeroloc.core.io) so a crash never leaves a half image."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

from aeroloc.core.errors import AerolocError
from aeroloc.core.io import atomic_write_bytes


def read_image(path: str | os.PathLike) -> np.ndarray:
    """RGB uint8 HxWx3 (EXIF orientation applied; grey and RGBA converted)."""
    path = Path(path)
    if not path.is_file():
        raise AerolocError(f"{path}: image file not found")
    try:
        with Image.open(path) as im:
            im = ImageOps.exif_transpose(im)
            return np.asarray(im.convert("RGB"))
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise AerolocError(f"{path}: not a readable image ({exc})") from None


def valid_mask(image: np.ndarray) -> np.ndarray:
    """Pixels that carry imagery: not pure black (0,0,0), which marks no-data/borders in rendered tiles.

    For unsigned images the channels are OR-ed: a max over the length-3 last axis took 24 ms on a 1200x900 photo
    (a quarter of its XFeat extraction), the OR 1 ms."""
    if image.ndim == 2:
        return image > 0
    if np.issubdtype(image.dtype, np.unsignedinteger):
        m = image[..., 0].copy()
        for c in range(1, image.shape[2]):
            m |= image[..., c]
        return m != 0
    return image.max(axis=2) > 0


def write_image(path: str | os.PathLike, image: np.ndarray, quality: int = 95) -> None:
    """Write RGB uint8 to PNG/JPEG by extension, atomically (temp file + rename)."""
    import io

    path = Path(path)
    buf = io.BytesIO()
    fmt = "JPEG" if path.suffix.lower() in (".jpg", ".jpeg") else "PNG"
    Image.fromarray(image).save(buf, format=fmt, **({"quality": quality} if fmt == "JPEG" else {}))
    atomic_write_bytes(path, buf.getvalue())
