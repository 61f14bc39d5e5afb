"""The Detector end to end with the shipped model on the bundled examples and real photos."""

from __future__ import annotations

import subprocess
import sys
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

import ccdn
from conftest import as_fitted, index_map, nearest_distances, no_growth_into_shade, no_holes, stress_scene, true_board


def test_runtime_never_imports_torch_or_training_code():
    code = "import sys, numpy as np, ccdn; ccdn.detect(np.zeros((64, 64), np.uint8)); " \
           "bad = [m for m in sys.modules if m.startswith(('torch', 'ccdn_training'))]; assert not bad, bad"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_finds_the_corners_of_a_rendered_board(detector, examples):
    ex = examples["board"]
    result = detector.detect(ex["path"])
    d = nearest_distances(result.xy, ex["corners"])
    assert (d < 5).mean() >= 0.95
    assert len(result) <= len(ex["corners"]) + 2


def test_image_without_a_board_returns_no_corners(detector, examples):
    result = detector.detect(examples["no-board"]["path"])
    assert len(result) == 0
    assert result.xy.shape == (0, 2) and result.xy.dtype == np.float32
    assert result.score.shape == (0,) and result.score.dtype == np.float32


def test_blank_image_returns_no_corners(detector):
    assert len(detector.detect(np.full((120, 160), 200, np.uint8))) == 0


def test_result_is_frozen_float32_xy_with_scores_in_unit_range(detector, examples):
    result = detector.detect(examples["board"]["path"])
    assert result.xy.dtype == np.float32 and result.xy.shape[1] == 2
    assert np.all((result.score >= 0) & (result.score <= 1))
    assert np.all(np.diff(result.score) <= 0)
    with pytest.raises(ValueError):
        result.xy[0, 0] = 1.0
    assert result.image_size == (640, 480)


def test_pixel_centres_are_integer_coordinates(detector, examples):
    """Shifting the image right by 3 px shifts every corner by +3.0 in x (no half-pixel offsets)."""
    import cv2

    gray = cv2.imread(str(examples["board"]["path"]), cv2.IMREAD_GRAYSCALE)
    shifted = np.zeros_like(gray)
    shifted[:, 3:] = gray[:, :-3]
    a, b = detector.detect(gray), detector.detect(shifted)
    d = np.linalg.norm(a.xy[:, None] + [3, 0] - b.xy[None], axis=2).min(1)
    assert np.median(d) < 0.05


def test_path_and_array_and_bgr_inputs_agree(detector, examples):
    import cv2

    path = examples["board"]["path"]
    bgr = cv2.imread(str(path))
    by_path, by_bgr = detector.detect(path), detector.detect(bgr)
    assert np.array_equal(by_path.xy, by_bgr.xy)


def test_module_level_detect_uses_a_cached_default(examples):
    assert np.array_equal(ccdn.detect(examples["board"]["path"]).xy, ccdn.detect(examples["board"]["path"]).xy)


def test_unknown_model_name_is_a_clear_error():
    with pytest.raises(ccdn.ModelError, match="unknown model"):
        ccdn.Detector("no-such-model")


def test_paper_model_is_bundled():
    assert "paper" in ccdn.available_models()


def test_every_bundled_model_has_a_card_titled_with_its_name_and_version():
    """models/<name>.md states the version in the model's metadata: a card left at an older version
    would document other weights (fast 1.1.0 was the first model to move past 1.0.0)."""
    from ccdn.models import models_dir
    from ccdn.session import ScoreSession

    for name in ccdn.available_models():
        info = ScoreSession(name, threads=1).info
        title = (models_dir() / f"{name}.md").read_text(encoding="utf-8").splitlines()[0]
        assert info.name == name and title.startswith(f"# Model card: `{name}` {info.version}")


@pytest.mark.parametrize("spinning", [True, False])
def test_session_workers_never_spin_between_runs_and_not_at_all_without_spinning(spinning):
    """A detector's two sessions each keep a thread pool: workers left spinning after one's run
    slowed the other's (ccdn.session); spinning=False also keeps them from spinning within a run."""
    from ccdn.session import ScoreSession

    options = ScoreSession("fast", threads=2, spinning=spinning)._session.get_session_options()
    assert options.get_session_config_entry("session.force_spinning_stop") == "1"
    assert options.intra_op_num_threads == 2
    if not spinning:
        assert options.get_session_config_entry("session.intra_op.allow_spinning") == "0"
    else:
        with pytest.raises(Exception):  # not set: onnxruntime's default, spinning
            options.get_session_config_entry("session.intra_op.allow_spinning")


def test_default_models_are_int8_only_on_cpus_with_8bit_dot_products(monkeypatch):
    from ccdn import models

    for has_vnni, names in ((True, ("fast-int8", "paper-int8")), (False, ("fast", "paper"))):
        monkeypatch.setattr(models, "_has_int8_dot_product", lambda: has_vnni)
        detector = ccdn.Detector(threads=1)
        assert (detector.coarse_model.name, detector.model.name) == names
        assert detector.models == "+".join(names)


@pytest.mark.parametrize("model", ["fast", "fast-int8", "fine", "fine-int8", "paper-int8", "paper"])
@pytest.mark.parametrize("name", ["board", "fisheye", "two-boards"])
def test_other_bundled_models_find_every_corner_of_the_examples_and_nothing_else(examples, name, model):
    ex = examples[name]
    detector = ccdn.Detector(model, threads=2)
    result = detector.detect(ex["path"])
    d = nearest_distances(result.xy, ex["corners"])
    # on two-boards `fast` used to add 2 points of a board's outline where light text touches it (a
    # stub row: ccdn.grid now drops those)
    assert len(result) == len(ex["corners"]) and d.max() < 0.3
    assert sorted(sorted((b.cols, b.rows)) for b in result.boards) == sorted(sorted(b) for b in ex["boards"])
    assert len(detector.detect(examples["no-board"]["path"])) == 0


