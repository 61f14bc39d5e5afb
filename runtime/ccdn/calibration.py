"""Camera calibration from board observations, with outlier views rejected, and its output files.

`calibrate` runs OpenCV's pinhole (cv2.calibrateCamera: k1 k2 p1 p2 k3) or fisheye (cv2.fisheye.calibrate:
equidistant, k1..k4) model on the views' found corners; a board with holes or a partial board just
contributes the corners it has (object points come from their grid indices, so an unknown offset of a
partial board only moves its pose). Views whose RMS reprojection error is far above the median are
dropped and the camera is solved again, until none is.

Writers: JSON, OpenCV FileStorage YAML, object/image points (npz), mrcal's corners.vnl, and a residual
plot. Pixel convention: (0, 0) is the centre of the top-left pixel (OpenCV's and mrcal's); object
points are (col * square, row * square, 0), right-handed with the board's +col, +row like image +x, +y.
"""

from __future__ import annotations

import io
import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .board import Board
from .writers import write_atomic

MODELS = ("pinhole", "fisheye")
MIN_VIEWS = 3
MIN_POINTS = 6  # per view
REJECT_FACTOR = 3.0  # a view whose RMS is above this times the median RMS is an outlier ...
REJECT_FLOOR_PX = 0.5  # ... and above this many pixels
_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-10)


class CalibrationError(ValueError):
    """Calibration was not possible (too few usable views, or OpenCV's solver failed); says why."""


@dataclass(frozen=True)
class View:
    """One board observation: the image's name, corners (M, 2) (x, y) px and their (row, col) (M, 2)."""

    name: str
    xy: np.ndarray
    grid: np.ndarray

    @classmethod
    def from_board(cls, name: str, board: Board) -> View:
        return cls(name, board.xy, board.grid)

    def object_points(self, square: float) -> np.ndarray:
        """(M, 3) float32 board coordinates: (col * square, row * square, 0)."""
        g = np.asarray(self.grid, np.float32)
        return np.column_stack([g[:, 1] * square, g[:, 0] * square, np.zeros(len(g), np.float32)])


@dataclass(frozen=True)
class Calibration:
    """A solved camera.

    camera_matrix (3, 3) and distortion (5,) pinhole k1 k2 p1 p2 k3 or (4,) fisheye k1..k4, in OpenCV's
    conventions; rms: px over all corners of the used views; view_errors: RMS px of every view (used:
    under the final solution; rejected: under the solution that rejected it); poses: (rvec, tvec) of
    each used view, board to camera.
    """

    model: str
    image_size: tuple[int, int]
    board: tuple[int, int]
    square: float
    camera_matrix: np.ndarray
    distortion: np.ndarray
    rms: float
    used: tuple[str, ...]
    rejected: tuple[str, ...]
    view_errors: dict[str, float] = field(default_factory=dict)
    poses: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict, repr=False)

    def project(self, view: View) -> np.ndarray:
        """(M, 2) reprojection of a used view's corners under this solution."""
        rvec, tvec = self.poses[view.name]
        return _project(self.model, view.object_points(self.square), rvec, tvec, self.camera_matrix,
                        self.distortion)

    def to_dict(self) -> dict:
        return {"model": self.model, "image_size": list(self.image_size),
                "board": {"cols": self.board[0], "rows": self.board[1], "square": self.square},
                "camera_matrix": self.camera_matrix.tolist(), "distortion": self.distortion.tolist(),
                "rms_px": self.rms, "used": list(self.used), "rejected": list(self.rejected),
                "view_rms_px": {k: round(v, 5) for k, v in self.view_errors.items()}}


def _project(model: str, obj: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, k: np.ndarray,
             d: np.ndarray) -> np.ndarray:
    if model == "fisheye":
        out, _ = cv2.fisheye.projectPoints(obj.reshape(1, -1, 3).astype(np.float64), rvec, tvec, k, d)
    else:
        out, _ = cv2.projectPoints(obj.astype(np.float64), rvec, tvec, k, d)
    return out.reshape(-1, 2)


def _flag(name: str) -> int:
    """A fisheye flag: cv2.fisheye.* in OpenCV 4, merged into cv2.* in OpenCV 5."""
    return getattr(cv2.fisheye, name, None) or getattr(cv2, name)


