"""Render the small example images the project ships in examples/ (with their exact labels)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from .synth import SceneConfig, render_scene

CALM = dict(p_occluder=0.0, p_glare=0.0, p_shadow=0.0, p_dark=0.0, p_low_contrast=0.0, p_motion=0.0, p_defocus=0.0,
            p_jpeg=0.0, noise_sigma=(0.0, 0.02), square_px=(22.0, 40.0), max_tilt_deg=45.0)
EXAMPLES = {
    "board": (1, SceneConfig(p_no_board=0.0, p_two_boards=0.0, p_radial=0.0, p_fisheye=0.0, board_sizes=[(9, 6)], **CALM)),
    "distorted": (23, SceneConfig(p_no_board=0.0, p_two_boards=0.0, p_radial=1.0, p_fisheye=0.0, board_sizes=[(7, 11)], **CALM)),
    "fisheye": (5, SceneConfig(p_no_board=0.0, p_two_boards=0.0, p_fisheye=1.0, board_sizes=[(9, 9)], **CALM)),
    "two-boards": (1, SceneConfig(p_no_board=0.0, p_two_boards=1.0, p_radial=0.0, p_fisheye=0.0, board_sizes=[(7, 7), (6, 9)],
                                 **{**CALM, "square_px": (14.0, 24.0)})),
    "no-board": (3, SceneConfig(p_no_board=1.0)),
}


def write_examples(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    labels = []
    for name, (seed, cfg) in EXAMPLES.items():
        scene = render_scene(np.random.default_rng(seed), cfg)
        cv2.imwrite(str(out / f"{name}.jpg"), scene.image, [cv2.IMWRITE_JPEG_QUALITY, 92])
        labels.append({"file": f"{name}.jpg", "seed": seed, "boards": [list(b) for b in scene.boards],
                       "corners": np.round(scene.corners, 4).tolist(), "board_index": scene.board_index.tolist(),
                       "grid": scene.grid.tolist()})
    (out / "labels.json").write_text(json.dumps({"images": labels}, indent=1) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description="Render the bundled example images.")
    parser.add_argument("--out", type=Path, default=Path("examples"))
    write_examples(parser.parse_args().out)


if __name__ == "__main__":
    main()
