"""Image input: paths or arrays in, a validated, C-contiguous HxW uint8 gray frame out.

Arrays: HxW gray, HxWx1, HxWx2 (gray + alpha), HxWx3 (BGR, OpenCV order) or HxWx4 (BGRA); any
memory layout (non-contiguous views and either byte order are copied as needed). dtypes: uint8 as
is; uint16 read as b-bit data, b the bits its largest colour value needs (at least 8), and scaled by
255 / (2^b - 1): a 10-, 12- or 14-bit camera's frames in 16-bit containers (Mono10/12/14 saved as
16-bit PNG or TIFF) get the whole grey range, full-range 16-bit data 1/257 (scaled by 1/257 alone,
a 12-bit frame kept 16 grey levels and lost its board); float in [0, 1] scaled by 255 and clipped
(NaN, infinity and values above FLOAT_MAX refused: 0-255 data passed as floats would be a blank
frame, silently); bool as 0/255. Other dtypes (signed or wider integers, complex, object) are refused.

Files are decoded by OpenCV (EXIF orientation applied) and then converted as arrays are, so an
8-bit file gives exactly the result of its `cv2.imread` array; but a JPEG is decoded to its luminance
(Y) plane directly, as `cv2.imread(path, cv2.IMREAD_GRAYSCALE)` does: 2-3x faster than decoding
its colours and converting them (a 12 Mpx photo: 59 -> 24 ms), and the same grey levels but where
the colours' round trip clipped them (on colourful real-dev photos up to 11 levels on up to 5 % of
the pixels). Converted, not refused: colour,
palette, gray + alpha and RGBA images (alpha is dropped, not composited), 16-bit (scaled as
above) and float images (clipped to [0, 1]). Before the pixels are decoded, the size is read from the
header (PNG, JPEG, BMP, GIF, WebP, TIFF, PNM), so an image over `max_pixels` is refused without
allocating it; other formats are checked after decoding. A JPEG without its end marker is refused
as truncated (older OpenCV would fill the missing part with gray). Any size down to 1x1 is valid.

Every refusal is an ImageError whose message is one line: the source, a colon, the reason.
"""

from __future__ import annotations

import os
import stat
import struct
from dataclasses import dataclass
from typing import BinaryIO

import cv2
import numpy as np

DEFAULT_MAX_PIXELS = 100_000_000
FLOAT_MAX = 2.0  # float images above this are refused: [0, 1] data that overshoots a little is clipped
HEADER_BYTES = 64 * 1024  # enough for every probed header except JPEGs with big APP segments (seeked)
JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


class ImageError(ValueError):
    """The input is not an image ccdn can use; the message says why, in one line."""


@dataclass(frozen=True)
class Header:
    """What a file's first bytes say: its format (None: not recognised) and (width, height) if readable."""

    format: str | None
    size: tuple[int, int] | None


