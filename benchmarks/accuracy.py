"""Accuracy benchmark: the paper's metrics on real photos (../shared/data/real-dev) and on renders.

Metrics (paper section 4, 5 px match radius): each label's nearest detection within 5 px is a hit
(accuracy: its distance in px, mean and 95th percentile; ">1px": how many hits lie over a pixel
off, the outliers that harm a calibration); a label without one is missed; further
detections within 5 px of an already-hit label are doubles; detections near no label are false
positives (renders: detections near a deliberately ignored, e.g. occluded, corner are not counted).
Reported per source and overall, with precision and recall. On real-dev also the boards (grid
recovery): an image counts as recovered when the detection's largest board has the labelled size
(either way round) and every one of its corners that matches a label carries that label's (row, col)
up to one of the board's 8 symmetries (labels are row-major); a spurious board is any further board.

    python benchmarks/accuracy.py [--model paper] [--refinement saddle] [--json out/accuracy.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

import ccdn
from ccdn.models import COARSE_MODEL_HELP, DEFAULT_HELP

from machine import cpu_name

ROOT = Path(__file__).resolve().parents[1]
REAL_DEV = ROOT.parent / "shared" / "data" / "real-dev"
MATCH_RADIUS = 5.0


def match(det: np.ndarray, labels: np.ndarray, ignore: np.ndarray | None = None, radius: float = MATCH_RADIUS) -> dict:
    """Counts and hit distances of one image's detections (N, 2) against its labels (M, 2).

    Detections and labels are paired one-to-one, closest pairs first, within `radius`; an unpaired
    detection within `radius` of a label is a double, one farther from every label a false positive.
    """
    det = det.reshape(-1, 2).astype(np.float64)
    labels = labels.reshape(-1, 2).astype(np.float64)
    if ignore is not None and len(ignore) and len(det):
        near_ignored = np.linalg.norm(det[:, None] - ignore[None], axis=2).min(1) < radius
        far_from_labels = (np.linalg.norm(det[:, None] - labels[None], axis=2).min(1) >= radius
                           if len(labels) else np.ones(len(det), bool))
        det = det[~(near_ignored & far_from_labels)]
    out = {"labels": len(labels), "detections": len(det), "hits": 0, "missed": len(labels), "double": 0,
           "false_positives": len(det), "errors": []}
    if len(det) == 0 or len(labels) == 0:
        return out
    d = np.linalg.norm(det[:, None] - labels[None], axis=2)  # (N, M)
    # one-to-one: closest pairs first, each detection and each label used once
    di, li = np.nonzero(d < radius)
    det_used, label_used = np.zeros(len(det), bool), np.zeros(len(labels), bool)
    for k in np.argsort(d[di, li], kind="stable"):
        i, j = di[k], li[k]
        if not det_used[i] and not label_used[j]:
            det_used[i] = label_used[j] = True
            out["errors"].append(float(d[i, j]))
    near = (d < radius).any(1)
    out["hits"] = int(label_used.sum())
    out["missed"] = int((~label_used).sum())
    out["false_positives"] = int((~near).sum())
    out["double"] = int((near & ~det_used).sum())
    return out


def summarise(rows: list[dict]) -> dict:
    """Aggregate per-image match counts into the paper's figures."""
    labels = sum(r["labels"] for r in rows)
    dets = sum(r["detections"] for r in rows)
    hits = sum(r["hits"] for r in rows)
    errors = np.array([e for r in rows for e in r["errors"]])
    return {
        "images": len(rows),
        "labels": labels,
        "detections": dets,
        "accuracy_px": float(errors.mean()) if errors.size else None,
        "accuracy_p95_px": float(np.percentile(errors, 95)) if errors.size else None,
        "over_1px": int((errors > 1.0).sum()),  # hits more than a pixel off their label: what harms a calibration
        "missed_pct": 100.0 * (labels - hits) / labels if labels else 0.0,
        "double_pct": 100.0 * sum(r["double"] for r in rows) / labels if labels else 0.0,
        "false_positives": sum(r["false_positives"] for r in rows),
        "fp_per_image": sum(r["false_positives"] for r in rows) / max(len(rows), 1),
        "precision": hits / dets if dets else None,
        "recall": hits / labels if labels else None,
        **({"boards_recovered": sum(r["board_recovered"] for r in rows),
            "spurious_boards": sum(r["spurious_boards"] for r in rows)} if rows and "board_recovered" in rows[0] else {}),
        **({"boards": sum(r["boards"] for r in rows), "wrong_index_boards": sum(r["wrong_index_boards"] for r in rows)}
           if rows and "wrong_index_boards" in rows[0] else {}),
    }


