"""The second looks (ccdn.magnify): which region is magnified, which clusters are stretched, the pixel
mappings, the merge."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
from conftest import stress_scene

from ccdn import magnify


def test_only_a_board_with_sliver_squares_gets_a_region(detector, examples):
    """A frontal board (squares ~40 px) is not magnified; the stress set's extreme-pose render
    7100011, tilted ~70 degrees with squares thinning to 2-5 px, is, around its board, inside the
    frame and within MAX_SHARE of it."""
    frontal = detector.detect(examples["board"]["path"])
    assert frontal.boards and magnify.thin_region(frontal.boards, frontal.image_size[::-1]) is None
    scene = stress_scene("extreme-pose", 7_100_011)
    steep = detector.detect(scene.image)
    h, w = scene.image.shape
    x0, y0, x1, y1 = magnify.thin_region(steep.boards, (h, w))
    assert 0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h
    assert (x1 - x0) * (y1 - y0) <= magnify.MAX_SHARE * h * w
    inside = (steep.xy >= [x0, y0]).all(1) & (steep.xy < [x1, y1]).all(1)
    assert inside.all()


def test_magnified_pixel_centres_map_onto_the_frames():
    """Pixel centres of the region, magnified, land on the frame's pixel centres: the magnified
    pixels 2k and 2k + 1 meet at the centre of frame pixel k (x0 + k)."""
    region = (10, 20, 30, 40)
    gray = np.arange(60 * 50, dtype=np.uint16).reshape(60, 50).astype(np.uint8)
    assert magnify.magnified(gray, region).shape == (40, 40)
    frame = magnify.from_view(np.array([[0.5, 0.5], [4.5, 8.5]]), magnify.magnified_to_frame(region))
    np.testing.assert_allclose(frame, [[10, 20], [12, 24]])


def test_a_bigger_magnified_board_takes_the_place_of_the_ones_it_covers(detector, examples):
    """merge: a magnified board with more corners than the boards it shares corners with replaces
    them; one with fewer stays out; one sharing no corner is added. xy and values of both passes
    are kept, one after the other, and the boards kept index them."""
    (board,) = detector.detect(examples["board"]["path"]).boards
    xy, values = board.xy, np.ones(len(board), np.float32)
    part = dataclasses.replace(board, corner_index=np.arange(len(board) - 5), grid=board.grid[5:], xy=board.xy[5:])
    whole = dataclasses.replace(board, corner_index=np.arange(len(board)), xy=board.xy + 0.25)
    elsewhere = dataclasses.replace(whole, corner_index=np.arange(len(board)) + len(board), xy=board.xy + 1000)
    more_xy = np.concatenate([whole.xy, elsewhere.xy])
    more_values = np.ones(len(more_xy), np.float32)

    merged_xy, merged_values, kept = magnify.merge(xy[5:], values[5:], (part,), more_xy, more_values, (whole,))
    assert len(merged_xy) == len(merged_values) == len(board) - 5 + len(more_xy)
    assert len(kept) == 1 and len(kept[0]) == len(board)  # the whole board in place of its part
    np.testing.assert_array_equal(merged_xy[kept[0].corner_index], whole.xy)

    whole_first = dataclasses.replace(board, corner_index=np.arange(len(board)))
    part_magnified = dataclasses.replace(part, xy=part.xy + 0.25)
    _, _, kept = magnify.merge(xy, values, (whole_first,), more_xy, more_values, (part_magnified, elsewhere))
    assert [len(b) for b in kept] == [len(board)] * 2
    assert kept[0].corner_index.max() < len(board)  # the first pass's board, left as it was (top first)
    merged_xy = np.concatenate([xy, more_xy])
    for b in kept:
        np.testing.assert_array_equal(merged_xy[b.corner_index], b.xy)


def test_a_stretched_view_maps_back_onto_the_frame():
    """stretched: the view's x runs along the cluster's long axis, its y across it STRETCH times
    longer, and the affine it returns maps the view's pixels back onto the frame's: a point of the
    frame, sent forward by the inverse and back by from_view, lands where it was."""
    t = np.linspace(0, 100, 21)
    cluster = np.stack([50 + t, 80 + 0.5 * t + np.tile([0.0, 3.0], 11)[:21]], 1)  # a thin band along (2, 1)
    yy, xx = np.mgrid[:240, :320]
    gray = (0.5 * xx + 0.3 * yy).astype(np.uint8)  # a ramp: bicubic resampling keeps it
    view, back = magnify.stretched(gray, cluster)
    forward = cv2.invertAffineTransform(back)
    along, across = forward[0, :2], forward[1, :2]
    np.testing.assert_allclose(np.linalg.norm(along), 1.0)
    np.testing.assert_allclose(np.linalg.norm(across), magnify.STRETCH)
    assert abs(along @ np.array([2.0, 1.0]) / np.sqrt(5)) > 0.99  # x along the band
    mapped = cluster @ forward[:, :2].T + forward[:, 2]
    assert ((mapped >= 0) & (mapped < view.shape[::-1])).all()
    np.testing.assert_allclose(magnify.from_view(mapped, back), cluster, atol=1e-3)
    x, y = np.rint(mapped[10]).astype(int)  # and the view's pixel there shows the frame's grey there
    source_x, source_y = magnify.from_view(np.array([[x, y]], np.float64), back)[0]
    assert abs(float(view[y, x]) - (0.5 * source_x + 0.3 * source_y)) <= 1.5


def test_only_sliver_shaped_clusters_are_looked_at_unless_any_shape():
    """loose_clusters: of four clusters of peaks, only the sliver (a sheared lattice of 3 rows of 15,
    long and thin) is looked at by default; a round one (a 6 x 6 lattice), a line (an edge's peaks)
    and a sliver too small (3 rows of 6) too with any_shape; the largest first either way."""
    col, row = np.meshgrid(np.arange(15), np.arange(3))
    sliver = np.stack([40 + 8 * col + 2 * row, 40 + 3 * row], -1).reshape(-1, 2)
    col, row = np.meshgrid(np.arange(6), np.arange(6))
    blob = np.stack([300 + 8 * col, 50 + 8 * row], -1).reshape(-1, 2)
    line = np.stack([40 + 5 * np.arange(40), np.full(40, 300)], -1)
    small = sliver[sliver[:, 0] < 40 + 8 * 6] + [0, 120]
    peaks = np.concatenate([sliver, blob, line, small]).astype(np.float64)
    assert len(small) == 18

    def sizes(clusters):
        return [len(cluster) for cluster in clusters]

    slivers = magnify.loose_clusters(peaks, (), (480, 640))
    assert sizes(slivers) == [45]
    np.testing.assert_array_equal(slivers[0], sliver)
    assert sizes(magnify.loose_clusters(peaks, (), (480, 640), any_shape=True)) == [45, 40, 36, 18]


def test_a_sliver_beside_clutter_is_looked_at_on_its_own():
    """A sliver (3 rows of 15 peaks 8 px apart) with a lattice of clutter peaks 10 px apart just
    below it: linked within LOOSE_LINK they form one cluster, not sliver-shaped; linked within
    TIGHT_LINK the sliver stands alone and is looked at. any_shape keeps the looser link's one cluster."""
    col, row = np.meshgrid(np.arange(15), np.arange(3))
    sliver = np.stack([40 + 8 * col + 2 * row, 40 + 3 * row], -1).reshape(-1, 2)
    col, row = np.meshgrid(np.arange(6), np.arange(6))
    clutter = np.stack([40 + 10 * col, 56 + 10 * row], -1).reshape(-1, 2)
    assert magnify.TIGHT_LINK < 10 <= magnify.LOOSE_LINK
    peaks = np.concatenate([sliver, clutter]).astype(np.float64)
    slivers = magnify.loose_clusters(peaks, (), (480, 640))
    assert len(slivers) == 1
    np.testing.assert_array_equal(slivers[0], sliver)
    assert [len(c) for c in magnify.loose_clusters(peaks, (), (480, 640), any_shape=True)] == [81]
