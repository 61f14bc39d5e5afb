"""Small test images made on the spot: a rendered checkerboard, and PNGs in modes OpenCV cannot write."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np


def checkerboard(width: int = 160, height: int = 120, seed: int = 0, squares: tuple[int, int] = (6, 5)) -> np.ndarray:
    """HxW uint8: a checkerboard under a random mild perspective, blurred, with a little noise."""
    rng = np.random.default_rng(seed)
    cell = 32
    cols, rows = squares
    board = (np.indices((rows * cell, cols * cell)) // cell).sum(0) % 2 * 180 + 40
    board = np.pad(board.astype(np.uint8), cell, constant_values=220)
    bh, bw = board.shape
    src = np.float32([[0, 0], [bw, 0], [bw, bh], [0, bh]])
    margin = np.float32([width, height]) * 0.08
    dst = np.float32([[0, 0], [width, 0], [width, height], [0, height]])
    dst += (np.float32([[1, 1], [-1, 1], [-1, -1], [1, -1]]) * margin) + rng.uniform(-1, 1, (4, 2)).astype(np.float32) * margin * 0.6
    image = cv2.warpPerspective(board, cv2.getPerspectiveTransform(src, dst), (width, height), borderValue=128)
    image = cv2.GaussianBlur(image, (0, 0), 0.8).astype(np.float32) + rng.normal(0, 3, image.shape)
    return np.clip(image, 0, 255).astype(np.uint8)


def png_bytes(pixels: np.ndarray, color_type: int, bit_depth: int = 8, palette: np.ndarray | None = None) -> bytes:
    """A minimal PNG: color_type 0 gray, 2 RGB, 3 palette (needs `palette`, (K, 3) uint8), 4 gray+alpha, 6 RGBA."""
    h, w = pixels.shape[:2]

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    dtype = ">u2" if bit_depth == 16 else np.uint8
    raw = b"".join(b"\x00" + pixels[y].astype(dtype).tobytes() for y in range(h))
    out = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, bit_depth, color_type, 0, 0, 0))
    if palette is not None:
        out += chunk(b"PLTE", np.asarray(palette, np.uint8).tobytes())
    return out + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")


def encode(image: np.ndarray, suffix: str = ".png") -> bytes:
    ok, buf = cv2.imencode(suffix, image)
    assert ok, suffix
    return buf.tobytes()
