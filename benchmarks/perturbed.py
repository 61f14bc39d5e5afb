"""Real photos under the changes a user's camera and pipeline make: ../shared/data/real-dev, each photo
perturbed, the paper's metrics and the boards recovered per perturbation (benchmarks/accuracy.py's).

The renders of benchmarks/stress.py isolate one condition each with exact labels; this asks the same
of real photos, whose labels move with the image: darker (x 0.2), lower contrast (a quarter, about
mid-grey), deep shade (gamma 2.5: the dark half of a board darkens far more than the lit half),
noise (sigma 12 grey levels, seeded per photo), Gaussian blur (sigma 2.5 px), horizontal motion
blur (9 px), rotated by 90 degrees, halved (area mean), a quality-25 JPEG, inverted. Evaluation
only: no threshold is chosen on these photos.

    python benchmarks/perturbed.py [--perturbations identity rot90] [--limit 46] [--json out/perturbed.json]
"""

from __future__ import annotations

import argparse
import time
import zlib
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

import ccdn
from ccdn.models import DEFAULT_HELP

from accuracy import REAL_DEV, ROOT, photo_counts, real_dev_cases, summarise, write_report
from machine import cpu_name

Perturbation = Callable[[np.ndarray, np.ndarray, int], tuple[np.ndarray, np.ndarray]]  # (gray, labels, seed)


def _scaled(factor: float, around: float = 0.0) -> Perturbation:
    """Grey levels scaled by factor about `around`."""
    return lambda gray, labels, seed: (np.clip(around + (gray - around) * factor, 0, 255).astype(np.uint8), labels)


def _gamma(gray: np.ndarray, labels: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    return np.clip(255 * (gray / 255.0) ** 2.5, 0, 255).astype(np.uint8), labels


def _noise(gray: np.ndarray, labels: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    noisy = gray + np.random.default_rng(seed).normal(0, 12, gray.shape)
    return np.clip(noisy, 0, 255).astype(np.uint8), labels


def _blur(gray: np.ndarray, labels: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    return cv2.GaussianBlur(gray, (0, 0), 2.5), labels


def _motion(gray: np.ndarray, labels: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    kernel = np.zeros((9, 9), np.float32)
    kernel[4] = 1 / 9  # odd length: centred, no half-pixel shift
    return cv2.filter2D(gray, -1, kernel), labels


def _rot90(gray: np.ndarray, labels: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Rotated 90 degrees counter-clockwise: pixel (x, y) goes to (y, w - 1 - x)."""
    w = gray.shape[1]
    return np.ascontiguousarray(np.rot90(gray)), np.stack([labels[:, 1], w - 1 - labels[:, 0]], 1)


def _half(gray: np.ndarray, labels: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    h, w = gray.shape
    return cv2.resize(gray, (w // 2, h // 2), interpolation=cv2.INTER_AREA), (labels + 0.5) / 2 - 0.5


def _jpeg(gray: np.ndarray, labels: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    return cv2.imdecode(cv2.imencode(".jpg", gray, [cv2.IMWRITE_JPEG_QUALITY, 25])[1], cv2.IMREAD_GRAYSCALE), labels


PERTURBATIONS: dict[str, Perturbation] = {
    "identity": lambda gray, labels, seed: (gray, labels),
    "dark x0.2": _scaled(0.2),
    "contrast x0.25": _scaled(0.25, 128.0),
    "gamma 2.5": _gamma,
    "noise 12": _noise,
    "blur 2.5": _blur,
    "motion 9": _motion,
    "rot90": _rot90,
    "half": _half,
    "jpeg 25": _jpeg,
    "inverted": lambda gray, labels, seed: (255 - gray, labels),
}


def evaluate(detector: ccdn.Detector, names: list[str], limit: int) -> dict:
    """Per perturbation: accuracy.summarise's figures, with the boards recovered and spurious (as
    accuracy.py counts them), and per-image rows."""
    cases = list(real_dev_cases())[:limit]
    photos = [(name, cv2.imread(str(path), cv2.IMREAD_GRAYSCALE), labels, sizes) for _, name, path, labels, sizes in cases]
    groups, per_image = {}, []
    for perturbation in names:
        rows = []
        for photo, gray, labels, sizes in photos:
            image, moved = PERTURBATIONS[perturbation](gray, labels, zlib.crc32(photo.encode()))
            row = photo_counts(detector.detect(image), moved, sizes)
            rows.append(row)
            per_image.append({"perturbation": perturbation, "file": photo,
                              **{k: v for k, v in row.items() if k != "errors"}})
        groups[perturbation] = summarise(rows)
    return {"groups": groups, "per_image": per_image}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", default=None, help=f"bundled model name or .onnx path ({DEFAULT_HELP})")
    parser.add_argument("--perturbations", nargs="+", choices=list(PERTURBATIONS), default=list(PERTURBATIONS))
    parser.add_argument("--limit", type=int, default=None, help="only the first LIMIT photos")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--json", type=Path, default=ROOT / "out" / "perturbed.json")
    args = parser.parse_args(argv)
    if not (REAL_DEV / "labels.json").is_file():
        raise SystemExit(f"no real-dev photos at {REAL_DEV}: nothing to perturb")
    detector = ccdn.Detector(args.model, args.threads)
    t0 = time.time()
    result = evaluate(detector, args.perturbations, args.limit)
    result["config"] = {"model": detector.models, "version": detector.model.version, "machine": cpu_name(),
                        "seconds": round(time.time() - t0, 1)}
    write_report(result, args.json)


if __name__ == "__main__":
    main()