def real_dev_cases():
    """(group, name, image path, labels (M, 2), labelled board sizes [(cols, rows)]) per real photo."""
    meta = json.loads((REAL_DEV / "labels.json").read_text())
    for item in meta["images"]:
        labels = np.concatenate([np.asarray(b["corners"], np.float64).reshape(-1, 2) for b in item["boards"]])
        group = item["source"].split("@")[0]
        yield group, item["file"], REAL_DEV / "images" / item["file"], labels, [(b["cols"], b["rows"]) for b in item["boards"]]


SYMMETRIES = [np.array(m) for m in ([[1, 0], [0, 1]], [[0, -1], [1, 0]], [[-1, 0], [0, -1]], [[0, 1], [-1, 0]],
                                    [[0, 1], [1, 0]], [[1, 0], [0, -1]], [[0, -1], [-1, 0]], [[-1, 0], [0, 1]])]


def board_recovered(result: ccdn.Detection, labels: np.ndarray, cols: int, rows: int) -> bool:
    """Whether the largest board has the labelled size and indices consistent with the labels."""
    if not result.boards:
        return False
    board = result.boards[0]
    if sorted((board.cols, board.rows)) != sorted((cols, rows)):
        return False
    d = np.linalg.norm(board.xy[:, None].astype(np.float64) - labels[None], axis=2)
    hit = d.min(1) < MATCH_RADIUS
    if hit.sum() < 4:
        return False
    true = np.column_stack(np.divmod(d.argmin(1)[hit], cols))
    return same_indexing(board.grid[hit], true)


def photo_counts(result: ccdn.Detection, labels: np.ndarray, sizes: list[tuple[int, int]]) -> dict:
    """match's counts for a labelled photo, with whether its one labelled board was recovered and
    how many boards beyond the labelled ones were found (spurious)."""
    counts = match(result.xy, labels)
    counts["board_recovered"] = len(sizes) == 1 and board_recovered(result, labels, *sizes[0])
    counts["spurious_boards"] = max(0, len(result.boards) - len(sizes))
    return counts


def same_indexing(found: np.ndarray, true: np.ndarray) -> bool:
    """Whether found (M, 2) (row, col) = one of the board's 8 symmetries of true (M, 2) + one offset."""
    return any((lambda off: (off == off[0]).all())(found - true @ m.T) for m in SYMMETRIES)