def _solve(model: str, views: Sequence[View], image_size: tuple[int, int], square: float):
    """One OpenCV solve: (K, dist, rvecs, tvecs, per-view RMS)."""
    obj = [v.object_points(square).astype(np.float64) for v in views]
    img = [np.asarray(v.xy, np.float64) for v in views]
    try:
        if model == "fisheye":
            # OpenCV's own start often fails (OpenCV 5: "norm_u1 > 0"); the same start given as a guess works
            w, h = image_size
            f0 = max(w, h) / np.pi
            k0 = np.array([[f0, 0, w / 2 - 0.5], [0, f0, h / 2 - 0.5], [0, 0, 1]])
            flags = _flag("CALIB_RECOMPUTE_EXTRINSIC") | _flag("CALIB_FIX_SKEW") | _flag("CALIB_USE_INTRINSIC_GUESS")
            _, k, d, rvecs, tvecs = cv2.fisheye.calibrate(
                [o.reshape(1, -1, 3) for o in obj], [i.reshape(1, -1, 2) for i in img], image_size, k0, np.zeros(4),
                flags=flags, criteria=_CRITERIA)
        else:
            _, k, d, rvecs, tvecs = cv2.calibrateCamera(
                [o.astype(np.float32) for o in obj], [i.astype(np.float32) for i in img], image_size, None, None,
                criteria=_CRITERIA)
    except cv2.error as exc:
        reason = str(exc).strip().splitlines()[-1]
        raise CalibrationError(f"OpenCV could not solve the {model} model: {reason}") from exc
    errors = np.array([np.sqrt(np.mean(np.sum((_project(model, o, r, t, k, d) - i) ** 2, axis=1)))
                       for o, i, r, t in zip(obj, img, rvecs, tvecs)])
    return k, d.ravel(), rvecs, tvecs, errors


def calibrate(views: Sequence[View], image_size: tuple[int, int], board: tuple[int, int], square: float,
              model: str = "pinhole", *, reject_factor: float = REJECT_FACTOR, max_rounds: int = 5) -> Calibration:
    """Solve the camera from board views, dropping outlier views (see the module docstring).

    image_size: (width, height) px; board: (cols, rows) inner corners; square: side in your unit
    (poses come out in it). Views with fewer than 6 corners or indices outside the board are not
    used. Raises CalibrationError when fewer than 3 views are usable or OpenCV fails.
    """
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    names = [v.name for v in views]
    if len(set(names)) != len(names):
        raise ValueError("view names must be unique")
    cols, rows = board
    usable = [v for v in views if len(v.xy) >= MIN_POINTS and np.all((v.grid >= 0) & (v.grid < [rows, cols]))]
    if len(usable) < MIN_VIEWS:
        raise CalibrationError(f"{len(usable)} usable views of a {cols}x{rows} board; "
                               f"at least {MIN_VIEWS} are needed")
    rejected: dict[str, float] = {}
    for _ in range(max_rounds):
        k, d, rvecs, tvecs, errors = _solve(model, usable, image_size, square)
        limit = max(reject_factor * float(np.median(errors)), REJECT_FLOOR_PX)
        worst = [i for i in np.argsort(-errors) if errors[i] > limit][: len(usable) - MIN_VIEWS]
        if not worst:
            break
        rejected.update({usable[i].name: float(errors[i]) for i in worst})
        usable = [v for i, v in enumerate(usable) if i not in worst]
    else:
        k, d, rvecs, tvecs, errors = _solve(model, usable, image_size, square)
    counts = np.array([len(v.xy) for v in usable])
    rms = float(np.sqrt(np.sum(errors**2 * counts) / counts.sum()))
    return Calibration(model, tuple(image_size), (cols, rows), float(square), k, d, rms,
                       tuple(v.name for v in usable), tuple(rejected),
                       {**{v.name: float(e) for v, e in zip(usable, errors)}, **rejected},
                       {v.name: (r, t) for v, r, t in zip(usable, rvecs, tvecs)})


# ----------------------------------------------------------------------------- writers
def write_calibration_json(path: Path, calibration: Calibration) -> None:
    write_atomic(path, (json.dumps(calibration.to_dict(), indent=1) + "\n").encode())


