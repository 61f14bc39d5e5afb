"""Synthetic checkerboard scenes with exact sub-pixel inner-corner labels.

A scene is rendered by inverse mapping at 3x supersampling: every sub-pixel of the output is taken
through the lens model (distorted -> ideal pinhole coordinates) and the inverse board homography to
board coordinates, where the checker pattern is evaluated exactly; an area average brings it back
to output resolution. Labels go the other way: board corners -> homography -> inverse lens model
(solved to 1e-6 px). Pixel convention: (0, 0) is the centre of the top-left pixel.

Everything is deterministic given the seed of the `numpy.random.Generator` passed in.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

SUPERSAMPLE = 3
PAPER_BOARDS = [(7, 7), (6, 9), (7, 11), (9, 9), (12, 13)]


@dataclass
class Scene:
    """A rendered image and its labels.

    image: (H, W) uint8 gray. corners: (N, 2) float32 (x, y) of visible inner corners.
    board_index: (N,) int board id of each corner; grid: (N, 2) int (row, col) on its board.
    ignore: (M, 2) float32 corners too occluded or too near the border to count either way.
    boards: (cols, rows) inner-corner size of each board rendered.
    """

    image: np.ndarray
    corners: np.ndarray
    board_index: np.ndarray
    grid: np.ndarray
    ignore: np.ndarray
    boards: list[tuple[int, int]] = field(default_factory=list)


@dataclass
class SceneConfig:
    """Ranges of the random scene; the defaults are the training distribution."""

    width: int = 640
    height: int = 480
    p_no_board: float = 0.08
    p_two_boards: float = 0.12
    square_px: tuple[float, float] = (6.0, 110.0)
    min_tilt_deg: float = 0.0
    max_tilt_deg: float = 70.0
    p_radial: float = 0.35
    radial_k1: tuple[float, float] = (-0.12, 0.45)  # > 0: barrel
    p_fisheye: float = 0.12
    p_margin: float = 0.6
    p_occluder: float = 0.2
    p_invert: float = 0.5
    p_blur: float = 0.45
    p_motion: float = 0.1
    p_defocus: float = 0.1
    p_noise: float = 0.6
    noise_sigma: tuple[float, float] = (0.0, 0.06)
    p_jpeg: float = 0.3
    p_low_contrast: float = 0.15
    p_dark: float = 0.1
    p_glare: float = 0.15
    p_shadow: float = 0.2
    shadow_depth: tuple[float, float] = (0.3, 0.75)  # share of the light a shadow takes away
    p_markers: float = 0.0  # a ChArUco-style board: a random 5x5-bit marker in each light square (0: no draw)
    marker_ratio: tuple[float, float] = (0.6, 0.8)  # the marker's side, of the square's
    board_sizes: list[tuple[int, int]] | None = None  # None: paper sizes and 3..15 random


# ----------------------------------------------------------------------------- lens models
@dataclass
class Lens:
    """Maps distorted output pixels to ideal pinhole pixels (and back for labels)."""

    f: float
    cx: float
    cy: float
    kind: str = "none"  # none | radial | fisheye
    k: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)  # k1, k2, p1, p2

    def to_ideal(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Distorted pixel -> ideal pixel; third output says where the mapping is valid."""
        xn, yn = (x - self.cx) / self.f, (y - self.cy) / self.f
        valid = np.ones(np.shape(x), bool)
        if self.kind == "radial":
            k1, k2, p1, p2 = self.k
            r2 = xn * xn + yn * yn
            radial = 1 + k1 * r2 + k2 * r2 * r2
            xu = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
            yu = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
        elif self.kind == "fisheye":  # equidistant: r_d = f * theta
            theta = np.sqrt(xn * xn + yn * yn)
            valid = theta < 1.45
            scale = np.where(theta > 1e-9, np.tan(np.minimum(theta, 1.45)) / np.maximum(theta, 1e-9), 1.0)
            xu, yu = xn * scale, yn * scale
        else:
            xu, yu = xn, yn
        return self.cx + self.f * xu, self.cy + self.f * yu, valid

    def to_distorted(self, xu: np.ndarray, yu: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Ideal pixel -> distorted pixel by Newton's method; third output: converged."""
        if self.kind == "fisheye":
            xn, yn = (xu - self.cx) / self.f, (yu - self.cy) / self.f
            r = np.sqrt(xn * xn + yn * yn)
            scale = np.where(r > 1e-12, np.arctan(r) / np.maximum(r, 1e-12), 1.0)
            return self.cx + self.f * xn * scale, self.cy + self.f * yn * scale, np.arctan(r) < 1.45
        x, y = xu.astype(np.float64).copy(), yu.astype(np.float64).copy()
        if self.kind == "none":
            return x, y, np.ones(x.shape, bool)
        h = 1e-3
        for _ in range(30):
            fx, fy, _ = self.to_ideal(x, y)
            ex, ey = fx - xu, fy - yu
            ax, ay, _ = self.to_ideal(x + h, y)
            bx, by, _ = self.to_ideal(x, y + h)
            j11, j21, j12, j22 = (ax - fx) / h, (ay - fy) / h, (bx - fx) / h, (by - fy) / h
            det = j11 * j22 - j12 * j21
            det = np.where(np.abs(det) < 1e-9, 1e-9, det)
            x = x - (j22 * ex - j12 * ey) / det
            y = y - (-j21 * ex + j11 * ey) / det
        fx, fy, _ = self.to_ideal(x, y)
        ok = np.hypot(fx - xu, fy - yu) < 1e-6
        return x, y, ok & np.isfinite(x) & np.isfinite(y)


def random_lens(rng: np.random.Generator, cfg: SceneConfig) -> Lens:
    w, h = cfg.width, cfg.height
    cx = w / 2 - 0.5 + rng.normal(0, w * 0.02)
    cy = h / 2 - 0.5 + rng.normal(0, h * 0.02)
    u = rng.random()
    if u < cfg.p_fisheye:
        return Lens(rng.uniform(0.28, 0.6) * w, cx, cy, "fisheye")
    f = rng.uniform(0.55, 1.6) * w
    if u < cfg.p_fisheye + cfg.p_radial:
        r_max = np.hypot(w, h) / 2 / f
        for _ in range(20):
            k1, k2 = rng.uniform(*cfg.radial_k1), rng.uniform(-0.05, 0.15)
            r = np.linspace(0, r_max, 64)
            if np.all(np.diff(r * (1 + k1 * r**2 + k2 * r**4)) > 0):  # monotonic: a real lens
                p1, p2 = rng.normal(0, 0.004, 2)
                return Lens(f, cx, cy, "radial", (k1, k2, p1, p2))
    return Lens(f, cx, cy)


# ----------------------------------------------------------------------------- boards
def _rotation(tilt: float, direction: float, roll: float) -> np.ndarray:
    axis = np.array([np.cos(direction), np.sin(direction), 0.0])
    r_tilt, _ = cv2.Rodrigues(axis * tilt)
    r_roll, _ = cv2.Rodrigues(np.array([0.0, 0.0, roll]))
    return r_tilt @ r_roll


@dataclass
class Board:
    """A board in the scene: inner-corner size, margin (squares) and board->ideal homography."""

    cols: int
    rows: int
    margin: float
    homography: np.ndarray  # maps (u, v, 1), u along cols in squares, to ideal pixels
    dark: float
    light: float
    markers: np.ndarray | None = None  # (rows + 1, cols + 1, 7, 7) bool: dark marker bits per square (ChArUco-style)
    marker_ratio: float = 0.0  # the markers' side, of a square's

    def inner_corners(self) -> tuple[np.ndarray, np.ndarray]:
        """Ideal-pixel positions (N, 2) of the inner corners and their (row, col), row-major."""
        rr, cc = np.mgrid[0 : self.rows, 0 : self.cols]
        uv1 = np.stack([cc.ravel() + 1.0, rr.ravel() + 1.0, np.ones(rr.size)])
        p = self.homography @ uv1
        in_front = p[2] > 1e-9
        xy = (p[:2] / np.where(in_front, p[2], 1.0)).T
        grid = np.stack([rr.ravel(), cc.ravel()], 1)
        return xy[in_front], grid[in_front]

    def render(self, xu: np.ndarray, yu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Intensity and coverage mask of the board at ideal-pixel positions."""
        inv = np.linalg.inv(self.homography)
        p0 = inv[0, 0] * xu + inv[0, 1] * yu + inv[0, 2]
        p1 = inv[1, 0] * xu + inv[1, 1] * yu + inv[1, 2]
        p2 = inv[2, 0] * xu + inv[2, 1] * yu + inv[2, 2]
        front = p2 > 1e-12
        p2 = np.where(front, p2, 1.0)
        u, v = p0 / p2, p1 / p2
        m = self.margin
        on_board = front & (u >= -m) & (u <= self.cols + 1 + m) & (v >= -m) & (v <= self.rows + 1 + m)
        in_squares = (u >= 0) & (u <= self.cols + 1) & (v >= 0) & (v <= self.rows + 1)
        parity = (np.floor(u) + np.floor(v)) % 2 == 0  # top-left square is dark
        dark = in_squares & parity
        if self.markers is not None:  # light squares hold markers: 7 x 7 cells, the outer ring dark
            dark |= in_squares & ~parity & self._marker_bits(u, v)
        value = np.where(dark, self.dark, self.light)
        return value.astype(np.float32), on_board

    def _marker_bits(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Whether board points (u, v) (squares) fall on a dark bit of their square's marker."""
        rows, cols = self.markers.shape[:2]
        col = np.clip(np.floor(u), 0, cols - 1).astype(np.int64)
        row = np.clip(np.floor(v), 0, rows - 1).astype(np.int64)
        border = (1 - self.marker_ratio) / 2
        fu, fv = (u - np.floor(u) - border) / self.marker_ratio, (v - np.floor(v) - border) / self.marker_ratio
        inside = (fu >= 0) & (fu < 1) & (fv >= 0) & (fv < 1)
        bu = np.clip((fu * 7).astype(np.int64), 0, 6)
        bv = np.clip((fv * 7).astype(np.int64), 0, 6)
        return inside & self.markers[row, col, bv, bu]


def random_board_size(rng: np.random.Generator, cfg: SceneConfig) -> tuple[int, int]:
    if cfg.board_sizes:
        return cfg.board_sizes[rng.integers(len(cfg.board_sizes))]
    if rng.random() < 0.4:
        c, r = PAPER_BOARDS[rng.integers(len(PAPER_BOARDS))]
    else:
        c, r = rng.integers(3, 16, 2)
    return (int(c), int(r)) if rng.random() < 0.5 else (int(r), int(c))


def random_board(rng: np.random.Generator, cfg: SceneConfig, lens: Lens) -> Board:
    cols, rows = random_board_size(rng, cfg)
    square = np.exp(rng.uniform(*np.log(cfg.square_px)))
    z = lens.f / square
    lo, hi = np.radians(cfg.min_tilt_deg), np.radians(cfg.max_tilt_deg)
    tilt = lo + (hi - lo) * np.sqrt(rng.random())
    rot = _rotation(tilt, rng.uniform(0, 2 * np.pi), rng.uniform(0, 2 * np.pi))
    cx = rng.uniform(0.1, 0.9) * cfg.width
    cy = rng.uniform(0.1, 0.9) * cfg.height
    t = z * np.array([(cx - lens.cx) / lens.f, (cy - lens.cy) / lens.f, 1.0])
    k = np.array([[lens.f, 0, lens.cx], [0, lens.f, lens.cy], [0, 0, 1.0]])
    centre = np.array([[1, 0, -(cols + 1) / 2], [0, 1, -(rows + 1) / 2], [0, 0, 1.0]])
    h = k @ np.column_stack([rot[:, 0], rot[:, 1], t]) @ centre
    margin = rng.uniform(0.3, 1.5) if rng.random() < cfg.p_margin else 0.0
    dark = rng.uniform(0.0, 0.35)
    light = rng.uniform(max(dark + 0.25, 0.55), 1.0)
    # markers draw from a spawned generator, which leaves rng's stream as it is: the scene is the same with or without
    if cfg.p_markers > 0 and (marker_rng := rng.spawn(1)[0]).random() < cfg.p_markers:
        bits = marker_rng.random((rows + 1, cols + 1, 7, 7)) < 0.5
        bits[:, :, [0, -1], :] = bits[:, :, :, [0, -1]] = True  # each marker's dark outer ring
        return Board(cols, rows, margin, h, dark, light, bits, float(marker_rng.uniform(*cfg.marker_ratio)))
    return Board(cols, rows, margin, h, dark, light)


# ----------------------------------------------------------------------------- background
def random_background(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Clutter at render resolution: smooth texture, edges, L and T junctions, lines, grids, text."""
    small = rng.random((rng.integers(2, 9), rng.integers(2, 9))).astype(np.float32)
    base = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC) * rng.uniform(0.2, 0.8) + rng.uniform(0, 0.5)
    img = np.clip(base * 255, 0, 255).astype(np.uint8)  # OpenCV draws text on 8-bit images only
    scale = h / 480
    for _ in range(rng.integers(0, 25)):
        colour = int(rng.integers(0, 256))
        kind = rng.integers(6)
        p = (rng.random(2) * [w, h]).astype(int)
        q = (rng.random(2) * [w, h]).astype(int)
        if kind == 0:
            cv2.rectangle(img, tuple(p), tuple(q), colour, -1 if rng.random() < 0.7 else int(1 + 3 * rng.random() * scale))
        elif kind == 1:
            cv2.line(img, tuple(p), tuple(q), colour, int(1 + rng.random() * 6 * scale), cv2.LINE_AA)
        elif kind == 2:
            cv2.circle(img, tuple(p), int(rng.uniform(5, 80) * scale), colour, -1 if rng.random() < 0.5 else 2, cv2.LINE_AA)
        elif kind == 3:
            pts = (rng.random((rng.integers(3, 7), 2)) * [w, h]).astype(np.int32)
            cv2.fillPoly(img, [pts], colour, cv2.LINE_AA)
        elif kind == 4:  # a grid of lines: crossings that are not checker corners
            step = int(rng.uniform(10, 60) * scale)
            x0, y0 = min(p[0], q[0]), min(p[1], q[1])
            x1, y1 = max(p[0], q[0]), max(p[1], q[1])
            thick = int(1 + rng.random() * 2 * scale)
            for x in range(x0, x1, step):
                cv2.line(img, (x, y0), (x, y1), colour, thick)
            for y in range(y0, y1, step):
                cv2.line(img, (x0, y), (x1, y), colour, thick)
        else:
            text = "".join(rng.choice(list("ABCDEFGHKMNXZ0123456789+#"), rng.integers(2, 9)))
            cv2.putText(img, text, tuple(p), cv2.FONT_HERSHEY_SIMPLEX, rng.uniform(0.5, 3) * scale, colour,
                        int(1 + rng.random() * 4 * scale), cv2.LINE_AA)
    return img.astype(np.float32) / 255


# ----------------------------------------------------------------------------- photometry
def _blur_and_light(img: np.ndarray, rng: np.random.Generator, cfg: SceneConfig) -> tuple[np.ndarray, float]:
    """Light, shadow, glare, contrast and blur; also returns the factor applied to the contrast."""
    h, w = img.shape
    gain = 1.0
    small = rng.random((3, 3)).astype(np.float32)
    light = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    img = img * (rng.uniform(0.6, 1.0) + rng.uniform(0.0, 0.5) * (light - 0.5))
    if rng.random() < cfg.p_shadow:
        pts = (rng.random((rng.integers(3, 6), 2)) * [w, h]).astype(np.int32)
        mask = np.zeros((h, w), np.float32)
        cv2.fillPoly(mask, [pts], 1.0)
        mask = cv2.GaussianBlur(mask, (0, 0), rng.uniform(1, 15))
        img = img * (1 - mask * rng.uniform(*cfg.shadow_depth))
    if rng.random() < cfg.p_glare:
        yy, xx = np.mgrid[0:h, 0:w]
        c = rng.random(2) * [w, h]
        s = rng.uniform(10, 120)
        img = img + rng.uniform(0.2, 0.7) * np.exp(-((xx - c[0]) ** 2 + (yy - c[1]) ** 2) / (2 * s * s))
    if rng.random() < cfg.p_low_contrast:
        m = rng.uniform(0.2, 0.8)
        factor = rng.uniform(0.2, 0.45)
        img, gain = m + (img - m) * factor, gain * factor
    if rng.random() < cfg.p_dark:
        factor = rng.uniform(0.15, 0.35)
        img, gain = img * factor, gain * factor
    img = np.clip(img, 0, 1).astype(np.float32)
    if rng.random() < cfg.p_blur:
        img = cv2.GaussianBlur(img, (0, 0), rng.uniform(0.3, 1.8))
    if rng.random() < cfg.p_defocus:
        r = int(rng.integers(1, 4))
        kernel = np.zeros((2 * r + 1, 2 * r + 1), np.float32)
        cv2.circle(kernel, (r, r), r, 1.0, -1)
        img = cv2.filter2D(img, -1, kernel / kernel.sum())
    if rng.random() < cfg.p_motion:  # odd lengths: an even kernel's anchor would shift the image half a pixel
        n = 2 * int(rng.integers(1, 5)) + 1
        kernel = np.zeros((n, n), np.float32)
        kernel[n // 2, :] = 1.0
        rot = cv2.getRotationMatrix2D(((n - 1) / 2, (n - 1) / 2), rng.uniform(0, 180), 1.0)
        kernel = cv2.warpAffine(kernel, rot, (n, n))
        img = cv2.filter2D(img, -1, kernel / kernel.sum())
    return img, gain


def _finish(img: np.ndarray, rng: np.random.Generator, cfg: SceneConfig, max_sigma: float) -> np.ndarray:
    """Inversion, noise (at most `max_sigma`, so the corners stay visible), 8 bits, JPEG."""
    if rng.random() < cfg.p_invert:
        img = 1.0 - img
    sigma = min(rng.uniform(*cfg.noise_sigma), max_sigma) if rng.random() < cfg.p_noise else 0.0
    img = img + rng.normal(0, 1, img.shape).astype(np.float32) * sigma
    out = np.clip(img * 255 + 0.5, 0, 255).astype(np.uint8)
    if rng.random() < cfg.p_jpeg:
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(30, 95))])
        out = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    return out


# ----------------------------------------------------------------------------- scene
def render_scene(rng: np.random.Generator, cfg: SceneConfig | None = None) -> Scene:
    """Render one random scene of `cfg` (default: the training distribution)."""
    cfg = cfg or SceneConfig()
    w, h, s = cfg.width, cfg.height, SUPERSAMPLE
    lens = random_lens(rng, cfg)
    xs = (np.arange(w * s, dtype=np.float32) + 0.5) / s - 0.5
    ys = (np.arange(h * s, dtype=np.float32) + 0.5) / s - 0.5
    xd, yd = np.meshgrid(xs, ys)
    xu, yu, valid = lens.to_ideal(xd, yd)
    img = random_background(rng, h * s, w * s)

    n_boards = 0 if rng.random() < cfg.p_no_board else (2 if rng.random() < cfg.p_two_boards else 1)
    boards = [random_board(rng, cfg, lens) for _ in range(n_boards)]
    covers = []
    for board in boards:
        value, mask = board.render(xu, yu)
        img = np.where(mask, value, img)
        covers.append(mask)
    if boards and rng.random() < cfg.p_occluder:
        occ = np.zeros((h * s, w * s), np.uint8)
        for _ in range(rng.integers(1, 3)):
            c = rng.random(2) * [w * s, h * s]
            pts = (c + rng.normal(0, 40 * s, (rng.integers(3, 7), 2))).astype(np.int32)
            cv2.fillPoly(occ, [pts], 1)
        img = np.where(occ > 0, float(rng.random()), img)
        covers.append(occ > 0)
    img = np.where(valid, img, 0.0).astype(np.float32)
    img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)

    corners, board_index, grid, ignore = _labels(boards, covers, lens, valid, w, h)
    img, gain = _blur_and_light(img, rng, cfg)
    contrast = min((b.light - b.dark for b in boards), default=1.0) * gain
    image = _finish(img, rng, cfg, max_sigma=0.35 * contrast)
    return Scene(image, corners, board_index, grid, ignore, [(b.cols, b.rows) for b in boards])


def _labels(boards, covers, lens, valid, w, h):
    """Visible corners of each board; corners near occluders, later boards or the border are ignored."""
    s = SUPERSAMPLE
    keep_xy, keep_board, keep_grid, ignore = [], [], [], []
    for i, board in enumerate(boards):
        ideal, grid = board.inner_corners()
        if len(ideal) == 0:
            continue
        x, y, ok = lens.to_distorted(ideal[:, 0], ideal[:, 1])
        inside = ok & (x > -0.5) & (x < w - 0.5) & (y > -0.5) & (y < h - 0.5)
        x, y, grid = x[inside], y[inside], grid[inside]
        hidden = np.zeros(len(x), bool)
        for later in covers[i + 1 :]:
            hidden |= _near(later, x, y, s, radius=3.0)
        hidden |= ~_near(valid, x, y, s, radius=0.0) | _near(~valid, x, y, s, radius=3.0)
        near_border = (x < 1.5) | (y < 1.5) | (x > w - 2.5) | (y > h - 2.5)
        bad = hidden | near_border
        ignore.append(np.stack([x[bad], y[bad]], 1))
        keep_xy.append(np.stack([x[~bad], y[~bad]], 1))
        keep_board.append(np.full((~bad).sum(), i))
        keep_grid.append(grid[~bad])
    if not keep_xy:
        return np.zeros((0, 2), np.float32), np.zeros(0, int), np.zeros((0, 2), int), np.zeros((0, 2), np.float32)
    return (np.concatenate(keep_xy).astype(np.float32), np.concatenate(keep_board),
            np.concatenate(keep_grid).astype(int), np.concatenate(ignore).astype(np.float32))


def _near(mask: np.ndarray, x: np.ndarray, y: np.ndarray, s: int, radius: float) -> np.ndarray:
    """Whether a supersampled boolean mask is set within `radius` output px of each point."""
    if len(x) == 0:
        return np.zeros(0, bool)
    r = int(np.ceil(radius * s))
    offsets = np.arange(-r, r + 1)
    ox, oy = np.meshgrid(offsets, offsets)
    disc = ox**2 + oy**2 <= r * r
    ox, oy = ox[disc], oy[disc]
    cx = np.round((x + 0.5) * s - 0.5).astype(int)
    cy = np.round((y + 0.5) * s - 0.5).astype(int)
    px = np.clip(cx[:, None] + ox[None], 0, mask.shape[1] - 1)
    py = np.clip(cy[:, None] + oy[None], 0, mask.shape[0] - 1)
    return mask[py, px].any(axis=1)
