"""Calibration benchmark: a known camera, 20 rendered views, ccdn vs OpenCV's findChessboardCornersSB.

Two cameras in OpenCV's own models, so that the truth is exactly representable: a pinhole with strong
barrel distortion (k1 -0.3) and a fisheye (equidistant + k1..k4). Each view of a 9 x 6 board is rendered
by inverse mapping at 3x supersampling (every sub-pixel is undistorted with OpenCV to the ideal image,
where the checker pattern is evaluated exactly), with a slight blur and noise; the true corners come
from cv2.projectPoints. Both detectors' corners go through the same ccdn.calibration.calibrate (outlier
rejection included), so the table compares detection: views found, corner error against the truth, RMS,
and the focal length / principal point error (distortion coefficients are not compared: they trade off).

--real-dev: the real photos (../shared/data/real-dev) have no true camera, so there the question is
which corners a camera model explains better. Per camera (source, image size and board, at least 3
photos) the pinhole model is solved twice with the same function: from the labels (which coincide with
findChessboardCornersSB's corners) and from ccdn's corners matched to them (nearest within 5 px, so
both solves use the same board points). A lower RMS reprojection error means corners more consistent
with one camera and rigid poses; the table also gives how far the two solutions' intrinsics differ.

    python benchmarks/calibration.py [--views 20] [--model paper] [--json out/calibration.json]
    python benchmarks/calibration.py --real-dev [--json out/calibration_real.json]
"""

from __future__ import annotations

import argparse
import json
import time
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np

import ccdn
from ccdn.calibration import MIN_VIEWS, CalibrationError, View, calibrate
from ccdn.models import DEFAULT_HELP

from accuracy import MATCH_RADIUS, REAL_DEV, real_dev_cases
from machine import cpu_name

BOARD = (9, 6)
SIZE = (640, 480)
SUPERSAMPLE = 3
CAMERAS = {
    "pinhole+radial": dict(model="pinhole", k=[[520.0, 0, 322.5], [0, 520.0, 236.0], [0, 0, 1]],
                           d=[-0.3, 0.1, 0.0005, -0.0004, -0.015]),
    "fisheye": dict(model="fisheye", k=[[210.0, 0, 318.0], [0, 210.0, 242.5], [0, 0, 1]],
                    d=[0.03, -0.01, 0.004, -0.001]),
}
_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 50, 1e-10)


def board_points() -> np.ndarray:
    """Inner corners in board squares, row-major: (col + 1, row + 1, 0); the outer squares start at 0."""
    rr, cc = np.mgrid[0 : BOARD[1], 0 : BOARD[0]]
    return np.column_stack([cc.ravel() + 1.0, rr.ravel() + 1.0, np.zeros(rr.size)])


