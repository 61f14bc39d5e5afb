"""Image input: paths or arrays in, a validated 2-D uint8 gray frame out.

Accepted arrays: HxW gray or HxWx3 BGR (OpenCV order), HxWx4 BGRA (alpha dropped); uint8 as is,
uint16 scaled by 1/257, float in [0, 1] scaled by 255 (NaN/inf refused). Files are decoded by
OpenCV (EXIF orientation applied, 16-bit and palette images converted to 8-bit gray).
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

DEFAULT_MAX_PIXELS = 100_000_000


class ImageError(ValueError):
    """The input is not an image ccdn can use; the message says why, in one line."""


def read_gray(path: str | os.PathLike, max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """Decode an image file to HxW uint8 gray, or raise ImageError with the reason."""
    p = Path(path)
    if not p.exists():
        raise ImageError(f"{p}: no such file")
    if p.is_dir():
        raise ImageError(f"{p}: is a directory, not an image")
    try:
        data = np.fromfile(p, dtype=np.uint8)  # handles any file name, unlike cv2.imread
    except OSError as exc:
        raise ImageError(f"{p}: cannot read ({exc.strerror or exc})") from exc
    if data.size == 0:
        raise ImageError(f"{p}: empty file")
    header = cv2.imdecode(data, cv2.IMREAD_REDUCED_GRAYSCALE_8)  # cheap size probe, 1/8 scale
    if header is None:
        raise ImageError(f"{p}: not a decodable image (corrupt, truncated or unsupported format)")
    if header.size * 64 > max_pixels * 1.05:
        raise ImageError(f"{p}: about {header.size * 64} pixels, over the limit of {max_pixels}")
    image = cv2.imdecode(data, cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
    if image is None:
        raise ImageError(f"{p}: not a decodable image (corrupt, truncated or unsupported format)")
    return to_gray(image, max_pixels, source=str(p))


def to_gray(image: np.ndarray, max_pixels: int = DEFAULT_MAX_PIXELS, source: str = "array") -> np.ndarray:
    """Validate an array and convert it to a C-contiguous HxW uint8 gray frame."""
    if not isinstance(image, np.ndarray):
        raise ImageError(f"{source}: expected a numpy array or a path, got {type(image).__name__}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (3, 4)):
        raise ImageError(f"{source}: expected HxW gray or HxWx3/HxWx4 colour, got shape {image.shape}")
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise ImageError(f"{source}: empty image, shape {image.shape}")
    if image.shape[0] * image.shape[1] > max_pixels:
        raise ImageError(f"{source}: {image.shape[0] * image.shape[1]} pixels, over the limit of {max_pixels}")
    image = _to_uint8(image, source)
    if image.ndim == 3:
        code = cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        image = cv2.cvtColor(image, code)
    return np.ascontiguousarray(image)


def _to_uint8(image: np.ndarray, source: str) -> np.ndarray:
    if image.dtype == np.uint8:
        return image
    if image.dtype == np.uint16:
        return (image.astype(np.float32) * (1 / 257) + 0.5).astype(np.uint8)
    if np.issubdtype(image.dtype, np.floating):
        if not np.all(np.isfinite(image)):
            raise ImageError(f"{source}: float image contains NaN or infinity")
        return (np.clip(image, 0.0, 1.0) * 255 + 0.5).astype(np.uint8)
    if image.dtype == np.bool_:
        return image.astype(np.uint8) * 255
    raise ImageError(f"{source}: unsupported dtype {image.dtype} (use uint8, uint16 or float in [0, 1])")
