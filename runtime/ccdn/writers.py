"""Output writers: JSON results and overlay images, each written atomically (temp file + rename)."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import cv2
import numpy as np

from .result import Detection


def write_atomic(path: Path, data: bytes) -> None:
    """Write `data` to `path` so that readers see the old file or the whole new one, never half."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_json(path: Path, detection: Detection, source: str) -> None:
    payload = {"image": source, **detection.to_dict()}
    write_atomic(path, (json.dumps(payload, indent=1) + "\n").encode())


def draw_overlay(gray: np.ndarray, detection: Detection) -> np.ndarray:
    """BGR copy of the image with each corner marked (green cross, radius scaled to the image)."""
    out = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    r = max(3, round(max(gray.shape) / 200))
    shift = 4  # sub-pixel drawing: coordinates in 1/16 px
    for x, y in detection.xy:
        c = (int(round(x * 16)), int(round(y * 16)))
        cv2.circle(out, c, r * 16, (0, 255, 0), 1, cv2.LINE_AA, shift)
        cv2.drawMarker(out, (int(round(x)), int(round(y))), (0, 0, 255), cv2.MARKER_CROSS, r, 1)
    return out


def write_overlay(path: Path, gray: np.ndarray, detection: Detection) -> None:
    ok, buf = cv2.imencode(path.suffix or ".jpg", draw_overlay(gray, detection))
    if not ok:
        raise OSError(f"{path}: OpenCV cannot encode this format")
    write_atomic(path, buf.tobytes())