def read_gray(path: str | os.PathLike, max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """Decode an image file to HxW uint8 gray, or raise ImageError with the reason.

    Refuses, without decoding: missing, unreadable, empty and non-regular files (a FIFO would
    block), and images whose header says they have more than `max_pixels` pixels.
    """
    if not isinstance(path, (str, bytes, os.PathLike)):
        raise ImageError(f"{type(path).__name__}: expected a path or a numpy array")
    source = os.fsdecode(path)
    try:
        info = os.stat(path)
        if stat.S_ISDIR(info.st_mode):
            raise ImageError(f"{source}: is a directory, not an image")
        if not stat.S_ISREG(info.st_mode):
            raise ImageError(f"{source}: not a regular file")
        if info.st_size == 0:
            raise ImageError(f"{source}: empty file (0 bytes)")
        with open(path, "rb") as f:
            header = probe_header(f)
            _check_pixels(header.size, max_pixels, source)
            f.seek(0)
            data = f.read()
    except FileNotFoundError as exc:
        raise ImageError(f"{source}: no such file") from exc
    except PermissionError as exc:
        raise ImageError(f"{source}: permission denied") from exc
    except OSError as exc:
        raise ImageError(f"{source}: cannot read ({exc.strerror or exc})") from exc
    if header.size is not None and 0 in header.size:
        raise ImageError(f"{source}: {header.format} header gives a size of {header.size[0]}x{header.size[1]}")
    if header.format == "JPEG" and not _jpeg_has_end(data):
        raise ImageError(f"{source}: cannot decode this JPEG file (corrupt or truncated: no end marker)")
    try:
        # a JPEG's own luminance: libjpeg skips the colour planes (a 12 Mpx photo 59 -> 24 ms)
        flags = cv2.IMREAD_GRAYSCALE if header.format == "JPEG" else cv2.IMREAD_ANYCOLOR | cv2.IMREAD_ANYDEPTH
        image = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    except cv2.error as exc:  # some decoders raise instead of returning None
        raise ImageError(f"{source}: cannot decode ({_error_line(str(exc))})") from exc
    if image is None:
        if header.format is None:
            raise ImageError(f"{source}: not an image (unrecognised file format)")
        raise ImageError(f"{source}: cannot decode this {header.format} file (corrupt or truncated)")
    return to_gray(image, max_pixels, source)


def to_gray(image: np.ndarray, max_pixels: int = DEFAULT_MAX_PIXELS, source: str = "array") -> np.ndarray:
    """Validate an array and convert it to a C-contiguous HxW uint8 gray frame (see module docstring)."""
    if not isinstance(image, np.ndarray):
        raise ImageError(f"{source}: expected a numpy array or a path, got {type(image).__name__}")
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (1, 2, 3, 4)):
        raise ImageError(f"{source}: expected HxW gray or HxWx3 BGR / HxWx4 BGRA, got shape {image.shape}")
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise ImageError(f"{source}: empty image, shape {image.shape}")
    _check_pixels((image.shape[1], image.shape[0]), max_pixels, source)
    if not image.dtype.isnative:
        image = image.astype(image.dtype.newbyteorder("="))
    image = _to_uint8(image, source)  # every channel, alpha too: NaN anywhere means a corrupt buffer
    if image.ndim == 3 and image.shape[2] in (1, 2):
        image = image[:, :, 0]  # gray, or gray + alpha: drop the alpha
    elif image.ndim == 3:
        code = cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        image = cv2.cvtColor(np.ascontiguousarray(image), code)
    return np.ascontiguousarray(image)


def _to_uint8(image: np.ndarray, source: str) -> np.ndarray:
    if image.dtype == np.uint8:
        return image
    if image.dtype == np.uint16:
        colour = image[..., :-1] if image.ndim == 3 and image.shape[2] in (2, 4) else image  # alpha: any range
        bits = max(8, int(colour.max()).bit_length())  # the sensor's bit depth, as far as the pixels tell
        return cv2.convertScaleAbs(np.ascontiguousarray(image), alpha=255 / ((1 << bits) - 1))  # rounds; no wide copy
    if np.issubdtype(image.dtype, np.floating):
        if not np.isfinite(image).all():
            raise ImageError(f"{source}: float image contains NaN or infinity")
        top = float(image.max())
        if top > FLOAT_MAX:  # 0-255 (or 0-65535) data as floats: clipped to [0, 1], it would be a blank frame
            raise ImageError(f"{source}: float image values reach {top:g}; floats must lie in [0, 1] "
                             "(divide by 255, or pass uint8)")
        return (np.clip(image, 0.0, 1.0).astype(np.float32) * 255 + 0.5).astype(np.uint8)
    if image.dtype == np.bool_:
        return image.astype(np.uint8) * 255
    raise ImageError(f"{source}: unsupported dtype {image.dtype} (use uint8, uint16 or float in [0, 1])")


def _check_pixels(size: tuple[int, int] | None, max_pixels: int, source: str) -> None:
    if size is not None and size[0] * size[1] > max_pixels:
        raise ImageError(f"{source}: {size[0]}x{size[1]} = {size[0] * size[1]} pixels, over the limit of {max_pixels}")


def _error_line(text: str) -> str:
    """The last non-empty line of an OpenCV error: the one that says what went wrong."""
    lines = [line.strip() for line in text.strip().splitlines() if line.strip()]
    return lines[-1] if lines else "unknown error"


def probe_header(f: BinaryIO) -> Header:
    """Format and (width, height) from the first bytes of an open file, without decoding pixels."""
    head = f.read(HEADER_BYTES)
    fmt = _format_of(head)
    if fmt is None:
        return Header(None, None)
    try:
        return Header(fmt, _SIZE_READERS[fmt](head, f))
    except (struct.error, ValueError):  # a header cut short or garbled: the format is known, the size is not
        return Header(fmt, None)


def _format_of(head: bytes) -> str | None:
    if head.startswith(b"\x89PNG\r\n\x1a\n"):
        return "PNG"
    if head.startswith(b"\xff\xd8\xff"):
        return "JPEG"
    if head.startswith(b"BM"):
        return "BMP"
    if head[:6] in (b"GIF87a", b"GIF89a"):
        return "GIF"
    if head[:4] == b"RIFF" and head[8:12] == b"WEBP":
        return "WebP"
    if head[:4] in (b"II*\x00", b"MM\x00*"):
        return "TIFF"
    if head[:1] == b"P" and head[1:2] in (b"1", b"2", b"3", b"4", b"5", b"6") and head[2:3].isspace():
        return "PNM"
    return None


