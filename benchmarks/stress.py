"""Stress benchmark: ccdn and peer detectors side by side on renders with exact labels, one subset per condition.

Every subset starts from a calm scene (one board, squares 15-60 px, tilt <= 40 deg, pinhole lens, no blur,
noise, JPEG or lighting effects, dark-on-light) and forces one condition on, at full strength:
fisheye, strong barrel distortion, motion blur, defocus, heavy noise, low contrast, darkness, glare,
small squares (6-10 px), extreme pose (tilt 60-75 deg), inverted intensity, two boards, partial boards
(large squares running off the frame), occluders, no board, a deep shadow (a polygon taking 80-95 %
of the light, its edge blurred 1-15 px: the lit part of a board 5-20x the contrast of its shaded
part), markers (a ChArUco-style board: a random 5 x 5-bit marker with a dark border, 0.6-0.8 of the
square's side, in every light square; the labels are the checker corners), close-ups (squares of
100-200 px: a few squares fill the frame, running off it, their size changing from one to the next
with perspective), fisheye close-ups (the same through a fisheye lens: 100-200 px at the centre,
thinning to a few px at the rim). Blur kernels and glare keep the renderer's own ranges (motion 3-9
px, defocus radius 1-3 px).

A render joins its subset only if it shows that condition and no other (`shows_condition`): the board
wholly in frame (its outer squares too, as OpenCV needs) with every inner corner countable; except that
two boards need only their inner corners in frame and may overlap, occluded boards must have a hidden
corner, and partial boards and (fisheye) close-ups a corner outside the frame. No two corners may be
closer than 3 px (too close to tell apart). Subset k tries seeds 7_000_000 + 10_000 k + i, i = 0, 1,
... in order (disjoint from every training and accuracy seed); adding a subset at the end keeps the
others' images.

All detectors (benchmarks/peers.py) run on the same images in one run. Metrics are the paper's
(benchmarks/accuracy.py, 5 px radius), with the renderer's ignored corners (occluded, at the border)
counted neither way. Where two corners are closer than 10 px (small squares, steep tilt) the radius
shrinks to half their distance (so >= 1.5 px): one detection can then hit one corner only. Times are
per image, median over the subset, after one warm-up call. For detectors that index their corners
(ccdn's boards) the run also counts boards whose (row, col) disagree with the render's grid: a
wrongly indexed board silently corrupts a calibration. Steep views and small squares have corners a
person can hardly see: each labelled corner's squares are measured (their narrowest width across,
from the labels' lattice) and the missed share is also given per width class (`WIDTH_CLASSES`).
Likewise per situation (`SITUATIONS`, from the labels alone): a corner in plain view, one beside a
corner the render does not show (under an occluder or another board, or off the frame), one in a
visible piece of its board under PIECE_CORNERS corners, one of squares under THIN_PX across; so a
subset's misses tell corners anyone sees from those only a lattice's continuation vouches for.

    python benchmarks/stress.py [--per-subset 20] [--subsets clean noise] [--detectors ccdn opencv]
    python benchmarks/stress.py --skip 20   # the next 20 per subset: a held-out sample of the same conditions
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
from ccdn.checker import altitude
from ccdn.models import COARSE_MODEL_HELP, DEFAULT_HELP
from ccdn_training.synth import PAPER_BOARDS, Scene, SceneConfig, render_scene
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).parent))
from machine import cpu_name  # noqa: E402
from accuracy import MATCH_RADIUS, format_table, match, same_indexing, summarise  # noqa: E402
from peers import DETECTORS, Adapter, BoardSize, load_adapters  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SEED_BASE = 7_000_000
SEEDS_PER_SUBSET = 10_000
MIN_SPACING_PX = 3.0
WIDTH_CLASSES = ((0.0, 4.0), (4.0, 6.0), (6.0, np.inf))  # px across a corner's narrowest square
WIDTH_NAMES = tuple(f"{low:g}-{high:g} px" if np.isfinite(high) else f">= {low:g} px" for low, high in WIDTH_CLASSES)
THIN_PX = WIDTH_CLASSES[0][1]  # squares thinner than this across: a steep view's slivers
PIECE_CORNERS = 8  # a visible piece of a board under this many corners: too few to link into a board (ccdn's least)
SITUATIONS = ("open", "beside a hidden corner", f"in a piece under {PIECE_CORNERS} corners",
              f"squares under {THIN_PX:g} px")  # label_situations' classes, in its order
_LATTICE_STEPS = ((-1, 0), (1, 0), (0, -1), (0, 1))
CALM = dict(p_no_board=0.0, p_two_boards=0.0, square_px=(15.0, 60.0), max_tilt_deg=40.0, p_radial=0.0, p_fisheye=0.0,
            p_occluder=0.0, p_invert=0.0, p_blur=0.0, p_motion=0.0, p_defocus=0.0, p_noise=0.0, p_jpeg=0.0,
            p_low_contrast=0.0, p_dark=0.0, p_glare=0.0, p_shadow=0.0)
SUBSETS: dict[str, dict] = {  # name -> SceneConfig fields changed from CALM; order fixes the seeds
    "clean": {},
    "fisheye": {"p_fisheye": 1.0},
    "radial": {"p_radial": 1.0, "radial_k1": (0.25, 0.45)},
    "motion-blur": {"p_motion": 1.0},
    "defocus": {"p_defocus": 1.0},
    "noise": {"p_noise": 1.0, "noise_sigma": (0.04, 0.1)},
    "low-contrast": {"p_low_contrast": 1.0},
    "dark": {"p_dark": 1.0},
    "glare": {"p_glare": 1.0},
    "small-squares": {"square_px": (6.0, 10.0)},
    "extreme-pose": {"min_tilt_deg": 60.0, "max_tilt_deg": 75.0},
    "inverted": {"p_invert": 1.0},
    "two-boards": {"p_two_boards": 1.0},
    "partial": {"square_px": (45.0, 110.0)},
    "occluded": {"p_occluder": 1.0},
    "no-board": {"p_no_board": 1.0},
    "shadow": {"p_shadow": 1.0, "shadow_depth": (0.8, 0.95)},
    "markers": {"p_markers": 1.0},
    "close-up": {"square_px": (100.0, 200.0)},
    "fisheye-close-up": {"square_px": (100.0, 200.0), "p_fisheye": 1.0},
}


def _extend(grid: np.ndarray, axis: int) -> np.ndarray:
    """One more grid line of points on each side along `axis`, extrapolated linearly."""
    first = 2 * np.take(grid, [0], axis) - np.take(grid, [1], axis)
    last = 2 * np.take(grid, [-1], axis) - np.take(grid, [-2], axis)
    return np.concatenate([first, grid, last], axis)


def squares_in_frame(scene: Scene) -> bool:
    """Whether the outer squares of every board, one square beyond its labelled inner corners, lie in the image."""
    h, w = scene.image.shape
    for b, (cols, rows) in enumerate(scene.boards):
        mine = scene.board_index == b
        if mine.sum() != cols * rows:
            return False
        grid = np.zeros((rows, cols, 2))
        grid[scene.grid[mine, 0], scene.grid[mine, 1]] = scene.corners[mine]
        outer = _extend(_extend(grid, 0), 1).reshape(-1, 2)
        if np.any((outer < -0.5) | (outer > [w - 0.5, h - 0.5])):
            return False
    return True


def square_widths(scene: Scene) -> np.ndarray:
    """(M,) per labelled corner, the narrowest width across of the squares around it that the labels
    span (a cell's lesser parallelogram height: a steep view thins squares to slivers); inf where none."""
    index = {(b, r, c): k for k, (b, (r, c)) in enumerate(zip(scene.board_index.tolist(), scene.grid.tolist()))}
    corner, along_rows, along_cols = [], [], []  # each labelled cell: its corner and its two neighbours
    for k, (b, (r, c)) in enumerate(zip(scene.board_index.tolist(), scene.grid.tolist())):
        for dr, dc in ((-1, -1), (-1, 1), (1, -1), (1, 1)):
            if (b, r + dr, c) in index and (b, r, c + dc) in index:
                corner.append(k), along_rows.append(index[(b, r + dr, c)]), along_cols.append(index[(b, r, c + dc)])
    widths = np.full(len(scene.corners), np.inf)
    if corner:
        xy = scene.corners.astype(np.float64)
        np.minimum.at(widths, corner, altitude(xy[along_rows] - xy[corner], xy[along_cols] - xy[corner]))
    return widths


def width_classes(widths: np.ndarray) -> np.ndarray:
    """(M,) each corner's WIDTH_CLASSES index from its square_widths, -1 where none applies (a corner
    without a labelled square around it)."""
    classes = np.full(len(widths), -1)
    for k, (low, high) in enumerate(WIDTH_CLASSES):
        classes[(widths >= low) & (widths < high)] = k
    return classes


def label_situations(scene: Scene, widths: np.ndarray) -> np.ndarray:
    """(M,) each labelled corner's SITUATIONS index, from the labels alone (widths: square_widths):
    squares under THIN_PX across; else in a piece under PIECE_CORNERS corners (the corners of its
    board the render shows, linked along rows and columns: a board behind another falls apart into
    such pieces); else beside a hidden corner (a row or column neighbour inside its board that the
    render does not show: under an occluder or another board, or off the frame); else open."""
    visible = {(b, r, c): k for k, (b, (r, c)) in enumerate(zip(scene.board_index.tolist(), scene.grid.tolist()))}
    hidden = np.zeros(len(scene.corners), bool)
    piece = np.zeros(len(scene.corners), np.int64)  # how many corners each one's piece holds
    for (b, r, c), k in visible.items():
        cols, rows = scene.boards[b]
        hidden[k] = any(0 <= r + dr < rows and 0 <= c + dc < cols and (b, r + dr, c + dc) not in visible
                        for dr, dc in _LATTICE_STEPS)
    unseen = set(visible)
    while unseen:  # each piece by a flood fill over the visible corners
        stack = [unseen.pop()]
        members = []
        while stack:
            b, r, c = stack.pop()
            members.append(visible[(b, r, c)])
            for dr, dc in _LATTICE_STEPS:
                if (b, r + dr, c + dc) in unseen:
                    unseen.remove((b, r + dr, c + dc))
                    stack.append((b, r + dr, c + dc))
        piece[members] = len(members)
    situation = hidden.astype(np.int64)
    situation[piece < PIECE_CORNERS] = 2
    situation[widths < THIN_PX] = 3
    return situation


def closest_spacing(scene: Scene) -> float:
    """Distance in px of the two closest corners, labelled or ignored (inf with fewer than two)."""
    points = np.concatenate([scene.corners, scene.ignore]).astype(np.float64)
    if len(points) < 2:
        return np.inf
    d = np.linalg.norm(points[:, None] - points[None], axis=2)
    np.fill_diagonal(d, np.inf)
    return float(d.min())


def shows_condition(name: str, scene: Scene) -> bool:
    """Whether a render shows its subset's condition and no other (see the module docstring)."""
    if closest_spacing(scene) < MIN_SPACING_PX:
        return False
    total = sum(cols * rows for cols, rows in scene.boards)
    in_frame = len(scene.corners) + len(scene.ignore) == total  # corners outside the image are in neither
    if name in ("partial", "close-up", "fisheye-close-up"):
        return len(scene.corners) > 0 and not in_frame
    if name == "occluded":
        return in_frame and len(scene.ignore) > 0
    if name == "two-boards":
        return in_frame
    return len(scene.corners) == total and squares_in_frame(scene)


def match_radius(scene: Scene) -> float:
    """The paper's 5 px, or half the distance of the two closest corners if less (one detection, one corner)."""
    return min(MATCH_RADIUS, 0.5 * closest_spacing(scene))


def render_subset(name: str, count: int, skip: int = 0) -> tuple[list[tuple[int, Scene]], int]:
    """`count` (seed, scene) of a subset that show its condition, after the first `skip` that do (a
    held-out sample: a change judged on one sample can be checked on another), and how many seeds were tried."""
    cfg = SceneConfig(**{**CALM, **SUBSETS[name]})
    first = SEED_BASE + SEEDS_PER_SUBSET * list(SUBSETS).index(name)
    kept = []
    for seed in range(first, first + SEEDS_PER_SUBSET):
        scene = render_scene(np.random.default_rng(seed), cfg)
        if shows_condition(name, scene):
            kept.append((seed, scene))
            if len(kept) == skip + count:
                return kept[skip:], seed - first + 1
    raise RuntimeError(f"subset {name}: only {len(kept)} of {skip + count} scenes in its {SEEDS_PER_SUBSET} seeds")


def wrongly_indexed(boards: list[tuple[np.ndarray, np.ndarray]], scene: Scene, radius: float) -> tuple[int, int]:
    """(boards checked, boards whose (row, col) disagree with the render's): a board's corners that
    hit labels must lie on one true board and map to its grid by one of the 8 symmetries plus an
    offset, as on real-dev (accuracy.board_recovered); boards hitting fewer than 4 labels are skipped."""
    checked = wrong = 0
    if len(scene.corners) == 0:  # a board on a frame without one: its corners count as false positives
        return checked, wrong
    for grid, xy in boards:
        d = np.linalg.norm(xy[:, None] - scene.corners[None], axis=2)
        hit = d.min(1) < radius
        if hit.sum() < 4:
            continue
        label = d.argmin(1)[hit]
        true = scene.grid[label]
        consistent = len(set(scene.board_index[label])) == 1 and same_indexing(grid[hit], true)
        checked, wrong = checked + 1, wrong + (not consistent)
    return checked, wrong


def opencv_size(scene: Scene, fallback: BoardSize) -> BoardSize:
    """The true size of the scene's most visible board (OpenCV needs one), or `fallback` without a board."""
    if not scene.boards:
        return fallback
    return scene.boards[int(np.bincount(scene.board_index, minlength=len(scene.boards)).argmax())]


def most_common_size(scenes: list[Scene]) -> BoardSize:
    """The board size seen most often (ties: first seen); the first paper board when there is none."""
    sizes = Counter(size for scene in scenes for size in scene.boards)
    return sizes.most_common(1)[0][0] if sizes else PAPER_BOARDS[0]


def evaluate(sets: dict[str, list[tuple[int, Scene]]], adapters: list[Adapter], show_bar: bool) -> dict:
    """Match every adapter's detections on every scene; per-subset summaries, times and per-image rows."""
    fallback = most_common_size([scene for scenes in sets.values() for _, scene in scenes])
    _, first = next(pair for scenes in sets.values() for pair in scenes)
    for adapter in adapters:  # warm-up: sessions, caches, lazy initialisation
        adapter.detect(first.image, opencv_size(first, fallback))
    subsets, per_image = {}, []
    pooled: dict[str, list[dict]] = {a.name: [] for a in adapters}
    pooled_ms: dict[str, list[float]] = {a.name: [] for a in adapters}
    bar = tqdm(total=sum(map(len, sets.values())) * len(adapters), unit="det", disable=not show_bar, file=sys.stderr)
    for name, scenes in sets.items():
        radii = [match_radius(scene) for _, scene in scenes]
        widths = [square_widths(scene) for _, scene in scenes]  # the labels', alike for every detector
        classes = [(width_classes(width), label_situations(scene, width))
                   for (_, scene), width in zip(scenes, widths)]
        subsets[name] = {"overrides": SUBSETS[name], "min_radius_px": min(radii), "detectors": {}}
        for adapter in adapters:
            rows, times = [], []
            for (seed, scene), radius, (width, situation) in zip(scenes, radii, classes):
                t0 = time.perf_counter()
                xy = adapter.detect(scene.image, opencv_size(scene, fallback))
                times.append((time.perf_counter() - t0) * 1e3)
                rows.append(match(xy, scene.corners, scene.ignore, radius))
                rows[-1]["missed_by_width"] = missed_by_class(xy, scene, width, len(WIDTH_CLASSES), radius)
                rows[-1]["missed_by_situation"] = missed_by_class(xy, scene, situation, len(SITUATIONS), radius)
                if adapter.boards is not None:
                    rows[-1]["boards"], rows[-1]["wrong_index_boards"] = wrongly_indexed(adapter.boards(), scene, radius)
                per_image.append({"subset": name, "seed": seed, "detector": adapter.name, "ms": times[-1],
                                  "radius_px": radius,
                                  **{k: v for k, v in rows[-1].items()
                                     if k not in ("errors", "missed_by_width", "missed_by_situation")}})
                bar.update()
            by_class = {f"missed_by_{what}": class_summary(rows, f"missed_by_{what}", names)
                        for what, names in (("width", WIDTH_NAMES), ("situation", SITUATIONS))}
            subsets[name]["detectors"][adapter.name] = {**summarise(rows), **by_class,
                                                        "median_ms": float(np.median(times)),
                                                        "p90_ms": float(np.percentile(times, 90))}
            pooled[adapter.name] += rows
            pooled_ms[adapter.name] += times
    bar.close()
    overall = {name: {**summarise(rows), "median_ms": float(np.median(pooled_ms[name])),
                      "p90_ms": float(np.percentile(pooled_ms[name], 90))} for name, rows in pooled.items()}
    return {"subsets": subsets, "all": overall, "per_image": per_image,
            "opencv_board_size": f"true size of the scene's most visible board; boardless scenes: {fallback}, "
                                 "the run's most common size"}


def missed_by_class(xy: np.ndarray, scene: Scene, classes: np.ndarray, count: int,
                    radius: float) -> list[tuple[int, int]]:
    """(labels, missed) for each class 0..count-1 of the scene's corners (classes (M,): width_classes or
    label_situations): each class's corners matched as the only labels, the other corners ignored (a
    detection near them counts neither way)."""
    counts = []
    for k in range(count):
        inside = classes == k
        others = np.concatenate([scene.ignore.reshape(-1, 2), scene.corners[~inside]])
        counts.append((int(inside.sum()), match(xy, scene.corners[inside], others, radius)["missed"]))
    return counts


def class_summary(rows: list[dict], key: str, names: tuple[str, ...]) -> dict[str, dict]:
    """Per class (by name): its labels and the missed share of them over a subset's images (rows'
    missed_by_class counts under `key`)."""
    out = {}
    for k, name in enumerate(names):
        labels = sum(r[key][k][0] for r in rows)
        missed = sum(r[key][k][1] for r in rows)
        out[name] = {"labels": labels, "missed_pct": 100.0 * missed / labels if labels else None}
    return out


def format_classes(result: dict) -> str:
    """Missed % per width class, for the subsets with corners of squares under the widest class, and per
    situation, for the subsets where a detector missed any corner."""
    lines = []
    for name, sub in result["subsets"].items():
        for det, s in sub["detectors"].items():
            thin = sum(c["labels"] for c in list(s["missed_by_width"].values())[:-1])
            for what, title, shown in (("width", "square width across", thin),
                                       ("situation", "situation", s["missed_pct"])):
                if shown:
                    cells = ", ".join(f"{key}: {c['missed_pct']:.1f} % of {c['labels']}"
                                      for key, c in s[f"missed_by_{what}"].items() if c["labels"])
                    lines.append(f"{name:<14}{det:<16}missed by {title}: {cells}")
    return "\n".join(lines)


def format_results(result: dict) -> str:
    """accuracy.py's table, one row per subset and detector (then each detector over all), plus median ms."""
    rows = {f"{name:<14}{det}": s for name, sub in result["subsets"].items() for det, s in sub["detectors"].items()}
    rows.update({f"{'all':<14}{det}": s for det, s in result["all"].items()})
    lines = format_table(rows).splitlines()
    lines[0] += f"{'ms':>8}"
    lines[1] += "-" * 8
    lines[2:] = [line + f"{s['median_ms']:>8.1f}" for line, s in zip(lines[2:], rows.values())]
    for det, s in result["all"].items():
        if "wrong_index_boards" in s:
            where = ", ".join(f"{name} {sub['detectors'][det]['wrong_index_boards']}"
                              for name, sub in result["subsets"].items() if sub["detectors"][det]["wrong_index_boards"])
            lines.append(f"{det} boards with wrong (row, col): {s['wrong_index_boards']} of {s['boards']}"
                         + (f" ({where})" if where else ""))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", default=None,
                        help=f"ccdn: bundled model name or .onnx path ({DEFAULT_HELP})")
    parser.add_argument("--coarse-model", default=None, help=COARSE_MODEL_HELP)
    parser.add_argument("--threads", type=int, default=None, help="ccdn and OpenCV threads (default: each library's)")
    parser.add_argument("--fast-check", action="store_true",
                        help="ccdn: Detector(fast_check=True), no full-resolution pass after shrunk passes without a board")
    parser.add_argument("--exhaustive", action="store_true",
                        help="ccdn: Detector(exhaustive=True), a stretched look at every loose cluster of peaks")
    parser.add_argument("--per-subset", type=int, default=20, help="images per subset")
    parser.add_argument("--skip", type=int, default=0,
                        help="leave out each subset's first SKIP images (--skip 20: a held-out sample)")
    parser.add_argument("--subsets", nargs="+", choices=list(SUBSETS), default=list(SUBSETS))
    parser.add_argument("--detectors", nargs="+", choices=DETECTORS, default=DETECTORS)
    parser.add_argument("--json", type=Path, default=ROOT / "out" / "stress.json")
    args = parser.parse_args(argv)
    if args.per_subset < 1 or args.skip < 0:
        parser.error("--per-subset must be at least 1 and --skip at least 0")

    t0 = time.time()
    show_bar = sys.stderr.isatty()
    rendered = {name: render_subset(name, args.per_subset, args.skip)
                for name in tqdm(args.subsets, unit="subset", desc="render", disable=not show_bar, file=sys.stderr)}
    adapters, skipped = load_adapters(args.detectors, args.model, args.threads, args.fast_check, args.exhaustive,
                                      args.coarse_model)
    result = evaluate({name: scenes for name, (scenes, _) in rendered.items()}, adapters, show_bar)
    for name, (_, tried) in rendered.items():
        result["subsets"][name]["seeds_tried"] = tried
    result["config"] = {"per_subset": args.per_subset, "skip": args.skip, "calm": CALM,
                        "seeds": f"tried in order from {SEED_BASE} + {SEEDS_PER_SUBSET} * subset index",
                        "match_radius_px": MATCH_RADIUS, "min_spacing_px": MIN_SPACING_PX, "threads": args.threads,
                        "detectors": {a.name: a.note for a in adapters}, "skipped": skipped,
                        "machine": cpu_name(), "cpus": os.cpu_count(),
                        "python": platform.python_version(), "seconds": round(time.time() - t0, 1)}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=1))
    print(format_results(result))
    print(format_classes(result))
    for name, note in {**result["config"]["detectors"], **skipped}.items():
        print(f"{name}: {note}")
    print(f"opencv board size: {result['opencv_board_size']}")
    print(f"written {args.json}")


if __name__ == "__main__":
    main()
