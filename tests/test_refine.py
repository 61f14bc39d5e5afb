"""Sub-pixel refinement on renders with exact labels."""

from __future__ import annotations

import numpy as np
import pytest

import cv2

from ccdn.refine import refine, refine_from_shrunk


@pytest.fixture(scope="module")
def clean_scene():
    from ccdn_training.synth import SceneConfig, render_scene

    cfg = SceneConfig(p_no_board=0, p_two_boards=0, p_occluder=0, p_blur=0, p_motion=0, p_defocus=0, noise_sigma=(0, 0),
                      p_jpeg=0, p_glare=0, p_shadow=0, p_dark=0, p_low_contrast=0, square_px=(20, 30), max_tilt_deg=30,
                      p_radial=0, p_fisheye=0)
    return render_scene(np.random.default_rng(11), cfg)


@pytest.mark.parametrize("method", ["saddle", "cornersubpix"])
def test_refinement_recovers_exact_corners_from_integer_peaks(clean_scene, method):
    start = np.rint(clean_scene.corners).astype(np.int32)
    refined, ok = refine(clean_scene.image, start, method)
    assert ok.mean() > 0.95
    err = np.linalg.norm(refined[ok] - clean_scene.corners[ok], axis=1)
    assert err.mean() < 0.1
    assert err.mean() < np.linalg.norm(start - clean_scene.corners, axis=1).mean() / 3


def test_a_flat_patch_does_not_converge():
    flat = np.full((50, 50), 128, np.uint8)
    refined, ok = refine(flat, np.array([[25, 25]], np.int32), "saddle")
    assert not ok[0]


def test_no_corners_refine_to_empty_arrays():
    refined, ok = refine(np.zeros((20, 20), np.uint8), np.zeros((0, 2), np.int32), "saddle")
    assert refined.shape == (0, 2) and ok.shape == (0,)


def test_corners_at_the_frame_edge_refine_without_bias(clean_scene):
    """A window cut by the frame's edge must not pull the fit off (it did by 0.7-1.4 px): crop the
    render so that a corner lies 2-3 px from its top and left edges, for several corners."""
    errors = []
    for corner in clean_scene.corners[::5]:
        x0, y0 = (int(np.floor(v)) - 2 for v in corner)
        if min(x0, y0) < 0:
            continue
        refined, ok = refine(clean_scene.image[y0:, x0:], np.rint(corner - [x0, y0])[None].astype(np.int32),
                             "saddle", radius=5)
        assert ok[0]
        errors.append(np.linalg.norm(refined[0] - (corner - [x0, y0])))
    assert len(errors) >= 5
    assert np.mean(errors) < 0.15 and np.max(errors) < 0.3