def test_finds_most_corners_of_a_real_photo(detector, real_dev):
    case = next(c for c in real_dev if "uEye.R080" in c["path"].name)
    result = detector.detect(case["path"])
    d = nearest_distances(result.xy, case["corners"])
    assert (d < 5).mean() >= 0.9


def test_a_coarse_pass_left_to_a_finer_one_fits_no_edge_lines(real_dev, monkeypatch):
    """Real-dev's second photo (2000x1500): the 8x pass finds the board with squares of 5-7 px there.
    Where the deepest passes too needed 7 px (DEEP_MIN_SQUARE 7), the 4x pass runs: the pass is
    judged before the edge-line refinement, which runs once, on the kept pass's corners (it ran on
    both before). By default the 8x pass is kept, for the same corners (measured: within 0.031 px),
    every labelled corner found either way."""
    import ccdn.detector

    case = real_dev[1]
    gray = cv2.imread(str(case["path"]), cv2.IMREAD_GRAYSCALE)
    assert gray.shape == (1500, 2000)
    detector = ccdn.Detector(threads=2)
    coarse, on_edges = ccdn.Detector._coarse, ccdn.detector._refined_on_edges
    kept, refined = [], []
    monkeypatch.setattr(ccdn.Detector, "_coarse", lambda self, gray, small, scale, *rest: _record(
        kept, scale, coarse(self, gray, small, scale, *rest)))
    monkeypatch.setattr(ccdn.detector, "_refined_on_edges", lambda *a: refined.append(len(a[1])) or on_edges(*a))
    deepest = detector.detect(gray)
    assert kept == [(8, True)] and len(refined) == 1
    kept.clear()
    refined.clear()
    monkeypatch.setattr(ccdn.detector, "DEEP_MIN_SQUARE", ccdn.detector.COARSE_MIN_SQUARE)
    finer = detector.detect(gray)
    assert kept == [(8, False), (4, True)] and len(refined) == 1
    for result in (deepest, finer):
        assert (nearest_distances(result.xy, case["corners"]) < 1.0).all()
    assert len(deepest.xy) == len(finer.xy)
    assert np.abs(np.sort(deepest.xy, 0) - np.sort(finer.xy, 0)).max() < 0.1


def _record(log: list, scale: int, result: tuple):
    """Log a coarse pass's scale and whether it was kept; return its result."""
    log.append((scale, result[0] is not None))
    return result


def test_grid_filter_returns_boards_with_their_sizes(detector, examples):
    result = detector.detect(examples["two-boards"]["path"])
    sizes = sorted(sorted((b.cols, b.rows)) for b in result.boards)
    assert sizes == sorted(sorted(b) for b in examples["two-boards"]["boards"])
    indexed = np.concatenate([b.corner_index for b in result.boards])
    assert sorted(indexed.tolist()) == list(range(len(result)))  # every corner is on a board, once


def test_paper_postprocessing_with_kmeans_is_still_available(examples):
    paper = ccdn.Detector(threads=2, filter="kmeans", refinement="none")
    result = paper.detect(examples["board"]["path"])
    d = nearest_distances(result.xy, examples["board"]["corners"])
    assert (d < 5).mean() >= 0.95
    assert np.array_equal(result.xy, np.round(result.xy))  # integer score peaks, as in the paper


def _network_frames(detector: ccdn.Detector) -> list[tuple[int, int, str]]:
    """(height, width, model name) of the frames `detector`'s networks run on, recorded as it detects."""
    shapes = []
    for session in {id(s): s for s in (detector._coarse_session, detector._session)}.values():
        def record(frame, *args, network=session.scores, name=session.info.name, **kwargs):
            shapes.append((*frame.shape, name))
            return network(frame, *args, **kwargs)
        session.scores = record
    return shapes


def test_a_vga_frame_with_big_squares_is_detected_on_the_halved_frame(examples):
    detector = ccdn.Detector(threads=2)
    shapes = _network_frames(detector)
    coarse = detector.detect(examples["board"]["path"])  # squares ~24 px: 12 px halved
    full = ccdn.Detector(threads=2, coarse_to_fine=False).detect(examples["board"]["path"])
    assert shapes == [(240, 320, ccdn.models.default_coarse_model())]  # the full-size pass was skipped
    assert len(coarse) == len(full) == 54
    assert max(nearest_distances(coarse.xy, full.xy)) < 0.01  # refined on the same full-size pixels


def test_a_2000x1500_frame_with_75_px_squares_is_detected_on_the_8x_frame_alone(examples):
    import cv2

    gray = cv2.imread(str(examples["board"]["path"]), cv2.IMREAD_GRAYSCALE)
    big = cv2.resize(gray, (2000, 1500), interpolation=cv2.INTER_CUBIC)
    truth = (examples["board"]["corners"] + 0.5) * 3.125 - 0.5
    detector = ccdn.Detector(threads=2)
    shapes = _network_frames(detector)
    coarse = detector.detect(big)
    full = ccdn.Detector(threads=2, coarse_to_fine=False).detect(big)
    assert shapes == [(187, 250, ccdn.models.default_coarse_model())]  # squares of ~9 px there: no finer pass
    errors = [nearest_distances(r.xy, truth) for r in (coarse, full)]  # an upscaled, blurred board: ~0.2 px
    assert len(coarse) == len(full) == 54
    assert max(errors[0]) < 0.5 and np.mean(errors[0]) < np.mean(errors[1]) + 0.02