def synthetic_cases(count: int, seed: int):
    """Renders of the training distribution from seeds no training run uses, and boardless scenes."""
    from ccdn_training.synth import SceneConfig, render_scene

    for i in range(count):
        scene = render_scene(np.random.default_rng(seed + i), SceneConfig(p_no_board=0.0))
        yield "synthetic", f"render-{seed + i}", scene.image, scene.corners, scene.ignore
    for i in range(count // 3):
        scene = render_scene(np.random.default_rng(seed + 10_000 + i), SceneConfig(p_no_board=1.0))
        yield "synthetic-no-board", f"empty-{seed + 10_000 + i}", scene.image, scene.corners, scene.ignore


def evaluate(detector: ccdn.Detector, synthetic: int, seed: int, real_dev: bool = True) -> dict:
    groups: dict[str, list[dict]] = defaultdict(list)
    per_image = []
    if real_dev and REAL_DEV.is_dir():
        for group, name, path, labels, sizes in real_dev_cases():
            r = photo_counts(detector.detect(path, boards=True), labels, sizes)
            groups[group].append(r)
            per_image.append({"group": group, "image": name, **{k: v for k, v in r.items() if k != "errors"}})
    elif real_dev:
        print(f"note: {REAL_DEV} not found; real-dev skipped", file=sys.stderr)
    for group, name, image, labels, ignore in synthetic_cases(synthetic, seed):
        r = match(detector.detect(image).xy, labels, ignore)
        groups[group].append(r)
        per_image.append({"group": group, "image": name, **{k: v for k, v in r.items() if k != "errors"}})
    summary = {g: summarise(rows) for g, rows in sorted(groups.items())}
    real = [r for g, rows in groups.items() if not g.startswith("synthetic") for r in rows]
    if real:
        summary["real-dev (all)"] = summarise(real)
    return {"groups": summary, "per_image": per_image}


def format_table(groups: dict) -> str:
    head = f"{'set':<34}{'imgs':>5}{'labels':>7}{'acc px':>8}{'p95':>7}{'>1px':>6}{'miss %':>8}{'dbl %':>7}{'FP':>5}{'FP/img':>7}{'prec':>7}{'recall':>7}"
    lines = [head, "-" * len(head)]
    fmt = lambda v, spec: format(v, spec) if v is not None else format("-", spec.rstrip("f").split(".")[0])  # noqa: E731
    for name, s in groups.items():
        lines.append(f"{name:<34}{s['images']:>5}{s['labels']:>7}{fmt(s['accuracy_px'], '>8.3f')}{fmt(s['accuracy_p95_px'], '>7.2f')}"
                     f"{s['over_1px']:>6}{s['missed_pct']:>8.2f}{s['double_pct']:>7.2f}{s['false_positives']:>5}{s['fp_per_image']:>7.2f}"
                     f"{fmt(s['precision'], '>7.3f')}{fmt(s['recall'], '>7.3f')}")
    boards = {n: s for n, s in groups.items() if "boards_recovered" in s}
    if boards:
        lines += ["", f"{'boards (real-dev)':<34}{'imgs':>5}{'recovered':>10}{'spurious':>9}"]
        lines += [f"{n:<34}{s['images']:>5}{s['boards_recovered']:>10}{s['spurious_boards']:>9}" for n, s in boards.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", default=None,
                        help=f"bundled model name or .onnx path ({DEFAULT_HELP})")
    parser.add_argument("--coarse-model", default=None, help=COARSE_MODEL_HELP)
    parser.add_argument("--refinement", default="saddle")
    parser.add_argument("--filter", default="grid", help="false-corner filter: grid (default), kmeans (paper), none")
    parser.add_argument("--no-coarse", action="store_true", help="always run the network at full resolution")
    parser.add_argument("--fast-check", action="store_true", help="Detector(fast_check=True): never at full resolution")
    parser.add_argument("--exhaustive", action="store_true",
                        help="Detector(exhaustive=True): a stretched look at every loose cluster of peaks")
    parser.add_argument("--synthetic", type=int, default=60, help="number of renders (plus a third as many boardless)")
    parser.add_argument("--seed", type=int, default=5_000_000)
    parser.add_argument("--no-real-dev", action="store_true", help="renders only (e.g. to choose between checkpoints)")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--json", type=Path, default=ROOT / "out" / "accuracy.json")
    args = parser.parse_args(argv)
    detector = ccdn.Detector(args.model, args.threads, coarse_model=args.coarse_model, refinement=args.refinement,
                             filter=args.filter, coarse_to_fine=not args.no_coarse, fast_check=args.fast_check,
                             exhaustive=args.exhaustive)
    t0 = time.time()
    result = evaluate(detector, args.synthetic, args.seed, real_dev=not args.no_real_dev)
    result["config"] = {"model": detector.models, "version": detector.model.version, "refinement": args.refinement,
                        "filter": args.filter, "coarse_to_fine": not args.no_coarse, "fast_check": args.fast_check,
                        "exhaustive": args.exhaustive,
                        "match_radius_px": MATCH_RADIUS, "seed": args.seed,
                        "machine": cpu_name(), "seconds": round(time.time() - t0, 1)}
    write_report(result, args.json)


def write_report(result: dict, path: Path) -> None:
    """Write an evaluation's result as JSON to path and print its groups' table."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=1))
    print(format_table(result["groups"]))
    print(f"written {path}")


if __name__ == "__main__":
    main()