def write_opencv_yaml(path: Path, calibration: Calibration) -> None:
    """OpenCV FileStorage YAML (read back with cv2.FileStorage): camera_matrix, distortion_coefficients, ..."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    fs.write("model", calibration.model)
    fs.write("image_width", calibration.image_size[0])
    fs.write("image_height", calibration.image_size[1])
    fs.write("board_width", calibration.board[0])
    fs.write("board_height", calibration.board[1])
    fs.write("square_size", calibration.square)
    fs.write("camera_matrix", calibration.camera_matrix)
    fs.write("distortion_coefficients", calibration.distortion.reshape(1, -1))
    fs.write("rms", calibration.rms)
    write_atomic(path, fs.releaseAndGetString().encode())


def write_points(path: Path, views: Sequence[View], square: float) -> None:
    """npz of OpenCV object/image points: names (V,), counts (V,) and, concatenated over the views,
    object_points (P, 3) float32, image_points (P, 2) float32, grid (P, 2) (row, col).
    Per view: np.split(object_points, np.cumsum(counts)[:-1]).
    """
    buf = _npz_bytes(names=np.array([v.name for v in views]), counts=np.array([len(v.xy) for v in views]),
                     object_points=np.concatenate([v.object_points(square) for v in views]).astype(np.float32),
                     image_points=np.concatenate([np.asarray(v.xy, np.float32) for v in views]),
                     grid=np.concatenate([np.asarray(v.grid, np.int32) for v in views]))
    write_atomic(path, buf)


def _npz_bytes(**arrays: np.ndarray) -> bytes:
    out = io.BytesIO()
    np.savez(out, **arrays)
    return out.getvalue()


def corners_vnl(views: Sequence[View], board: tuple[int, int], missing: Sequence[str] = ()) -> str:
    """mrcal's corners.vnl: `# filename x y level`, cols x rows lines per view in row-major board order,
    level 0 for a found corner and `- - -` for a missing one; an image without a board is one `- - -` line.
    """
    cols, rows = board
    lines = ["# filename x y level"]
    records = [(v.name, v) for v in views] + [(name, None) for name in missing]
    for name, view in sorted(records, key=lambda r: r[0]):
        if view is None:
            lines.append(f"{name} - - -")
            continue
        at = {(int(r), int(c)): p for (r, c), p in zip(view.grid, view.xy)}
        for r in range(rows):
            for c in range(cols):
                p = at.get((r, c))
                lines.append(f"{name} - - -" if p is None else f"{name} {p[0]:.3f} {p[1]:.3f} 0")
    return "\n".join(lines) + "\n"


def write_corners_vnl(path: Path, views: Sequence[View], board: tuple[int, int], missing: Sequence[str] = ()) -> None:
    write_atomic(path, corners_vnl(views, board, missing).encode())


# ----------------------------------------------------------------------------- residual plots
def _nice_scale(residuals: np.ndarray, target_px: float) -> float:
    """A 1-2-5 magnification that draws the 95th-percentile residual about target_px long."""
    p95 = float(np.percentile(np.linalg.norm(residuals, axis=1), 95)) if len(residuals) else 0.0
    raw = target_px / max(p95, 1e-6)
    steps = [m * 10**e for e in range(-1, 6) for m in (1, 2, 5)]
    return float(max([s for s in steps if s <= raw], default=steps[0]))


def draw_residuals(calibration: Calibration, views: Sequence[View], max_width: int = 1280) -> np.ndarray:
    """BGR plot of all used views' corners on the image frame with error vectors, magnified (see legend)."""
    used = [v for v in views if v.name in calibration.poses]
    w, h = calibration.image_size
    f = min(1.0, max_width / w)
    canvas = np.full((round(h * f), round(w * f), 3), 40, np.uint8)
    res = [calibration.project(v) - np.asarray(v.xy, np.float64) for v in used]
    scale = _nice_scale(np.concatenate(res) if res else np.zeros((0, 2)), 0.03 * canvas.shape[1])
    for i, (v, r) in enumerate(zip(used, res)):
        hue = int(180 * i / max(len(used), 1))
        colour = cv2.cvtColor(np.uint8([[[hue, 200, 255]]]), cv2.COLOR_HSV2BGR)[0, 0].tolist()
        for p, e in zip(np.asarray(v.xy, np.float64) * f, r * f * scale):
            a = (int(round(p[0])), int(round(p[1])))
            cv2.line(canvas, a, (int(round(p[0] + e[0])), int(round(p[1] + e[1]))), colour, 1, cv2.LINE_AA)
            cv2.circle(canvas, a, 1, colour, -1)
    text = (f"{calibration.model}: RMS {calibration.rms:.3f} px, {len(used)} views "
            f"({len(calibration.rejected)} rejected); error vectors x{scale:g}")
    cv2.putText(canvas, text, (10, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
    return canvas


def draw_view_residuals(gray: np.ndarray, calibration: Calibration, view: View) -> np.ndarray:
    """BGR image of one used view: found corners (green), reprojections (red), magnified error vectors."""
    out = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    xy = np.asarray(view.xy, np.float64)
    proj = calibration.project(view)
    scale = _nice_scale(proj - xy, 0.03 * max(gray.shape))
    r = max(2, round(max(gray.shape) / 300))
    for p, q in zip(xy, proj):
        a = (int(round(p[0])), int(round(p[1])))
        b = (int(round(p[0] + (q[0] - p[0]) * scale)), int(round(p[1] + (q[1] - p[1]) * scale)))
        cv2.line(out, a, b, (0, 200, 255), 1, cv2.LINE_AA)
        cv2.circle(out, a, r, (0, 255, 0), 1, cv2.LINE_AA)
        cv2.drawMarker(out, (int(round(q[0])), int(round(q[1]))), (0, 0, 255), cv2.MARKER_CROSS, 2 * r, 1)
    text = f"{view.name}: RMS {calibration.view_errors[view.name]:.3f} px; error vectors x{scale:g}"
    cv2.putText(out, text, (10, 10 + 3 * r), cv2.FONT_HERSHEY_SIMPLEX, r / 4, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def write_image(path: Path, image: np.ndarray) -> None:
    ok, buf = cv2.imencode(path.suffix or ".png", image)
    if not ok:
        raise OSError(f"{path}: OpenCV cannot encode this format")
    write_atomic(path, buf.tobytes())


def write_outputs(out: Path, calibration: Calibration, views: Sequence[View], missing: Sequence[str] = (),
                  load: Callable[[str], np.ndarray] | None = None) -> list[Path]:
    """Write calibration.json, calibration.yaml, corners.vnl, points.npz and residuals.png into `out`,
    and with `load` (view name -> gray image) residuals/<name>.jpg for each used view. Returns the paths.
    """
    paths = [out / "calibration.json", out / "calibration.yaml", out / "corners.vnl", out / "points.npz",
             out / "residuals.png"]
    write_calibration_json(paths[0], calibration)
    write_opencv_yaml(paths[1], calibration)
    write_corners_vnl(paths[2], views, calibration.board, missing)
    write_points(paths[3], views, calibration.square)
    write_image(paths[4], draw_residuals(calibration, views))
    for view in views if load is not None else ():
        if view.name in calibration.poses:
            paths.append(out / "residuals" / f"{view.name}.jpg")
            write_image(paths[-1], draw_view_residuals(load(view.name), calibration, view))
    return paths


def report(calibration: Calibration) -> str:
    """A few lines for people: the model, focal length, principal point, RMS and rejected views."""
    k = calibration.camera_matrix
    lines = [f"{calibration.model} camera, {calibration.image_size[0]}x{calibration.image_size[1]} px, "
             f"{len(calibration.used)} views used, {len(calibration.rejected)} rejected",
             f"  focal length  fx {k[0, 0]:.2f}  fy {k[1, 1]:.2f} px",
             f"  principal pt  cx {k[0, 2]:.2f}  cy {k[1, 2]:.2f} px",
             f"  distortion    {' '.join(f'{x:.5f}' for x in calibration.distortion)}",
             f"  RMS reprojection error {calibration.rms:.3f} px"]
    lines += [f"  rejected {name}: RMS {calibration.view_errors[name]:.2f} px" for name in calibration.rejected]
    return "\n".join(lines)
