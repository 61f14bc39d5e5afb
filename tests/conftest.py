"""Shared fixtures: the bundled examples with exact labels, real-dev photos when ../shared is present."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
REAL_DEV = ROOT.parent / "shared" / "data" / "real-dev"


@pytest.fixture(scope="session")
def examples() -> dict[str, dict]:
    """name -> {"path", "corners" (N, 2), "boards"} for the bundled rendered examples."""
    meta = json.loads((EXAMPLES / "labels.json").read_text())["images"]
    return {Path(m["file"]).stem: {"path": EXAMPLES / m["file"], "corners": np.asarray(m["corners"], np.float64).reshape(-1, 2),
                                   "boards": m["boards"]} for m in meta}


@pytest.fixture(scope="session")
def real_dev() -> list[dict]:
    if not (REAL_DEV / "labels.json").is_file():
        pytest.skip("../shared/data/real-dev is absent")
    meta = json.loads((REAL_DEV / "labels.json").read_text())["images"]
    return [{"path": REAL_DEV / "images" / m["file"], "source": m["source"],
             "corners": np.concatenate([np.asarray(b["corners"], np.float64).reshape(-1, 2) for b in m["boards"]])}
            for m in meta]


@pytest.fixture(scope="session")
def detector():
    import ccdn

    return ccdn.Detector(threads=2)


def nearest_distances(found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """For each true point, the distance to the nearest found point (inf if none)."""
    if len(found) == 0:
        return np.full(len(truth), np.inf)
    return np.linalg.norm(truth[:, None] - found[None].astype(np.float64), axis=2).min(1)
