"""Calibration (ccdn.calibration) on exact synthetic views, its output files, and `ccdn calibrate`."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from ccdn.calibration import (CalibrationError, View, calibrate, corners_vnl, draw_view_residuals, report,
                              write_outputs)

SIZE = (1280, 960)
BOARD = (9, 6)
SQUARE = 0.025
GRID = np.stack(np.mgrid[0 : BOARD[1], 0 : BOARD[0]], -1).reshape(-1, 2)  # (row, col), row-major
PINHOLE_K = np.array([[1000.0, 0, 652.0], [0, 1000.0, 471.0], [0, 0, 1]])
PINHOLE_D = np.array([-0.38, 0.2, 0.0008, -0.0005, -0.06])  # strong barrel
FISHEYE_K = np.array([[380.0, 0, 641.0], [0, 380.0, 483.0], [0, 0, 1]])
FISHEYE_D = np.array([0.04, -0.015, 0.006, -0.002])


def project(model: str, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    obj = View("", np.zeros((len(GRID), 2)), GRID).object_points(SQUARE).astype(np.float64)
    if model == "fisheye":
        p, _ = cv2.fisheye.projectPoints(obj.reshape(1, -1, 3), rvec, tvec, FISHEYE_K, FISHEYE_D)
    else:
        p, _ = cv2.projectPoints(obj, rvec, tvec, PINHOLE_K, PINHOLE_D)
    return p.reshape(-1, 2)


def synthetic_views(model: str, n: int = 15, noise: float = 0.05, seed: int = 0) -> list[View]:
    """n views of the board, entirely inside the image, with Gaussian pixel noise."""
    rng = np.random.default_rng(seed)
    views = []
    while len(views) < n:
        rvec = rng.normal(0, 0.45, 3)
        depth = rng.uniform(0.12, 0.3) if model == "fisheye" else rng.uniform(0.25, 0.5)
        tvec = np.array([rng.uniform(-0.7, 0.2) * depth, rng.uniform(-0.6, 0.2) * depth, depth])
        rot, _ = cv2.Rodrigues(rvec)
        obj = View("", np.zeros((len(GRID), 2)), GRID).object_points(SQUARE)
        if ((obj @ rot.T + tvec)[:, 2] < 0.05).any():
            continue
        xy = project(model, rvec, tvec)
        if (xy < 5).any() or (xy[:, 0] > SIZE[0] - 5).any() or (xy[:, 1] > SIZE[1] - 5).any():
            continue
        views.append(View(f"view{len(views):02d}.png", xy + rng.normal(0, noise, xy.shape), GRID))
    return views


@pytest.mark.parametrize("model, k", [("pinhole", PINHOLE_K), ("fisheye", FISHEYE_K)])
def test_recovers_a_known_camera(model, k):
    result = calibrate(synthetic_views(model), SIZE, BOARD, SQUARE, model)
    assert result.model == model and result.rejected == ()
    np.testing.assert_allclose(np.diag(result.camera_matrix)[:2], np.diag(k)[:2], rtol=0.005)
    np.testing.assert_allclose(result.camera_matrix[:2, 2], k[:2, 2], atol=2.0)
    assert result.rms <= 0.2
    assert len(result.distortion) == (4 if model == "fisheye" else 5)


def test_a_corrupted_view_is_rejected_and_the_rest_still_calibrate():
    views = synthetic_views("pinhole")
    rng = np.random.default_rng(5)
    views[4] = View(views[4].name, views[4].xy + rng.normal(0, 4.0, views[4].xy.shape), views[4].grid)
    result = calibrate(views, SIZE, BOARD, SQUARE)
    assert result.rejected == (views[4].name,)
    assert result.view_errors[views[4].name] > 1.0
    assert views[4].name not in result.used and len(result.used) == len(views) - 1
    np.testing.assert_allclose(result.camera_matrix[0, 0], PINHOLE_K[0, 0], rtol=0.005)
    assert result.rms <= 0.2


def test_partial_boards_with_unknown_offset_and_holes_calibrate_as_well():
    """A partial board's indices start at 0 where its found part starts: only its pose changes."""
    rng = np.random.default_rng(2)
    views = []
    for v in synthetic_views("pinhole", n=15, seed=3):
        keep = (v.grid[:, 1] >= 2) & (rng.random(len(v.grid)) > 0.1)  # lose two columns and ~10 % holes
        views.append(View(v.name, v.xy[keep], v.grid[keep] - [0, 2]))
    result = calibrate(views, SIZE, BOARD, SQUARE)
    np.testing.assert_allclose(result.camera_matrix[0, 0], PINHOLE_K[0, 0], rtol=0.005)
    assert result.rms <= 0.2