def test_peaks_of_a_halved_frame_refine_on_it_first_then_to_the_exact_corners(clean_scene):
    """Coarse-to-fine: peaks of the half-size frame, here up to a (half-size) pixel off as the
    network's can be, start ~2 px off at full size; the rough pass on the half-size frame brings
    every one to the corner (the fine pass alone, from there, converges on ~2/3 of them)."""
    image = clean_scene.image
    half = cv2.resize(image, (image.shape[1] // 2, image.shape[0] // 2), interpolation=cv2.INTER_AREA)
    peaks = np.rint((clean_scene.corners + 0.5) / 2 - 0.5).astype(np.int32)
    peaks += np.random.default_rng(0).integers(-1, 2, peaks.shape, dtype=np.int32)
    refined, ok = refine_from_shrunk(image, half, peaks, 2, 3, 4.0)
    assert ok.mean() > 0.95
    assert np.linalg.norm(refined[ok] - clean_scene.corners[ok], axis=1).mean() < 0.05


def test_peaks_whose_fit_fails_on_the_halved_frame_still_get_the_full_size_fit(clean_scene):
    """The shrunk frame's fit can fail where the full frame's does not (an occluder's edge next to
    the corner, glare): such peaks are fitted on the full frame from the peak itself. Here the
    halved frame is blank, so every rough fit fails."""
    image = clean_scene.image
    blank = np.full((image.shape[0] // 2, image.shape[1] // 2), 128, np.uint8)
    peaks = np.rint((clean_scene.corners + 0.5) / 2 - 0.5).astype(np.int32)  # within a pixel at full size
    refined, ok = refine_from_shrunk(image, blank, peaks, 2, 3, 4.0)
    assert ok.mean() > 0.9
    assert np.linalg.norm(refined[ok] - clean_scene.corners[ok], axis=1).mean() < 0.05


def test_corners_at_the_frame_edge_refine_from_a_halved_frame_without_bias(clean_scene):
    """Coarse-to-fine at the frame's edge: corners 2-3 px from its top and left edges, from peaks of
    the halved frame, land on the exact corner."""
    errors = []
    for corner in clean_scene.corners[::5]:
        x0, y0 = (int(np.floor(v)) - 2 for v in corner)
        if min(x0, y0) < 0:
            continue
        image = clean_scene.image[y0:, x0:]
        half = cv2.resize(image, (image.shape[1] // 2, image.shape[0] // 2), interpolation=cv2.INTER_AREA)
        peak = np.rint((corner - [x0, y0] + 0.5) / 2 - 0.5)[None].astype(np.int32)
        refined, ok = refine_from_shrunk(image, half, peak, 2, 4, 4.0)
        assert ok[0]
        errors.append(np.linalg.norm(refined[0] - (corner - [x0, y0])))
    assert len(errors) >= 5
    assert np.mean(errors) < 0.1 and np.max(errors) < 0.25


def test_corners_spread_over_a_big_frame_refine_as_they_do_alone(clean_scene):
    """Corners far apart on a big frame are smoothed patch by patch (a stacked mosaic), not as one
    region: the result must be the region's, also where the frame's edge cuts a patch."""
    image, corners = clean_scene.image, clean_scene.corners
    h, w = image.shape
    canvas = np.full((1500, 2000), 128, np.uint8)
    canvas[:h, :w] = image
    canvas[-h:, -w:] = image
    x_cut = int(np.floor(corners[:, 0].min())) - 6  # a copy whose leftmost corner lies 6-7 px from the edge:
    # its window stays inside the frame, its blur does not
    canvas[700 : 700 + h, : w - x_cut] = image[:, x_cut:]
    groups = [corners, corners + [2000 - w, 1500 - h], corners[corners[:, 0].argmin()][None] + [-x_cut, 700]]
    start = np.rint(np.concatenate(groups)).astype(np.int32)
    together, ok = refine(canvas, start, "saddle", radius=4)
    bounds = np.cumsum([0] + [len(g) for g in groups])
    alone = [refine(canvas, start[a:b], "saddle", radius=4) for a, b in zip(bounds[:-1], bounds[1:])]  # small regions
    assert np.array_equal(ok, np.concatenate([a[1] for a in alone])) and ok.mean() > 0.95
    assert np.abs(together - np.concatenate([a[0] for a in alone])).max() < 1e-3
    truth = np.concatenate(groups)
    assert np.linalg.norm(together[ok] - truth[ok], axis=1).mean() < 0.1


def test_the_window_stays_small_on_big_squares_where_a_wide_one_is_worse():
    """The window follows the blur, not the square (window_for_spacing's measurement): on renders of
    the training distribution with squares >= 55 px, the rule's 4 px window beats the 6 px one that
    a tenth of such squares would give."""
    from ccdn_training.synth import SceneConfig, render_scene

    from ccdn.grid import nearest_neighbours
    from ccdn.refine import window_for_spacing

    cfg = SceneConfig(p_no_board=0, p_two_boards=0, p_occluder=0, square_px=(70, 110))
    errors = {"rule": [], 6: []}
    for seed in range(9_970_000, 9_970_016):
        scene = render_scene(np.random.default_rng(seed), cfg)
        spacing = np.median(np.sqrt(nearest_neighbours(scene.corners.astype(np.float64), 1)[1]))
        if len(scene.corners) < 4 or spacing < 55:  # steep views and big boards shrink the squares
            continue
        start = scene.corners + np.random.default_rng(seed).uniform(-0.5, 0.5, scene.corners.shape)
        assert window_for_spacing(spacing) == 4
        for key, radius in (("rule", window_for_spacing(spacing)), (6, 6)):
            refined, ok = refine(scene.image, start.astype(np.float32), "saddle", 2.0, radius)
            errors[key].append(np.linalg.norm(refined[ok] - scene.corners[ok], axis=1))
    assert len(errors[6]) >= 4
    rule, wide = (np.concatenate(errors[k]).mean() for k in ("rule", 6))
    assert rule < wide  # measured: 0.125 vs 0.145 px


def test_fits_at_sub_pixel_centres_equal_fits_of_the_bilinear_samples(clean_scene):
    """_fit blends the 4 integer fits around a sub-pixel centre (the fit is linear in the pixels):
    it must equal the plain fit of the bilinearly sampled patch, inside and at the frame's edge."""
    from ccdn.refine import _fit, _quadric, _smoothed_around, _weighted_pinv

    x0, y0 = np.floor(clean_scene.corners[0]).astype(int) - 1  # cropped: that corner's window is cut
    gray = clean_scene.image[y0:, x0:]
    h, w = gray.shape
    corners = clean_scene.corners - [x0, y0]
    corners = corners[(corners >= 0).all(1)]
    centres = corners[:8] + np.random.default_rng(3).uniform(-0.5, 0.5, (min(8, len(corners)), 2))
    centres[0] = np.maximum(centres[0], 0)
    assert (centres[0] < 3).all() and (centres[1:] >= 3).any()
    quadric = _quadric(3)
    smoothed = _smoothed_around(gray, centres, 1.2, 12)
    offset, ok = _fit(smoothed, centres, quadric, 0.0)
    frame = np.zeros((h, w), np.float32)  # the smoothed pixels, back in frame coordinates
    for k, (x, y) in enumerate(np.floor(centres).astype(int)):
        for dy in range(-4, 6):
            for dx in range(-4, 6):
                if 0 <= x + dx < w and 0 <= y + dy < h:
                    frame[y + dy, x + dx] = smoothed.image[y + dy - smoothed.shift[k, 1], x + dx - smoothed.shift[k, 0]]
    for k, (x, y) in enumerate(centres):
        sx, sy = x + quadric.ox, y + quadric.oy
        inside = (sx >= 0) & (sx <= w - 1) & (sy >= 0) & (sy <= h - 1)
        x0, y0 = np.floor(np.clip(sx, 0, w - 1)).astype(int), np.floor(np.clip(sy, 0, h - 1)).astype(int)
        fx, fy = np.clip(sx, 0, w - 1) - x0, np.clip(sy, 0, h - 1) - y0
        x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
        values = ((1 - fx) * (1 - fy) * frame[y0, x0] + fx * (1 - fy) * frame[y0, x1] + (1 - fx) * fy * frame[y1, x0]
                  + fx * fy * frame[y1, x1])
        a, b, c, d, e, _ = _weighted_pinv(quadric.design, quadric.weight * inside) @ values
        expected = np.linalg.solve([[2 * a, b], [b, 2 * c]], [-d, -e])
        assert np.allclose(offset[k], expected, atol=1e-6), k


def test_patches_hold_the_frame_pixels_whole_or_cut_by_its_edge(clean_scene):
    """Corners spread over a big frame are smoothed in one patch per corner: a patch inside the frame
    is a copy of its window, a patch the frame's edge cuts holds the frame's pixels and zeros beyond
    (unsmoothed here, sigma 0, to compare pixels). Two copies of the board far apart make the
    smoothing work on patches rather than on the region the corners span; corners at the frame's
    edge cut theirs."""
    from ccdn.refine import _smoothed_around

    h, w = clean_scene.image.shape
    frame = np.zeros((3 * h, 3 * w), np.uint8)
    frame[:h, :w] = frame[2 * h :, 2 * w :] = clean_scene.image
    frame[-1, -1] = frame[0, 0] = 255  # pixels a cut patch must keep where the frame ends
    frame_corners = [[0.0, 0.0], [3 * w - 1, 3 * h - 1]]
    start = np.concatenate([clean_scene.corners, clean_scene.corners + [2 * w, 2 * h], frame_corners])
    smoothed = _smoothed_around(frame, start, 0.0, 12)
    side = smoothed.high[0, 0] - smoothed.low[0, 0] + 1
    assert smoothed.image.shape == (side, len(start) * side)  # patches, side by side
    padded = np.pad(frame, side)
    cut = 0
    for k in range(len(start)):
        (x, y), (left, _) = smoothed.shift[k] + smoothed.low[k], smoothed.low[k]
        patch = smoothed.image[:, left : left + side]
        assert np.array_equal(patch, padded[y + side : y + 2 * side, x + side : x + 2 * side]), k
        cut += not (0 <= x and 0 <= y and x + side <= 3 * w and y + side <= 3 * h)
    assert cut >= 2