def project(cam: dict, pts: np.ndarray, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    k, d = np.array(cam["k"]), np.array(cam["d"])
    if cam["model"] == "fisheye":
        out, _ = cv2.fisheye.projectPoints(pts.reshape(1, -1, 3), rvec, tvec, k, d)
    else:
        out, _ = cv2.projectPoints(pts, rvec, tvec, k, d)
    return out.reshape(-1, 2)


def render(cam: dict, rvec: np.ndarray, tvec: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The board at pose (rvec, tvec), board units = squares, through the camera; uint8 gray."""
    w, h, s = SIZE[0], SIZE[1], SUPERSAMPLE
    k, d = np.array(cam["k"]), np.array(cam["d"])
    xd, yd = np.meshgrid((np.arange(w * s) + 0.5) / s - 0.5, (np.arange(h * s) + 0.5) / s - 0.5)
    pts = np.stack([xd.ravel(), yd.ravel()], 1).reshape(-1, 1, 2)
    if cam["model"] == "fisheye":
        ideal = cv2.fisheye.undistortPoints(pts, k, d, P=k, criteria=_CRITERIA).reshape(-1, 2)
    else:
        ideal = cv2.undistortPoints(pts, k, d, P=k, criteria=_CRITERIA).reshape(-1, 2)
    rot, _ = cv2.Rodrigues(rvec)
    hom = np.linalg.inv(k @ np.column_stack([rot[:, 0], rot[:, 1], tvec]))
    p = hom @ np.vstack([ideal.T, np.ones(len(ideal))])
    front = p[2] > 1e-9
    u, v = p[0] / np.where(front, p[2], 1), p[1] / np.where(front, p[2], 1)
    cols, rows = BOARD
    inside = front & (u >= 0) & (u <= cols + 1) & (v >= 0) & (v <= rows + 1)
    margin = front & (u >= -0.6) & (u <= cols + 1.6) & (v >= -0.6) & (v <= rows + 1.6)
    value = np.where(inside & ((np.floor(u) + np.floor(v)) % 2 == 0), 0.12, 0.88)
    img = np.where(margin, value, 0.45).reshape(h * s, w * s).astype(np.float32)
    img = cv2.GaussianBlur(cv2.resize(img, SIZE, interpolation=cv2.INTER_AREA), (0, 0), 0.6)
    img += rng.normal(0, 0.01, img.shape).astype(np.float32)
    return np.clip(img * 255 + 0.5, 0, 255).astype(np.uint8)


def poses(cam: dict, n: int, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """n poses whose whole board is in the image: (rvec, tvec, true corners (54, 2))."""
    out = []
    f = cam["k"][0][0]
    while len(out) < n:
        rvec = np.array([rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6), rng.uniform(-0.4, 0.4)])
        z = rng.uniform(0.45, 0.9) * f / 18  # squares of about 18..36 px at the centre
        rot, _ = cv2.Rodrigues(rvec)
        centre = rot @ np.array([(BOARD[0] + 1) / 2, (BOARD[1] + 1) / 2, 0])
        tvec = np.array([rng.uniform(-0.35, 0.35) * z, rng.uniform(-0.3, 0.3) * z, z]) - centre
        xy = project(cam, board_points(), rvec, tvec)
        if ((board_points() @ rot.T + tvec)[:, 2] > 0.5).all() and (xy > 8).all() and (xy < np.array(SIZE) - 8).all():
            out.append((rvec, tvec, xy))
    return out


def ccdn_view(detector: ccdn.Detector, gray: np.ndarray, name: str) -> View | None:
    boards = detector.detect(gray, boards=True, board_size=BOARD).boards
    return View.from_board(name, boards[0]) if boards else None


def opencv_view(gray: np.ndarray, name: str) -> View | None:
    ok, corners = cv2.findChessboardCornersSB(gray, BOARD)
    if not ok:
        return None
    rr, cc = np.mgrid[0 : BOARD[1], 0 : BOARD[0]]
    return View(name, corners.reshape(-1, 2), np.column_stack([rr.ravel(), cc.ravel()]))


def corner_error(view: View, truth: np.ndarray) -> np.ndarray:
    """Distance of each found corner to the nearest true corner, px."""
    return np.linalg.norm(np.asarray(view.xy, np.float64)[:, None] - truth[None], axis=2).min(1)


def evaluate(cam: dict, views: list[View], truths: dict[str, np.ndarray], seconds: float) -> dict:
    errors = np.concatenate([corner_error(v, truths[v.name]) for v in views]) if views else np.zeros(0)
    row = {"views_found": len(views), "corners": int(len(errors)), "detect_ms_per_image": seconds * 1e3 / len(truths),
           "corner_err_mean_px": float(errors.mean()) if len(errors) else None,
           "corner_err_p95_px": float(np.percentile(errors, 95)) if len(errors) else None}
    try:
        result = calibrate(views, SIZE, BOARD, 1.0, cam["model"])
    except CalibrationError as exc:
        return {**row, "error": str(exc)}
    k, true_k = result.camera_matrix, np.array(cam["k"])
    return {**row, "views_used": len(result.used), "rms_px": result.rms,
            "fx_err_pct": 100 * (k[0, 0] / true_k[0, 0] - 1), "fy_err_pct": 100 * (k[1, 1] / true_k[1, 1] - 1),
            "cx_err_px": k[0, 2] - true_k[0, 2], "cy_err_px": k[1, 2] - true_k[1, 2]}


def real_dev_views(detector: ccdn.Detector) -> dict[tuple, dict[str, list[View]]]:
    """Per real-dev camera (source, (width, height), board (cols, rows) with cols >= rows): the
    photos' views from the labels and from ccdn's corners nearest to each label (within
    MATCH_RADIUS; a label without one is left out of that view). Photos labelled with the board
    the other way round get (row, col) swapped, so one camera has one board frame."""
    cameras: dict[tuple, dict[str, list[View]]] = defaultdict(lambda: {"labels": [], "ccdn": []})
    for group, name, path, labels, sizes in real_dev_cases():
        if len(sizes) != 1:
            continue  # every real-dev photo shows one board; a photo with more would need its boards told apart
        (cols, rows), = sizes
        grid = np.column_stack(np.divmod(np.arange(len(labels)), cols))  # labels are row-major
        if cols < rows:
            grid, cols, rows = grid[:, ::-1], rows, cols
        result = detector.detect(path)
        camera = cameras[(group, result.image_size, (cols, rows))]
        camera["labels"].append(View(name, labels, grid))
        if len(result.xy):
            d = np.linalg.norm(labels[:, None] - result.xy[None].astype(np.float64), axis=2)
            hit = d.min(1) < MATCH_RADIUS
            camera["ccdn"].append(View(name, result.xy[d.argmin(1)[hit]].astype(np.float64), grid[hit]))
    return {key: views for key, views in cameras.items() if len(views["labels"]) >= MIN_VIEWS}


def real_dev_main(detector: ccdn.Detector, report: dict) -> None:
    """The --real-dev table (module docstring) into report["real_dev"]."""
    print(f"{'camera':42} {'photos':>6} {'RMS labels':>10} {'RMS ccdn':>8} {'fx diff %':>9} {'cx, cy diff px':>14}")
    report["real_dev"] = []
    for (group, size, board), views in sorted(real_dev_views(detector).items()):
        label = f"{group} {size[0]}x{size[1]} {board[0]}x{board[1]}"
        try:
            solved = {k: calibrate(v, size, board, 1.0) for k, v in views.items()}
        except CalibrationError as exc:
            print(f"{label:42} calibration failed: {exc}")
            continue
        ref, mine = solved["labels"], solved["ccdn"]
        k0, k1 = ref.camera_matrix, mine.camera_matrix
        row = {"source": group, "image_size": list(size), "board": list(board), "photos": len(views["labels"]),
               "views_used": {k: len(c.used) for k, c in solved.items()},
               "rms_px": {k: c.rms for k, c in solved.items()},
               "fx_diff_pct": 100 * (k1[0, 0] / k0[0, 0] - 1), "cx_diff_px": k1[0, 2] - k0[0, 2],
               "cy_diff_px": k1[1, 2] - k0[1, 2]}
        report["real_dev"].append(row)
        print(f"{label:42} {row['photos']:>6} {ref.rms:>10.3f} {mine.rms:>8.3f} {row['fx_diff_pct']:>9.2f} "
              f"{row['cx_diff_px']:>6.2f}, {row['cy_diff_px']:>5.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=20)
    parser.add_argument("--model", default=None,
                        help=f"ccdn model ({DEFAULT_HELP})")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--real-dev", action="store_true", help="calibrate real-dev's cameras instead (docstring)")
    args = parser.parse_args()
    detector = ccdn.Detector(args.model, args.threads)
    report = {"model": f"{detector.models} {detector.model.version}", "threads": detector.threads,
              "cpu": cpu_name()}
    if args.real_dev:
        if not REAL_DEV.is_dir():
            raise SystemExit(f"no real-dev photos at {REAL_DEV}")
        real_dev_main(detector, report)
        write_report(args.json, report)
        return
    report.update({"board": BOARD, "image_size": SIZE, "views": args.views, "cameras": {}})
    print(f"{'camera':16} {'detector':8} {'views':>7} {'corner err':>11} {'RMS px':>7} {'fx %':>7} {'fy %':>7} "
          f"{'cx px':>7} {'cy px':>7} {'ms/img':>7}")
    for name, cam in CAMERAS.items():
        rng = np.random.default_rng(args.seed)
        frames = {f"view{i:02d}": (render(cam, r, t, rng), xy)
                  for i, (r, t, xy) in enumerate(poses(cam, args.views, rng))}
        truths = {k: xy for k, (_, xy) in frames.items()}
        report["cameras"][name] = {"truth": cam}
        for label, find in (("ccdn", lambda g, n: ccdn_view(detector, g, n)), ("opencv", opencv_view)):
            t0 = time.perf_counter()
            views = [v for v in (find(gray, k) for k, (gray, _) in frames.items()) if v is not None]
            row = evaluate(cam, views, truths, time.perf_counter() - t0)
            report["cameras"][name][label] = row
            if "error" in row:
                print(f"{name:16} {label:8} {row['views_found']:>3}/{args.views:<3} calibration failed: {row['error']}")
                continue
            print(f"{name:16} {label:8} {row['views_used']:>3}/{args.views:<3} {row['corner_err_mean_px']:>11.3f} "
                  f"{row['rms_px']:>7.3f} {row['fx_err_pct']:>7.3f} {row['fy_err_pct']:>7.3f} {row['cx_err_px']:>7.2f} "
                  f"{row['cy_err_px']:>7.2f} {row['detect_ms_per_image']:>7.0f}")
    write_report(args.json, report)


def write_report(path: Path | None, report: dict) -> None:
    if path:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
