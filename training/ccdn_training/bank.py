"""A bank of rendered scenes saved to one .npz, and random training crops drawn from it.

Rendering costs ~0.2 s a scene on this CPU, so scenes are rendered once (in parallel) and the
training loop draws many crops of each, with rotations by 90 degrees and flips.
"""

from __future__ import annotations

import argparse
import json
from concurrent.futures import ProcessPoolExecutor
from functools import partial
from pathlib import Path

import numpy as np

from .synth import SceneConfig, render_scene


def _render(seed: int, overrides: dict):
    scene = render_scene(np.random.default_rng(seed), SceneConfig(**overrides))
    return scene.image, scene.corners, scene.ignore


def build_bank(path: Path, count: int, seed: int, workers: int, overrides: dict | None = None) -> None:
    """Render `count` scenes with seeds seed..seed+count-1 (SceneConfig fields changed by
    `overrides`, e.g. a bank of steep poses) and save them to `path`."""
    with ProcessPoolExecutor(workers) as pool:
        scenes = list(pool.map(partial(_render, overrides=overrides or {}), range(seed, seed + count), chunksize=8))
    images = np.stack([s[0] for s in scenes])
    corners = [s[1] for s in scenes]
    ignore = [s[2] for s in scenes]
    np.savez_compressed(
        path,
        images=images,
        corners=np.concatenate(corners),
        corner_counts=np.array([len(c) for c in corners]),
        ignore=np.concatenate(ignore),
        ignore_counts=np.array([len(c) for c in ignore]),
        seed=seed,
    )


class SceneBank:
    """Scenes loaded from one or more bank files: images (N, H, W) uint8, per-scene corners and
    ignored corners."""

    def __init__(self, *paths: Path) -> None:
        images, self.corners, self.ignore = [], [], []
        for path in paths:
            data = np.load(path)
            images.append(data["images"])
            self.corners += np.split(data["corners"], np.cumsum(data["corner_counts"])[:-1])
            self.ignore += np.split(data["ignore"], np.cumsum(data["ignore_counts"])[:-1])
        self.images = np.concatenate(images)

    def __len__(self) -> int:
        return len(self.images)

    def crops(self, rng: np.random.Generator, batch: int, size: int) -> tuple[np.ndarray, np.ndarray]:
        """(batch, size, size) float32 crops in [0, 1] and targets (1 corner, 0 not, -1 ignored).

        The pixel nearest each corner is 1 and its 8 neighbours are ignored (a corner between two
        pixels is no error on either); most crops are centred near a corner; a third touch an image border so the network learns
        what the zero padding looks like; each is rotated by a random multiple of 90 deg and flipped.
        """
        xs = np.empty((batch, size, size), np.float32)
        ys = np.empty((batch, size, size), np.float32)
        for b in range(batch):
            i = int(rng.integers(len(self)))
            image, corners = self.images[i], self.corners[i]
            h, w = image.shape
            if len(corners) and rng.random() < 0.7:
                cx, cy = corners[rng.integers(len(corners))] + rng.uniform(-size / 2, size / 2, 2)
                x0, y0 = int(cx - size / 2), int(cy - size / 2)
            else:
                x0, y0 = int(rng.integers(0, w - size + 1)), int(rng.integers(0, h - size + 1))
            if rng.random() < 0.35:
                x0 = 0 if rng.random() < 0.5 else w - size
            if rng.random() < 0.35:
                y0 = 0 if rng.random() < 0.5 else h - size
            x0, y0 = int(np.clip(x0, 0, w - size)), int(np.clip(y0, 0, h - size))
            target = np.zeros((size, size), np.float32)
            _stamp(target, self.ignore[i], x0, y0, -1.0, radius=1)
            _stamp(target, corners, x0, y0, -1.0, radius=1)  # a corner's 8 neighbours: neither class
            _stamp(target, corners, x0, y0, 1.0, radius=0)
            crop = image[y0 : y0 + size, x0 : x0 + size].astype(np.float32) / 255
            k = int(rng.integers(4))
            crop, target = np.rot90(crop, k), np.rot90(target, k)
            if rng.random() < 0.5:
                crop, target = crop[:, ::-1], target[:, ::-1]
            xs[b], ys[b] = crop, target
        return xs, ys


def _stamp(target: np.ndarray, points: np.ndarray, x0: int, y0: int, value: float, radius: int) -> None:
    """Set `value` at the pixel nearest each point (and its neighbours within `radius`)."""
    if len(points) == 0:
        return
    px = np.rint(points[:, 0]).astype(int) - x0
    py = np.rint(points[:, 1]).astype(int) - y0
    h, w = target.shape
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            qx, qy = px + dx, py + dy
            ok = (qx >= 0) & (qx < w) & (qy >= 0) & (qy < h)
            target[qy[ok], qx[ok]] = value


def main() -> None:
    parser = argparse.ArgumentParser(description="Render a bank of synthetic training scenes.")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--count", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--config", type=json.loads, default={},
                        help='SceneConfig fields to change, as JSON, e.g. \'{"min_tilt_deg": 50, "max_tilt_deg": 78}\'')
    args = parser.parse_args()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    build_bank(args.out, args.count, args.seed, args.workers, args.config)


if __name__ == "__main__":
    main()