def test_shrunk_frames_are_halvings_that_map_onto_the_frame_like_a_direct_area_mean(examples):
    import cv2

    from ccdn.detector import _halvings

    gray = cv2.imread(str(examples["board"]["path"]), cv2.IMREAD_GRAYSCALE)
    odd = cv2.resize(gray, (1003, 757), interpolation=cv2.INTER_CUBIC)  # odd sides: every level crops
    levels = _halvings(odd, 3)
    for k, level in zip((2, 4, 8), levels):
        cropped = odd[: 757 - 757 % k, : 1003 - 1003 % k]
        direct = cv2.resize(cropped, (1003 // k, 757 // k), interpolation=cv2.INTER_AREA)
        assert level.shape == direct.shape
        assert np.abs(level.astype(int) - direct).max() <= 2  # rounding at each halving only


def test_squares_too_small_for_the_halved_frame_get_the_full_resolution_pass(small_board):
    frame = small_board["frame"]
    detector = ccdn.Detector(threads=2)
    shapes = _network_frames(detector)
    coarse = detector.detect(frame)
    full = ccdn.Detector(threads=2, coarse_to_fine=False).detect(frame)
    assert len(full) >= 50
    assert np.array_equal(coarse.xy, full.xy)
    # the default cascade: `fast` on the halved frame, the paper net on the full one's part where
    # `fast` responded (ccdn.regions): the board, 256x192 px, and a margin, not the whole frame
    assert shapes[0] == (240, 320, ccdn.models.default_coarse_model())
    assert {name for *_, name in shapes[1:]} == {ccdn.models.default_model()}
    assert sum(h * w for h, w, _ in shapes[1:]) < 0.6 * 480 * 640
    assert coarse.model.startswith(ccdn.models.default_model() + " ")


def test_a_board_whose_squares_thin_too_much_on_the_halved_frame_gets_the_full_resolution_pass(monkeypatch):
    """The stress set's fisheye render 7010145: the halved frame's squares are big at the board's
    middle and a few px across at its rim, where `fast` cannot follow them; kept, that pass found 61
    of the 77 corners (67 since completion's loose fits, session 38). Its thinnest squares under
    THIN_SQUARE send the frame on: 76 (all 77 before session 39 refused the second chance to crowded
    corners whose wide-sampled quads are mixed, ccdn.growth.CROWDED: a rim corner 8 px from the next),
    every one a true corner. (Kept, the pass would also have its holes looked at, ccdn.holes: left
    out here, for the halved frame alone.)"""
    from ccdn import detector as detector_module

    scene = stress_scene("fisheye", 7_010_145)
    found = ccdn.Detector(threads=2).detect(scene.image)
    assert len(scene.corners) == 77 and len(found.boards) == 1
    assert len(found) == 76 and (nearest_distances(found.xy, scene.corners) < 1.5).sum() == 76
    monkeypatch.setattr(detector_module, "THIN_SQUARE", 0.0)
    monkeypatch.setattr("ccdn.detector.predicted_holes", no_holes)
    detector = ccdn.Detector(threads=2)
    shapes = _network_frames(detector)
    assert (nearest_distances(detector.detect(scene.image).xy, scene.corners) < 1.5).sum() <= 70
    assert shapes == [(240, 320, ccdn.models.default_coarse_model())]  # the halved frame alone


def test_a_frame_without_a_board_runs_the_full_resolution_pass_only_where_the_halved_one_responded(examples):
    import cv2

    gray = cv2.imread(str(examples["no-board"]["path"]), cv2.IMREAD_GRAYSCALE)
    frame = np.full_like(gray, int(np.median(gray)))
    frame[300:420, 40:200] = gray[300:420, 40:200]  # a patch of clutter on a plain wall
    detector = ccdn.Detector(threads=2)
    shapes = _network_frames(detector)
    assert len(detector.detect(frame)) == 0
    assert shapes[0] == (240, 320, ccdn.models.default_coarse_model())
    assert 0 < sum(h * w for h, w, _ in shapes[1:]) <= (120 + 2 * 12 + 16) * (160 + 2 * 12 + 16)  # patch, halo, margin


def test_fast_check_skips_the_full_resolution_pass_when_the_shrunk_passes_find_no_board(examples, small_board):
    """Like OpenCV's CALIB_CB_FAST_CHECK: a frame without a board costs the halved pass only, a
    board with big squares is found as without the check, and one with squares too small for the
    halved frame is the price (the default finds it on the full frame)."""
    detector = ccdn.Detector(threads=2, fast_check=True)
    shapes = _network_frames(detector)
    assert len(detector.detect(examples["no-board"]["path"])) == 0
    assert shapes == [(240, 320, ccdn.models.default_coarse_model())]
    big = detector.detect(examples["board"]["path"])
    assert np.array_equal(big.xy, ccdn.Detector(threads=2).detect(examples["board"]["path"]).xy) and len(big) == 54
    frame = small_board["frame"]
    shapes.clear()
    small = detector.detect(frame)
    assert shapes == [(240, 320, ccdn.models.default_coarse_model())]  # never the full-resolution pass
    assert len(small) == 0 and small.boards == () and small.xy.shape == (0, 2)
    assert len(ccdn.Detector(threads=2).detect(frame)) >= 50


def test_a_named_model_runs_every_pass_itself(examples):
    detector = ccdn.Detector("paper", threads=2)
    shapes = _network_frames(detector)
    result = detector.detect(examples["board"]["path"])
    assert shapes == [(240, 320, "paper")] and result.model.startswith("paper ")
    cascade = ccdn.Detector("paper", threads=2, coarse_model="fast")
    assert cascade.coarse_model.name == "fast" and cascade.detect(examples["board"]["path"]).model.startswith("fast ")


def test_big_frames_run_in_strips_that_stitch_to_the_whole_frame_scores(detector, examples):
    import cv2

    gray = cv2.imread(str(examples["board"]["path"]), cv2.IMREAD_GRAYSCALE)
    whole = detector.scores(gray)
    stitched = detector._session.scores(gray, strip_pixels=100 * gray.shape[1])  # 5 strips of 100 rows
    np.testing.assert_allclose(stitched, whole, atol=1e-5)


@pytest.mark.parametrize("model", ["paper", "fine", "fast"])  # input multiples 1, 2 and 4
def test_scores_in_boxes_equal_the_whole_frame_scores_there_and_zero_elsewhere(examples, model):
    import cv2

    session = ccdn.Detector(model, threads=2)._session
    gray = cv2.imread(str(examples["board"]["path"]), cv2.IMREAD_GRAYSCALE)
    whole = session.scores(gray)
    boxes = [(101, 230, 37, 300), (0, 50, 590, 640), (400, 480, 0, 21)]  # inside, at two corners of the frame
    part = session.scores_in(gray, boxes)
    inside = np.zeros(gray.shape, bool)
    for top, bottom, left, right in boxes:
        inside[top:bottom, left:right] = True
    np.testing.assert_allclose(part[inside], whole[inside], atol=1e-5)
    assert not part[~inside].any() and whole[~inside].any()
    assert not session.scores_in(gray, []).any()  # nothing to look at: no network run, an empty map


def test_fast_check_and_exhaustive_are_refused_together():
    with pytest.raises(ValueError, match="exclude each other"):
        ccdn.Detector(fast_check=True, exhaustive=True)


def test_unknown_filter_is_refused():
    with pytest.raises(ValueError, match="unknown filter"):
        ccdn.Detector(filter="magic")


def test_a_coarse_pass_lets_refinement_walk_three_shrunk_pixels_from_a_peak():
    """`fast`'s peaks on a shrunk frame can lie ~2 shrunk px off (its 4x4-pixel output cells): this
    corner of a partial board 3.6 px from the frame's edge has its halved-frame peak 4.1 px away
    (measured), beyond the 2-shrunk-pixel walk allowed before, and was missed."""
    scene = stress_scene("partial", 7_130_015)
    corner = np.array([[48.0, 476.4]])
    assert nearest_distances(ccdn.Detector(threads=2).detect(scene.image).xy, corner)[0] < 0.1


def test_a_steep_boards_narrow_squares_are_completed():
    """At 60-75 degrees of tilt a board's squares can be narrower than the saddle fit's window, which
    then spans the neighbouring corners' edges and finds no saddle: on the stress set's extreme-pose
    render 7100104 grid completion found 15 of 54 corners (measured). Predicted corners of squares
    narrower than ccdn.completion.NARROW_ALTITUDE windows are fitted again with the narrowest window."""
    scene = stress_scene("extreme-pose", 7_100_104)
    found = ccdn.Detector(threads=2).detect(scene.image).xy
    assert (nearest_distances(found, scene.corners) < 1.5).sum() >= 48
    assert (nearest_distances(scene.corners, found) < 1.5).all()  # every corner found is a true one


def test_a_board_is_not_grown_into_cells_flatter_than_a_seed_square():
    """At 60-75 degrees of tilt a board's squares thin to slivers whose tips, where two squares of one
    colour nearly touch, score like corners; grown into cells flatter than a seed square may be
    (sine of the lattice steps' angle <= ccdn.lattice.MIN_SINE), a board took a lattice of such tips:
    on the stress set's extreme-pose render 7100021, 16 of a 25-corner board's corners lay 2-4 px
    from every true corner. A steep board whose cells stay above that (render 7100050, sines down to
    0.45) is still found whole."""
    detector = ccdn.Detector(threads=2)
    sliver = stress_scene("extreme-pose", 7_100_021)
    found = detector.detect(sliver.image).xy
    assert (nearest_distances(sliver.corners, found) < 1.5).all()  # every corner found is a true one
    board = stress_scene("extreme-pose", 7_100_050)
    found = detector.detect(board.image).xy
    assert (nearest_distances(found, board.corners) < 1.5).all()  # every true corner found
    assert (nearest_distances(board.corners, found) < 1.5).all()


def test_a_lattice_of_squares_under_five_px_both_ways_is_no_board():
    """Where the lines of a double-lined grid cross, their crossings and the cells between them form
    a lattice of ~4 px steps that passes every test a corner gets (the stress set's extreme-pose
    render 7100506: a false board of 14 corners beside the true one). A board whose squares are under
    ccdn.detector.MIN_BOARD_SQUARE px both ways, smaller than any the networks were trained on, is
    dropped; the steep board of the same frame, its squares ~4 px across but longer along, stays."""
    scene = stress_scene("extreme-pose", 7_100_506)
    result = ccdn.Detector(threads=2).detect(scene.image)
    assert (nearest_distances(scene.corners, result.xy) < 1.5).all()  # every corner found is a true one
    assert [len(board) for board in result.boards] == [len(scene.corners)]


def test_a_close_up_whose_squares_change_size_from_one_to_the_next_is_found():
    """A close-up (the stress set's close-up render 7180018: 13 corners of 100-200 px squares, running
    off the frame): perspective changes the squares' size from one to the next, and the seed squares'
    quads, sampled widely with one square's steps, cross into other squares, so the plain search finds
    no board. The search sampling quads near their corners (the marker search) finds it, and a plain
    board it finds is kept where its squares span over ccdn.grid.CLOSE_UP of the frame's shorter side."""
    scene = stress_scene("close-up", 7_180_018)
    truth = scene.corners.astype(np.float64)
    assert ccdn.grid.find_boards(scene.image, truth, np.ones(len(truth)), complete=True) == ()
    result = ccdn.Detector(threads=2).detect(scene.image)
    assert [len(board) for board in result.boards] == [len(truth)]
    assert (nearest_distances(result.xy, truth) < 0.3).all()


@pytest.mark.parametrize("seed", [7_180_035, 7_180_009])
def test_a_close_up_of_six_corners_is_a_board_of_its_own(seed, monkeypatch):
    """A close-up with 6 corners in view (the stress set's close-up renders 7180035 and 7180009:
    squares of 100-200 px; in 7180009 they are all the corners the frame holds, where find_boards
    returned before any search) is a piece of a board alone, which is no board unless it is a
    close-up (ccdn.grid.MIN_PIECE, _close_up): its squares are too large for clutter to pass for
    them. Found, indexed as it is, each corner within 0.1 px of its label; a piece that is no
    close-up stays out (tests/test_grid.py)."""
    scene = stress_scene("close-up", seed)
    boards = ccdn.Detector(threads=2).detect(scene.image).boards
    assert [len(board) for board in boards] == [6] and true_board(boards[0], scene, 0.1)
    monkeypatch.setattr("ccdn.grid.CLOSE_UP", 0.5)  # no square spans half the frame: no close-up
    assert ccdn.Detector(threads=2).detect(scene.image).boards == ()


def test_a_close_ups_corner_the_frame_cuts_off_beyond_is_kept(monkeypatch):
    """In the close-up render 7180171 (a fresh seed) the board's outermost column holds one corner,
    whose neighbours beyond lie off the frame: extrapolated from the two columns inside, they fell
    within the frame (perspective widens the squares column by column), and the outline trim
    dropped the corner as a stub. Within ccdn.cleanup.TRIM_INSIDE of a step of the frame's edge the
    frame may cut them: all 17 corners, each within 0.1 px of its label."""
    scene = stress_scene("close-up", 7_180_171)
    result = ccdn.Detector(threads=2).detect(scene.image)
    assert [len(board) for board in result.boards] == [17]
    assert nearest_distances(result.xy, scene.corners).max() < 0.1
    monkeypatch.setattr("ccdn.cleanup.TRIM_INSIDE", 0.0)
    assert [len(board) for board in ccdn.Detector(threads=2).detect(scene.image).boards] == [16]


def test_a_fisheye_close_up_is_told_by_its_largest_squares():
    """Through a fisheye lens a close-up's squares thin from ~130 px at the centre to a few px at the
    rim (the stress set's fisheye close-up render 7190017: 43 corners, none found before): the board
    the marker search finds there has a median step of ~67 px, under ccdn.grid.CLOSE_UP of the
    frame's 480 px, but the longest tenth of its steps ~128 px. Judged by those, it is kept."""
    scene = stress_scene("fisheye-close-up", 7_190_017)
    result = ccdn.Detector(threads=2).detect(scene.image)
    assert len(result.boards) == 1 and len(result.boards[0]) >= 25
    assert (nearest_distances(scene.corners, result.xy) < 0.5).all()  # every corner found is a true one


def test_a_fisheye_close_up_is_grown_from_its_large_squares_to_its_thin_rim():
    """Through a fisheye lens a close-up's squares shrink 1.5-2 x from one to the next towards the rim
    (the stress set's fisheye close-up render 7190005: 66 corners, none found before). Growth tests a
    candidate with the lattice steps measured at it where they differ from its neighbours' by over
    ccdn.growth.STEP_CHANGE (theirs sample quads outside its squares): the board is found whole."""
    scene = stress_scene("fisheye-close-up", 7_190_005)
    result = ccdn.Detector(threads=2).detect(scene.image)
    assert [len(board) for board in result.boards] == [len(scene.corners)]
    assert (nearest_distances(result.xy, scene.corners) < 0.5).all()


def test_a_prediction_two_corners_fit_about_as_well_takes_neither():
    """Between fast-growing squares a growth prediction can fall between two corners (the stress
    set's fisheye close-up render 7190032: 26 and 29 px off, a tolerance of 27 px); the nearer, a
    knight's move from the right position, gave a wrongly indexed board. A corner over half the
    tolerance off is not taken where the next lies within 1.5 x its distance (ccdn.growth.AMBIGUOUS):
    every board found maps onto the true indices by one rotation and one offset."""
    scene = stress_scene("fisheye-close-up", 7_190_032)
    result = ccdn.Detector(threads=2).detect(scene.image)
    assert result.boards
    for board in result.boards:
        apart = np.linalg.norm(board.xy[:, None] - scene.corners[None], axis=2)
        assert (apart.min(1) < 0.5).all()
        assert index_map(board, scene.grid[apart.argmin(1)]) is not None


def test_corners_under_a_shadows_edge_are_completed():
    """Where a blurred shadow's edge crosses a board, the light falls across a corner's quads: at
    their centres, half a square away, a lit dark square can outshine a shaded light one, and
    completion's strict image test failed there (the stress set's shadow render 7160017: 23 of 77
    corners missed, measured). The test also passes on the quads sampled close to the corner, where
    the light varies less, if the corner's contrast shows it lies in other light than the seed's
    (ccdn.completion.SHADED_CONTRAST)."""
    scene = stress_scene("shadow", 7_160_017)
    found = ccdn.Detector(threads=2).detect(scene.image).xy
    assert len(scene.corners) == 77
    assert (nearest_distances(found, scene.corners) < 1.5).sum() >= 75
    # every corner found is a true one; one of the outer row in the shade, found since completion's
    # edge-line crossings skip the ring test, lies 1.55 px off: the levelled frame's fit across the
    # shadow's edge (ccdn.shade.refined_across_shadows_edge) moves it there from 0.24 px
    assert (nearest_distances(scene.corners, found) < 2.0).all()


def test_corners_in_a_soft_shadow_are_fitted_on_the_log_scale():
    """Under a soft shadow the light falls off across a corner's few pixels several times faster
    than the shaded squares differ, and the saddle fit, which a slope in the grey levels shifts by
    slope / contrast, found no saddle there (the stress set's shadow render 7160010: 68 of 77
    corners, the 9 in the shade missed). Completion fits such corners again on the log scale,
    where the shade's factor becomes a small offset and the squares keep the contrast of the lit
    ones (ccdn.grid's _in_shade, _LOG_GREY): all 77, in one board, every one a true corner."""
    scene = stress_scene("shadow", 7_160_010)
    found = ccdn.Detector(threads=2).detect(scene.image)
    assert len(scene.corners) == 77 and [len(board) for board in found.boards] == [77]
    assert (nearest_distances(scene.corners, found.xy) < 1.5).all()  # every corner found, each a true one
    assert (nearest_distances(found.xy, scene.corners) < 1.5).all()


def test_a_board_continues_past_a_line_the_shadows_edge_hides(monkeypatch):
    """A shadow's sharp edge along a row of corners darkens two quads of each: that row fails the
    image test, and growth and completion, which step one position at a time, stopped there (the
    stress set's shadow render 7160200: 17 of 27 corners, the lit part; the network on the halved
    frame gives no peaks in the shade). Completion also asks the image two positions out, past such a
    line, where the quads alternate at their centres (ccdn.grid's _beyond): 21 then, the 4 more in
    the shade, in the same board, every one a true corner, the line between them empty. Since
    session 38 completion also fits corners there where only growth's plain test passes and their
    half-edges are even (ccdn.completion.LOOSE_EDGES): 25, the line filled but for one."""
    scene = stress_scene("shadow", 7_160_200)
    for loose_edges, least, gap in ((0.6, 25, 1), (1.1, 21, 2)):  # 1.1: no loose fit passes
        monkeypatch.setattr("ccdn.completion.LOOSE_EDGES", loose_edges)
        found = ccdn.Detector(threads=2).detect(scene.image)
        assert len(scene.corners) == 27 and len(found.boards) == 1
        board = found.boards[0]
        assert (nearest_distances(scene.corners, board.xy) < 1.5).all()  # every corner found is a true one
        assert (nearest_distances(board.xy, scene.corners) < 1.5).sum() >= least
        lines = [np.unique(board.grid[:, axis]) for axis in (0, 1)]
        assert max(np.diff(line).max() for line in lines) == gap  # 2: corners on both sides of an empty line


def test_corners_on_a_shadows_edge_are_found_on_their_edge_lines(monkeypatch):
    """A shadow's blurred edge through a corner curves its grey levels more than a quadric holds: no
    saddle fit finds it on either scale (the stress set's shadow render 7160182: 14 of 24 corners,
    measured, the rest along and beyond the shadow's edge). Completion then takes the crossing of
    the corner's lattice lines fitted to its squares' edges on the log scale, where each of its
    four half-edges shows at least half the strongest one's contrast (ccdn.completion.EVEN_EDGES; on a
    board's outline one runs into the margin): at least 21 true corners now, in one board (the
    saddle fits alone: 20, 14 before prune kept corners whose other neighbours the shadow hides)."""
    scene = stress_scene("shadow", 7_160_182)
    found = ccdn.Detector(threads=2).detect(scene.image)
    assert len(scene.corners) == 24 and len(found.boards) == 1 and len(found.boards[0]) >= 22
    off = nearest_distances(scene.corners, found.xy)  # each found corner's distance to the nearest true one
    assert (off < 1.5).sum() >= 21 and np.median(off) < 0.1
    assert (nearest_distances(found.xy, scene.corners) < 1.5).sum() >= 21
    monkeypatch.setattr("ccdn.completion.EVEN_EDGES", np.inf)  # no corner passes: the saddle fits alone ...
    monkeypatch.setattr("ccdn.detector.predicted_holes", no_holes)  # ... of the grid (21 with ccdn.holes' look
    monkeypatch.setattr("ccdn.detector.grown_into_shade", no_growth_into_shade)  # or with ccdn.shaded's growth)
    monkeypatch.setattr("ccdn.detector.off_lattice", as_fitted)  # (ccdn.outliers fits one of them again: 21)
    assert (nearest_distances(ccdn.Detector(threads=2).detect(scene.image).xy, scene.corners) < 1.5).sum() <= 20


def test_a_gap_on_a_shadows_edge_is_filled_from_its_edge_lines(monkeypatch):
    """A shadow's edge across a board makes the corners along it fail completion's strict image test
    at their predictions (a quad half lit, or a lit dark square lighter than a shaded light one): the
    board grows around them and leaves a gap (the stress set's shadow render 7160033: 73 of 81
    corners, measured). Where the board holds a prediction's neighbours on both sides and its quads
    look like the board's in shade, the edge-line fit is asked directly (ccdn.completion.Completion._on_shadows_edge):
    77 now, every one a true corner (with `fast` 1.1.0 on the halved frame: 75 without that fit; the
    search on the levelled frame, which this board's shadow also calls for, is left out here, and so is
    the network vouching for corners: Grower.vouch took one of them without that fit, and so is the
    full-resolution look at the holes: ccdn.holes)."""
    monkeypatch.setattr("ccdn.grid.SHADE_SPREAD", np.inf)
    monkeypatch.setattr("ccdn.detector.predicted_holes", no_holes)
    monkeypatch.setattr("ccdn.growth.VOUCH_SCORE", np.inf)
    scene = stress_scene("shadow", 7_160_033)
    found = ccdn.Detector(threads=2).detect(scene.image)
    assert len(scene.corners) == 81 and len(found.boards) == 1
    assert (nearest_distances(scene.corners, found.xy) < 1.5).all()  # each found corner near a true one
    assert (nearest_distances(found.xy, scene.corners) < 1.5).sum() >= 77  # true corners found
    monkeypatch.setattr("ccdn.completion.Completion._on_shadows_edge", lambda self, cells, *rest: np.zeros(len(cells), bool))
    monkeypatch.setattr("ccdn.detector.grown_into_shade", no_growth_into_shade)  # (77 with ccdn.shaded's growth)
    assert (nearest_distances(ccdn.Detector(threads=2).detect(scene.image).xy, scene.corners) < 1.5).sum() <= 75


def test_a_board_across_a_soft_shadows_edge_is_found_on_the_levelled_frame(monkeypatch):
    """Where a shadow's edge is soft the light falls off across a corner as steeply as its squares
    differ, and the corners along it fail the image tests on the grey and the log scale alike: in
    the stress set's shadow render 7160393 the board stopped at that edge, 29 of its 44 corners.
    A board lit that unevenly (ccdn.shade.light_spread above ccdn.grid.SHADE_SPREAD) is searched for
    again on the frame divided by its light level (ccdn.shade.levelled): all 44, indexed as they
    are, each within 0.5 px of its true place (one a penumbra pulled 1.2 px off, ccdn.outliers fits
    again; without the levelled frame: 35 since prune keeps the corners whose other neighbours the
    shadow hides, ccdn.cleanup.Cleanup._hidden_around)."""
    scene = stress_scene("shadow", 7_160_393)
    found = ccdn.Detector(threads=2).detect(scene.image)
    assert len(scene.corners) == 44 and len(found.boards) == 1 and len(found) == 44
    assert nearest_distances(scene.corners, found.xy).max() < 0.5
    board = found.boards[0]
    label = np.linalg.norm(board.xy[:, None] - scene.corners[None], axis=2).argmin(1)
    assert index_map(board, scene.grid[label]) is not None
    monkeypatch.setattr("ccdn.grid.SHADE_SPREAD", np.inf)
    monkeypatch.setattr("ccdn.detector.predicted_holes", no_holes)  # (ccdn.holes' look fills 5 of them: 40)
    monkeypatch.setattr("ccdn.detector.grown_into_shade", no_growth_into_shade)  # (ccdn.shaded's growth: 36)
    assert len(ccdn.Detector(threads=2).detect(scene.image)) <= 35


def test_the_holes_the_halved_frame_leaves_in_a_board_are_filled_at_full_resolution(monkeypatch):
    """In the stress set's occluded render 7140776 (fresh renders, seeds from the 60th on) the halved
    frame's pass finds the board without two corners inside it, next to occluders' edges (holes:
    ccdn.board.hole_cells), which the full-resolution network peaks on. Scored only around the holes,
    its peaks' fits fill them (ccdn.holes): all 61 corners, one board indexed as it is, each within
    0.1 px of its label (the two 0.03 and 0.04 px); without (HOLE_SCORE infinite) 59."""
    scene = stress_scene("occluded", 7_140_776)
    found = ccdn.Detector(threads=2).detect(scene.image)
    assert len(scene.corners) == 61 and len(found.boards) == 1
    assert nearest_distances(found.xy, scene.corners).max() < 0.1  # every corner found, within 0.1 px
    distance = np.linalg.norm(found.boards[0].xy[:, None] - scene.corners[None], axis=2)
    labelled = distance.min(1) < 1.5  # and one corner the occluder half covers, which the render leaves unlabelled
    assert index_map(SimpleNamespace(grid=found.boards[0].grid[labelled]),
                     scene.grid[distance[labelled].argmin(1)]) is not None
    monkeypatch.setattr("ccdn.holes.HOLE_SCORE", np.inf)
    assert (nearest_distances(ccdn.Detector(threads=2).detect(scene.image).xy, scene.corners) < 1.5).sum() == 59


def test_a_hole_a_shadows_edge_runs_across_takes_the_fit_on_the_levelled_frame(monkeypatch):
    """In the stress set's shadow render 7160602 (fresh renders, seeds from the 140th on) a sharp
    shadow's edge runs along a board of 195 corners: the halved frame's pass leaves holes along it,
    where the full-resolution network peaks but the saddle fit finds no saddle (the edge's slope),
    so 7 were missed. On a board lit that unevenly the hole takes the fit on the levelled frame
    (ccdn.shade.refined_across_shadows_edge) where it lies near the grid's prediction: 2 missed, the
    5 within 0.2 px of their labels, one board indexed as it is, no false corner."""
    scene = stress_scene("shadow", 7_160_602)
    found = ccdn.Detector(threads=2).detect(scene.image)
    assert len(scene.corners) == 195 and len(found.boards) == 1
    distance = nearest_distances(found.xy, scene.corners)
    assert (distance >= 1.5).sum() == 2 and (nearest_distances(scene.corners, found.xy) < 1.5).all()
    board = found.boards[0]
    label = np.linalg.norm(board.xy[:, None] - scene.corners[None], axis=2).argmin(1)
    assert index_map(board, scene.grid[label]) is not None
    monkeypatch.setattr("ccdn.holes.SHADE_SPREAD", np.inf)  # no levelled fit
    monkeypatch.setattr("ccdn.detector.grown_into_shade", no_growth_into_shade)  # (which takes them too)
    without = nearest_distances(ccdn.Detector(threads=2).detect(scene.image).xy, scene.corners)
    assert (without >= 1.5).sum() == 7
    assert distance[without >= 1.5][distance[without >= 1.5] < 1.5].max() < 0.2


def test_a_boards_part_in_deep_shade_is_grown_from_the_network_on_the_levelled_frame(monkeypatch):
    """In the stress set's shadow render 7160855 (fresh renders, seeds from the 200th on) a shadow
    takes most of the light from three columns of a board of 156 corners: the network scores them
    below its peak threshold and the board is found without them (27 missed). A shadow's edge runs
    across the found part's corners, so the board is grown outwards, into the shade and its
    penumbra, on the frame levelled around it (ccdn.shaded), where the network scores the shaded
    corners like lit ones: 27 more, within 0.2 px of their labels, one board indexed as it is, no
    false corner (one corner whose fit a penumbra pulls 1.6 px off ccdn.outliers fits again, with the
    growth or without)."""
    scene = stress_scene("shadow", 7_160_855)
    found = ccdn.Detector(threads=2).detect(scene.image)
    assert len(scene.corners) == 156 and len(found.boards) == 1
    distance = nearest_distances(found.xy, scene.corners)
    assert (distance >= 1.5).sum() == 0
    board = found.boards[0]
    to_labels = np.linalg.norm(board.xy[:, None] - scene.corners[None], axis=2)
    labelled = to_labels.min(1) < 1.5
    assert index_map(SimpleNamespace(grid=board.grid[labelled]), scene.grid[to_labels[labelled].argmin(1)]) is not None
    monkeypatch.setattr("ccdn.detector.grown_into_shade", no_growth_into_shade)
    without = ccdn.Detector(threads=2).detect(scene.image).xy
    assert (nearest_distances(without, scene.corners) >= 1.5).sum() == 27
    grown = (nearest_distances(without, scene.corners) >= 1.5) & (distance < 1.5)
    assert grown.sum() == 27 and distance[grown].max() < 0.2
    false = (nearest_distances(scene.corners, found.xy) >= 1.5).sum()
    assert false == (nearest_distances(scene.corners, without) >= 1.5).sum() == 0


def test_a_small_board_that_a_shadow_keeps_from_seeding_is_found_on_the_levelled_frame(monkeypatch):
    """In the stress set's shadow render 7160514 (fresh renders, seeds from the 140th on) a shadow
    lies across a small board (3 x 6 corners): its edge crosses a quad of every seed square's
    corners, no seed passes, and no board was found to call for the levelled frame. Where the
    full frame's pass finds no board, its corner-like points are lit more unevenly than
    ccdn.grid.SHADE_SPREAD (ccdn.shade.points_light_spread) and their median gap is taken for the
    square, the search runs again on the levelled frame: all 18 corners, one board indexed as it
    is, each within 0.11 px of its true place."""
    scene = stress_scene("shadow", 7_160_514)
    found = ccdn.Detector(threads=2).detect(scene.image)
    assert len(scene.corners) == 18 and [len(board) for board in found.boards] == [18]
    assert nearest_distances(scene.corners, found.xy).max() < 0.11
    label = np.linalg.norm(found.boards[0].xy[:, None] - scene.corners[None], axis=2).argmin(1)
    assert index_map(found.boards[0], scene.grid[label]) is not None
    monkeypatch.setattr("ccdn.grid.SHADE_SPREAD", np.inf)
    assert len(ccdn.Detector(threads=2).detect(scene.image)) == 0


def test_corners_across_a_shadows_edge_are_fitted_again_on_the_levelled_frame(monkeypatch):
    """Across a shadow's soft edge the light's slope pulls a corner's saddle fit and edge lines off
    (the stress set's shadow render 7160287: its 28 corners whose two light quads differ by more
    than ccdn.shade.SHADOW_EDGE, 0.72 px off the truth on average). On a board lit that unevenly
    they are fitted again on the frame divided by its light level (ccdn.shade.levelled): 0.23 px."""
    from ccdn.edges import lattice_steps
    from ccdn.shade import across_shadows_edge, light_levels
    scene = stress_scene("shadow", 7_160_287)

    def across_the_edge() -> np.ndarray:
        """The distance to the truth of the found board's corners across the shadow's edge."""
        (board,) = ccdn.Detector(threads=2).detect(scene.image).boards
        steps = lattice_steps(board)
        edge = across_shadows_edge(light_levels(scene.image, board.xy.astype(np.float64), steps))
        return nearest_distances(scene.corners, board.xy[edge])

    levelled = across_the_edge()
    assert len(levelled) >= 20 and levelled.mean() < 0.3
    monkeypatch.setattr("ccdn.detector.SHADE_SPREAD", np.inf)
    monkeypatch.setattr("ccdn.detector.off_lattice", as_fitted)  # (ccdn.outliers fits 2 of them again: 0.54)
    assert across_the_edge().mean() > 0.6


def test_a_steep_views_narrow_squares_complete_without_taking_the_tips_between_them():
    """A board tilted ~70 degrees: sheared squares 4.5-6 px across, the network's peaks on part of
    them (the stress set's extreme-pose render 7100011: 40 of 156 corners before). Completion's saddle
    fit gets the narrow window's second try there (ccdn.completion.NARROW_ALTITUDE), and growth matches
    within 1.5 x the cells' height, not 0.3 of their long step (SLIVER_REACH), which a tip between two
    squares of one colour lay within: without it the board took 38 such tips, wrongly indexed."""
    scene = stress_scene("extreme-pose", 7_100_011)
    found = ccdn.Detector(threads=2).detect(scene.image)
    assert len(scene.corners) == 156 and len(found.boards) == 1
    board = found.boards[0]
    distance = np.linalg.norm(board.xy[:, None] - scene.corners[None], axis=2)
    assert (distance.min(1) < 2.5).all()  # every corner found is a true one (the tips lay 3.4-5 px off)
    assert len(board) >= 100
    assert index_map(board, scene.grid[distance.argmin(1)]) is not None


def test_a_steep_boards_far_slivers_are_found_magnified(monkeypatch):
    """The stress set's extreme-pose render 7100011 (tilted ~70 degrees, squares thinning to 2-5 px
    across): the full-frame pass finds 116 of its 156 corners, the network barely scoring the far
    slivers. Its board's region, magnified twice (ccdn.magnify), gives the board with at least 150,
    every one a true corner, indexed right; without the magnified look, no more than 120."""
    from ccdn import magnify

    scene = stress_scene("extreme-pose", 7_100_011)
    detector = ccdn.Detector(threads=2)
    found = detector.detect(scene.image)
    assert len(scene.corners) == 156 and len(found.boards) == 1
    board = found.boards[0]
    distance = np.linalg.norm(board.xy[:, None] - scene.corners[None], axis=2)
    assert (distance.min(1) < 1.0).all() and len(board) >= 150
    assert index_map(board, scene.grid[distance.argmin(1)]) is not None
    monkeypatch.setattr(magnify, "THIN_ALTITUDE", 0.0)
    assert len(detector.detect(scene.image).xy) <= 120


def test_a_sliver_board_no_pass_links_is_found_stretched(monkeypatch):
    """The stress set's extreme-pose render 7100061: a board seen so steeply that its cells are sheared
    past what a lattice is grown over (sines 0.23-0.29 < ccdn.lattice.MIN_SINE) and its squares are 2-3 px
    across: no pass finds any of its 42 corners. The sliver-shaped cluster of score peaks there, looked
    at stretched 3x across its long axis (ccdn.magnify.stretched), gives the board, every corner within
    0.5 px of the truth, indexed right, but for one 0.51 px off that ccdn.outliers drops (off its
    neighbours' local lattice; 41 of 42); exhaustive detection, which looks at clusters of any shape,
    finds the same."""
    from ccdn import magnify

    scene = stress_scene("extreme-pose", 7_100_061)
    assert len(scene.corners) == 42
    for exhaustive in (False, True):
        found = ccdn.Detector(threads=2, exhaustive=exhaustive).detect(scene.image)
        assert len(found.boards) == 1 and len(found.boards[0]) == 41
        board = found.boards[0]
        distance = np.linalg.norm(board.xy[:, None] - scene.corners[None], axis=2)
        assert distance.min(1).max() < 0.5 and distance.min(1).mean() < 0.25
        assert index_map(board, scene.grid[distance.argmin(1)]) is not None
    monkeypatch.setattr(magnify, "MAX_LOOKS", 0)
    assert len(ccdn.Detector(threads=2).detect(scene.image).xy) == 0