def _png_size(head: bytes, f: BinaryIO) -> tuple[int, int] | None:
    return struct.unpack(">II", head[16:24]) if head[12:16] == b"IHDR" else None


def _jpeg_size(head: bytes, f: BinaryIO) -> tuple[int, int] | None:
    """Walk the JPEG markers up to the first start-of-frame, seeking over APP segments of any size."""
    f.seek(2)
    while True:
        byte = f.read(1)
        if byte != b"\xff":
            return None
        while byte == b"\xff":  # fill bytes before a marker
            byte = f.read(1)
        if not byte:
            return None
        marker = byte[0]
        if marker in (0x01, 0xD8) or 0xD0 <= marker <= 0xD7:  # markers without a length
            continue
        if marker in (0xD9, 0xDA):  # end of image or start of scan before any frame header
            return None
        (length,) = struct.unpack(">H", f.read(2))
        if marker in JPEG_SOF:
            _, h, w = struct.unpack(">BHH", f.read(5))
            return (w, h)
        if length < 2:
            return None
        f.seek(length - 2, os.SEEK_CUR)


def _jpeg_has_end(data: bytes) -> bool:
    """Whether an end-of-image marker follows the first scan (entropy-coded data never holds one)."""
    pos = 2
    while pos + 4 <= len(data) and data[pos] == 0xFF:
        marker = data[pos + 1]
        if marker == 0xFF:  # a fill byte
            pos += 1
        elif marker == 0x01 or 0xD0 <= marker <= 0xD8:  # markers without a length
            pos += 2
        elif marker == 0xDA:
            return data.find(b"\xff\xd9", pos) != -1
        else:
            pos += 2 + int.from_bytes(data[pos + 2 : pos + 4], "big")
    return False


def _bmp_size(head: bytes, f: BinaryIO) -> tuple[int, int] | None:
    if struct.unpack("<I", head[14:18])[0] == 12:  # OS/2 BITMAPCOREHEADER: 16-bit sizes
        return struct.unpack("<HH", head[18:22])
    w, h = struct.unpack("<ii", head[18:26])
    return (abs(w), abs(h))  # negative height: a top-down bitmap


def _gif_size(head: bytes, f: BinaryIO) -> tuple[int, int] | None:
    return struct.unpack("<HH", head[6:10])


def _webp_size(head: bytes, f: BinaryIO) -> tuple[int, int] | None:
    chunk = head[12:16]
    if chunk == b"VP8 ":
        w, h = struct.unpack("<HH", head[26:30])
        return (w & 0x3FFF, h & 0x3FFF)
    if chunk == b"VP8L":
        (bits,) = struct.unpack("<I", head[21:25])
        return (1 + (bits & 0x3FFF), 1 + ((bits >> 14) & 0x3FFF))
    if chunk == b"VP8X":
        return (1 + int.from_bytes(head[24:27], "little"), 1 + int.from_bytes(head[27:30], "little"))
    return None


def _tiff_size(head: bytes, f: BinaryIO) -> tuple[int, int] | None:
    """ImageWidth (256) and ImageLength (257) from the first IFD, if it lies within `head`."""
    order = "<" if head[:2] == b"II" else ">"
    (offset,) = struct.unpack(order + "I", head[4:8])
    (count,) = struct.unpack(order + "H", head[offset : offset + 2])
    found = {}
    for i in range(count):
        tag, kind, _, value = struct.unpack(order + "HHI4s", head[offset + 2 + 12 * i : offset + 14 + 12 * i])
        if tag in (256, 257):
            found[tag] = struct.unpack(order + ("H" if kind == 3 else "I"), value[: 2 if kind == 3 else 4])[0]
    return (found[256], found[257]) if len(found) == 2 else None


def _pnm_size(head: bytes, f: BinaryIO) -> tuple[int, int] | None:
    tokens = []
    for line in head[2:].split(b"\n"):
        tokens += line.split(b"#", 1)[0].split()
        if len(tokens) >= 2:
            return (int(tokens[0]), int(tokens[1])) if tokens[0].isdigit() and tokens[1].isdigit() else None
    return None


_SIZE_READERS = {"PNG": _png_size, "JPEG": _jpeg_size, "BMP": _bmp_size, "GIF": _gif_size, "WebP": _webp_size,
                 "TIFF": _tiff_size, "PNM": _pnm_size}