def test_too_few_views_or_an_unknown_model_is_refused():
    views = synthetic_views("pinhole", n=2)
    with pytest.raises(CalibrationError, match="at least 3"):
        calibrate(views, SIZE, BOARD, SQUARE)
    with pytest.raises(ValueError, match="model"):
        calibrate(synthetic_views("pinhole", n=3), SIZE, BOARD, SQUARE, "spline")


def test_views_whose_indices_exceed_the_board_are_not_used():
    views = synthetic_views("pinhole", n=4)
    with pytest.raises(CalibrationError):
        calibrate(views, SIZE, (8, 6), SQUARE)  # every view has column 8, outside an 8 x 6 board


def test_output_files_read_back(tmp_path):
    views = synthetic_views("pinhole", n=6)
    holed = View(views[0].name, views[0].xy[1:], views[0].grid[1:])  # corner (0, 0) missing
    views = [holed, *views[1:]]
    result = calibrate(views, SIZE, BOARD, SQUARE)
    paths = write_outputs(tmp_path, result, views, missing=["empty.png"],
                          load=lambda name: np.zeros(SIZE[::-1], np.uint8))
    assert all(p.is_file() for p in paths)

    fs = cv2.FileStorage(str(tmp_path / "calibration.yaml"), cv2.FILE_STORAGE_READ)
    np.testing.assert_allclose(fs.getNode("camera_matrix").mat(), result.camera_matrix)
    np.testing.assert_allclose(fs.getNode("distortion_coefficients").mat().ravel(), result.distortion)
    assert fs.getNode("model").string() == "pinhole" and fs.getNode("image_width").real() == SIZE[0]
    fs.release()

    data = json.loads((tmp_path / "calibration.json").read_text())
    np.testing.assert_allclose(data["camera_matrix"], result.camera_matrix)
    assert data["board"] == {"cols": 9, "rows": 6, "square": SQUARE} and data["rms_px"] == pytest.approx(result.rms)

    lines = (tmp_path / "corners.vnl").read_text().splitlines()
    assert lines[0] == "# filename x y level"
    rows = [line.split() for line in lines[1:]]
    assert all(len(r) == 4 for r in rows)
    assert rows[0] == ["empty.png", "-", "-", "-"]  # an image without a board: one line
    first = [r for r in rows if r[0] == holed.name]
    assert len(first) == 54 and first[0][1:] == ["-", "-", "-"]  # the hole at (0, 0)
    for k, r in enumerate(first[1:], start=1):  # row-major: line k is corner (k // cols, k % cols)
        i = np.nonzero((holed.grid[:, 0] == k // 9) & (holed.grid[:, 1] == k % 9))[0][0]
        np.testing.assert_allclose([float(r[1]), float(r[2])], holed.xy[i], atol=1e-3)
        assert r[3] == "0"

    with np.load(tmp_path / "points.npz") as npz:
        obj = np.split(npz["object_points"], np.cumsum(npz["counts"])[:-1])
        img = np.split(npz["image_points"], np.cumsum(npz["counts"])[:-1])
        assert list(npz["names"]) == [v.name for v in views]
    assert [len(o) for o in obj] == [len(v.xy) for v in views]
    np.testing.assert_allclose(obj[0][:, :2], holed.grid[:, ::-1] * SQUARE, atol=1e-6)
    np.testing.assert_allclose(img[1], views[1].xy, atol=1e-4)

    plot = cv2.imread(str(tmp_path / "residuals.png"))
    assert plot.shape[1] == SIZE[0] and plot.shape[0] == SIZE[1]
    assert len(list((tmp_path / "residuals").glob("*.jpg"))) == len(result.used)
    assert "focal length" in report(result)


def test_corners_vnl_of_no_views_is_the_header_only():
    assert corners_vnl([], BOARD) == "# filename x y level\n"


def test_view_overlay_marks_reprojections_in_red():
    views = synthetic_views("pinhole", n=5)
    result = calibrate(views, SIZE, BOARD, SQUARE)
    out = draw_view_residuals(np.full(SIZE[::-1], 128, np.uint8), result, views[0])
    assert out.shape == (SIZE[1], SIZE[0], 3)
    x, y = np.rint(result.project(views[0])[10]).astype(int)
    patch = out[y - 2 : y + 3, x - 2 : x + 3].reshape(-1, 3).astype(int)
    assert ((patch[:, 2] > 200) & (patch[:, 1] < 80)).any()  # a red cross at the reprojection


# ----------------------------------------------------------------------------- ccdn calibrate, end to end
def render_view(lens, rvec: np.ndarray, tvec: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """A clean render of a 9 x 6 board (square = 1 unit) at pose rvec, tvec through the renderer's lens."""
    synth = pytest.importorskip("ccdn_training.synth")
    w, h = size
    rot, _ = cv2.Rodrigues(rvec)
    k = np.array([[lens.f, 0, lens.cx], [0, lens.f, lens.cy], [0, 0, 1]])
    board = synth.Board(9, 6, 0.6, k @ np.column_stack([rot[:, 0], rot[:, 1], tvec]), 0.1, 0.9)
    s = synth.SUPERSAMPLE
    xd, yd = np.meshgrid((np.arange(w * s) + 0.5) / s - 0.5, (np.arange(h * s) + 0.5) / s - 0.5)
    xu, yu, _ = lens.to_ideal(xd, yd)
    value, mask = board.render(xu, yu)
    img = cv2.resize(np.where(mask, value, 0.45).astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
    return np.clip(img * 255 + 0.5, 0, 255).astype(np.uint8)


def test_calibrate_command_recovers_a_rendered_camera(tmp_path):
    synth = pytest.importorskip("ccdn_training.synth")
    from ccdn.cli import main

    size = (640, 480)
    lens = synth.Lens(560.0, 322.0, 236.0)
    rng = np.random.default_rng(7)
    (tmp_path / "in").mkdir()
    for i in range(8):
        rvec = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3)])
        tvec = np.array([rng.uniform(-6.5, -3.5), rng.uniform(-4.5, -2.5), rng.uniform(17, 23)])
        cv2.imwrite(str(tmp_path / "in" / f"view{i}.png"), render_view(lens, rvec, tvec, size))
    cv2.imwrite(str(tmp_path / "in" / "blank.png"), np.full(size[::-1], 90, np.uint8))
    code = main(["calibrate", str(tmp_path / "in"), "--board", "9x6", "--square", "1", "--out", str(tmp_path / "out"),
                 "--threads", "2", "--quiet"])
    assert code == 0
    data = json.loads((tmp_path / "out" / "calibration.json").read_text())
    k = np.array(data["camera_matrix"])
    assert k[0, 0] == pytest.approx(lens.f, rel=0.02) and k[1, 1] == pytest.approx(lens.f, rel=0.02)
    assert abs(k[0, 2] - lens.cx) < 8 and abs(k[1, 2] - lens.cy) < 8
    assert "blank.png - - -" in (tmp_path / "out" / "corners.vnl").read_text()


def test_calibrate_command_fails_without_enough_boards(tmp_path):
    from ccdn.cli import main

    (tmp_path / "in").mkdir()
    for i in range(3):
        cv2.imwrite(str(tmp_path / "in" / f"blank{i}.png"), np.full((120, 160), 90 + i, np.uint8))
    assert main(["calibrate", str(tmp_path / "in"), "--board", "9x6", "--square", "1", "--out",
                 str(tmp_path / "out"), "--quiet"]) == 1
    with pytest.raises(SystemExit):
        main(["calibrate", str(tmp_path / "in"), "--board", "9by6", "--square", "1", "--out", str(tmp_path)])


def test_calibrate_command_uses_cut_off_boards_only_with_partial(tmp_path):
    synth = pytest.importorskip("ccdn_training.synth")
    from ccdn.cli import main

    lens = synth.Lens(560.0, 322.0, 236.0)
    rng = np.random.default_rng(3)
    (tmp_path / "in").mkdir()
    for i in range(4):  # the board's last two columns are beyond the right edge of the image
        rvec = np.array([rng.uniform(-0.4, 0.4), rng.uniform(-0.4, 0.4), rng.uniform(-0.2, 0.2)])
        image = render_view(lens, rvec, np.array([5.0, -3.5, 20.0]), (640, 480))
        cv2.imwrite(str(tmp_path / "in" / f"cut{i}.png"), image)
    args = ["calibrate", str(tmp_path / "in"), "--board", "9x6", "--square", "1", "--threads", "2", "--quiet"]
    assert main([*args, "--out", str(tmp_path / "strict")]) == 1
    assert main([*args, "--out", str(tmp_path / "partial"), "--partial"]) == 0
    assert len(json.loads((tmp_path / "partial" / "calibration.json").read_text())["used"]) >= 3
