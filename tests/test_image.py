"""Image input: header probing, file decoding and array validation, through the module and the Detector."""

from __future__ import annotations

import io
import os
import struct
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from ccdn import image as image_module
from ccdn.image import ImageError, probe_header, read_gray, to_gray
from conftest import nearest_distances
from imagefiles import checkerboard, encode, png_bytes

ENCODINGS = [(".png", []), (".jpg", []), (".jpg", [cv2.IMWRITE_JPEG_PROGRESSIVE, 1]), (".bmp", []), (".tif", []),
             (".webp", []), (".webp", [cv2.IMWRITE_WEBP_QUALITY, 101]), (".pgm", []), (".gif", [])]


def _write(path, data: bytes):
    path.write_bytes(data)
    return path


@settings(max_examples=40, deadline=None)
@given(w=st.integers(1, 80), h=st.integers(1, 80), encoding=st.sampled_from(ENCODINGS), colour=st.booleans())
def test_header_probe_gives_the_size_the_decoder_gives(w, h, encoding, colour):
    suffix, params = encoding
    image = np.random.default_rng(w * 100 + h).integers(0, 256, (h, w, 3) if colour else (h, w), dtype=np.uint8)
    if suffix == ".pgm" and colour:  # OpenCV writes PGM from gray only, GIF from colour only
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if suffix == ".gif" and not colour:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    ok, buf = cv2.imencode(suffix, image, params)
    assert ok
    header = probe_header(io.BytesIO(buf.tobytes()))
    decoded = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    assert header.size == (decoded.shape[1], decoded.shape[0]) == (w, h)


def test_jpeg_size_is_found_behind_large_metadata_segments():
    jpeg = encode(checkerboard(40, 30), ".jpg")
    app1 = b"\xff\xe1" + struct.pack(">H", 65535) + bytes(65533)  # two maximal APP1 segments: 128 KiB
    data = jpeg[:2] + app1 + app1 + jpeg[2:]
    assert cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE).shape == (30, 40)
    assert probe_header(io.BytesIO(data)).size == (40, 30)


def test_huge_header_is_refused_without_decoding(tmp_path, monkeypatch):
    png = bytearray(png_bytes(np.zeros((4, 4), np.uint8), 0))
    png[16:24] = struct.pack(">II", 50_000, 40_000)  # claims 2 gigapixels; the CRC no longer matters
    jpeg = encode(checkerboard(40, 30), ".jpg")
    sof = jpeg.index(b"\xff\xc0")
    jpeg = jpeg[: sof + 5] + struct.pack(">HH", 30_000, 60_000) + jpeg[sof + 9 :]
    monkeypatch.setattr(image_module.cv2, "imdecode", lambda *a: pytest.fail("decoded an image refused by its header"))
    for name, data in [("huge.png", bytes(png)), ("huge.jpg", jpeg)]:
        with pytest.raises(ImageError, match="over the limit of 100000000"):
            read_gray(_write(tmp_path / name, data))


def test_max_pixels_limits_files_and_arrays(tmp_path):
    path = _write(tmp_path / "board.png", encode(checkerboard(40, 30)))
    assert read_gray(path, max_pixels=1200).shape == (30, 40)
    with pytest.raises(ImageError, match=r"40x30 = 1200 pixels, over the limit of 1199"):
        read_gray(path, max_pixels=1199)
    with pytest.raises(ImageError, match="over the limit"):
        to_gray(np.zeros((30, 40), np.uint8), max_pixels=1199)


def _bad_files(tmp_path):
    good_png, good_jpg = encode(checkerboard(64, 48)), encode(checkerboard(64, 48), ".jpg")
    damaged = bytearray(good_png)
    damaged[1:4] = b"XYZ"
    fifo = tmp_path / "fifo.png"
    os.mkfifo(fifo)
    (tmp_path / "folder.png").mkdir()
    return {
        "empty.png": (b"", "empty file"),
        "half.png": (good_png[: len(good_png) // 2], "cannot decode this PNG file"),
        "head-only.png": (good_png[:30], "cannot decode this PNG file"),
        "half.jpg": (good_jpg[: len(good_jpg) // 2], "cannot decode this JPEG file"),
        "no-end.jpg": (good_jpg[:-2], "cannot decode this JPEG file"),
        "magic.png": (bytes(damaged), "not an image"),
        "text.jpg": (b"this is a text file, not a JPEG\n", "not an image"),
        "noise.bmp": (bytes(np.random.default_rng(0).integers(0, 256, 500, dtype=np.uint8)), "not an image"),
        "fifo.png": (None, "not a regular file"),
        "folder.png": (None, "is a directory"),
        "missing.png": (None, "no such file"),
    }


def test_bad_files_raise_image_error_with_a_one_line_reason(tmp_path):
    for name, (data, reason) in _bad_files(tmp_path).items():
        if data is not None:
            _write(tmp_path / name, data)
        with pytest.raises(ImageError) as info:
            read_gray(tmp_path / name)
        message = str(info.value)
        assert message.startswith(str(tmp_path / name) + ": ") and reason in message and "\n" not in message, name


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX permissions")
def test_unreadable_file_is_reported_as_permission_denied(tmp_path):
    path = _write(tmp_path / "locked.png", encode(checkerboard(40, 30)))
    path.chmod(0)
    if os.access(path, os.R_OK):
        pytest.skip("running as root: file permissions are not enforced")
    with pytest.raises(ImageError, match="permission denied"):
        read_gray(path)


def test_png_modes_opencv_cannot_write_are_converted_to_gray(tmp_path):
    gray = np.random.default_rng(1).integers(0, 256, (12, 16), dtype=np.uint8)
    palette = np.repeat(np.arange(0, 256, 17, dtype=np.uint8)[:, None], 3, 1)  # 16 gray levels
    cases = {
        "palette": (png_bytes(gray // 17, 3, palette=palette), (gray // 17) * 17),
        "gray-alpha": (png_bytes(np.dstack([gray, 255 - gray]), 4), gray),
        "rgba": (png_bytes(np.dstack([gray, gray, gray, 255 - gray]), 6), gray),
        "gray16": (png_bytes(gray.astype(np.uint16) * 257, 0, 16), gray),
        "rgb16": (png_bytes(np.dstack([gray] * 3).astype(np.uint16) * 257, 2, 16), gray),
    }
    for name, (data, expected) in cases.items():
        result = read_gray(_write(tmp_path / f"{name}.png", data))
        assert result.dtype == np.uint8 and result.flags.c_contiguous, name
        np.testing.assert_array_equal(result, expected, err_msg=name)


def test_a_path_detects_exactly_like_its_imread_array(tmp_path, detector):
    """A PNG path reads as its cv2.imread array (BGR, converted); a JPEG path as its luminance plane,
    cv2.imread(path, cv2.IMREAD_GRAYSCALE), which the converted colours miss by a few grey levels
    where their round trip clipped them (a red and blue board: saturated colours)."""
    board = checkerboard(160, 120, seed=5)
    colour = cv2.merge([255 - board, np.zeros_like(board), board])
    readers = {"colour.png": lambda p: cv2.imread(p), "colour.jpg": lambda p: cv2.imread(p, cv2.IMREAD_GRAYSCALE)}
    for name, array in readers.items():
        path = _write(tmp_path / name, encode(colour, Path(name).suffix))
        np.testing.assert_array_equal(read_gray(path), to_gray(array(str(path))))
        by_path, by_array = detector.detect(path), detector.detect(array(str(path)))
        assert len(by_path) > 0
        np.testing.assert_array_equal(by_path.xy, by_array.xy)
    converted = cv2.cvtColor(cv2.imread(str(tmp_path / "colour.jpg")), cv2.COLOR_BGR2GRAY).astype(int)
    assert 0 < np.abs(read_gray(tmp_path / "colour.jpg") - converted).max() <= 5


def test_a_jpegs_exif_orientation_is_applied(tmp_path):
    data = encode(checkerboard(40, 30), ".jpg")
    tiff = b"II*\x00" + struct.pack("<IH", 8, 1) + struct.pack("<HHII", 0x0112, 3, 1, 6) + struct.pack("<I", 0)  # rotate 90
    exif = b"\xff\xe1" + struct.pack(">H", 8 + len(tiff)) + b"Exif\x00\x00" + tiff
    path = _write(tmp_path / "rotated.jpg", data[:2] + exif + data[2:])
    np.testing.assert_array_equal(read_gray(path), cv2.rotate(read_gray(_write(tmp_path / "plain.jpg", data)),
                                                              cv2.ROTATE_90_CLOCKWISE))


def test_odd_file_names_are_read(tmp_path):
    data = encode(checkerboard(40, 30))
    names = ["-leading-dash.png", "with space.png", "ünïcødé 图像.png", "quote's \"name\".png", "new\nline.png"]
    for name in names:
        assert read_gray(_write(tmp_path / name, data)).shape == (30, 40), name
    raw = os.path.join(os.fsencode(tmp_path), b"latin1-\xe9.png")  # not valid UTF-8
    with open(raw, "wb") as f:
        f.write(data)
    assert read_gray(raw).shape == (30, 40)


def test_one_pixel_files_and_arrays_give_empty_detections(tmp_path, detector):
    for suffix in (".png", ".jpg", ".bmp"):
        path = _write(tmp_path / f"one{suffix}", encode(np.full((1, 1), 77, np.uint8), suffix))
        result = detector.detect(path)
        assert result.image_size == (1, 1) and len(result) == 0 and result.xy.shape == (0, 2)
    for shape in [(1, 1), (2, 3), (3, 2), (2, 2), (1, 40), (40, 1)]:
        for fill in (0, 255):
            assert len(detector.detect(np.full(shape, fill, np.uint8))) == 0, shape
        assert len(detector.detect(np.random.default_rng(0).integers(0, 256, shape, dtype=np.uint8))) == 0, shape


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(image=hnp.arrays(np.uint8, hnp.array_shapes(min_dims=2, max_dims=2, min_side=1, max_side=14)))
def test_tiny_images_never_crash_and_corners_lie_inside(image, detector):
    result = detector.detect(image)
    h, w = image.shape
    assert result.image_size == (w, h) and result.xy.dtype == np.float32 and result.score.shape == (len(result),)
    assert np.all(np.isfinite(result.xy)) and np.all((result.xy >= 0) & (result.xy <= [w - 1, h - 1]))


DTYPES = st.sampled_from([np.uint8, np.uint16, np.int8, np.int16, np.int32, np.int64, np.uint32, np.float16,
                          np.float32, np.float64, np.bool_, np.complex64, ">u2", ">f4", "<f8"])


@st.composite
def any_array(draw):
    """Arrays of any small shape and dtype, as C-contiguous arrays or strided / reversed / transposed views."""
    dtype = np.dtype(draw(DTYPES))
    shape = draw(hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=6))
    elements = None
    if dtype.kind == "f":
        width = dtype.itemsize * 8  # [0, 1] data with overshoots, 0-255 data (refused), NaN and infinities
        elements = (st.floats(-2, 2, width=width) | st.floats(-2, 300, width=width)
                    | st.sampled_from([np.nan, np.inf, -np.inf]))
    array = draw(hnp.arrays(dtype, shape, elements=elements))
    view = draw(st.sampled_from(["as is", "step", "reverse", "transpose"]))
    if array.ndim >= 2 and view == "step":
        array = array[::2, ::-1]
    elif array.ndim >= 2 and view == "reverse":
        array = array[::-1]
    elif array.ndim >= 2 and view == "transpose":
        array = np.swapaxes(array, 0, 1)
    return array


@settings(max_examples=300, deadline=None)
@given(array=any_array())
@example(array=np.array([[[0.0, np.nan]]], np.float16))  # NaN in a gray + alpha image's alpha: refused, as in BGRA
def test_any_array_becomes_contiguous_gray_uint8_or_image_error(array):
    usable_shape = array.ndim == 2 or (array.ndim == 3 and 1 <= array.shape[2] <= 4)
    usable_dtype = array.dtype.kind in "bf" or array.dtype.newbyteorder("=") in (np.uint8, np.uint16)
    usable = usable_shape and array.size > 0 and usable_dtype and (
        array.dtype.kind != "f" or (np.isfinite(array).all() and array.max() <= image_module.FLOAT_MAX))
    try:
        gray = to_gray(array)
    except ImageError as exc:
        assert "\n" not in str(exc) and str(exc).startswith("array: ")
        assert not usable, f"refused a usable array: {exc}"
        return
    assert usable
    assert gray.ndim == 2 and gray.dtype == np.uint8 and gray.flags.c_contiguous
    assert gray.shape == array.shape[:2]
    np.testing.assert_array_equal(gray, to_gray(np.ascontiguousarray(array)))


@settings(max_examples=60, deadline=None)
@given(image=hnp.arrays(np.uint8, st.tuples(st.integers(1, 20), st.integers(1, 20), st.sampled_from([1, 2, 3, 4]))))
def test_colour_and_alpha_arrays_match_opencv_gray(image):
    channels = image.shape[2]
    if channels <= 2:  # gray, gray + alpha
        expected = image[:, :, 0]
    else:
        expected = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY if channels == 3 else cv2.COLOR_BGRA2GRAY)
    np.testing.assert_array_equal(to_gray(image), expected)


def test_scaled_dtypes_map_onto_the_uint8_range():
    values = np.array([[0, 1, 128, 255]], np.uint8)
    np.testing.assert_array_equal(to_gray(values.astype(np.uint16) * 257), values)
    np.testing.assert_array_equal(to_gray((values.astype(np.uint16) * 257).astype(">u2")), values)
    np.testing.assert_array_equal(to_gray(values / 255.0), values)
    np.testing.assert_array_equal(to_gray(np.array([[-3.0, 1.5]])), [[0, 255]])  # floats are clipped to [0, 1]
    np.testing.assert_array_equal(to_gray(np.array([[False, True]])), [[0, 255]])


def test_uint16_frames_of_a_10_or_12_bit_camera_detect_like_their_8_bit_source(tmp_path, detector, examples):
    # Mono10 / Mono12 data in 16-bit containers: read as 1/257 of full scale they kept 4-16 grey levels
    # and lost the board (the fisheye example: 0 corners at 10 bit, 18 of 81 at 12 bit)
    gray = cv2.imread(str(examples["fisheye"]["path"]), cv2.IMREAD_GRAYSCALE)
    expected = detector.detect(gray)
    assert len(expected) == 81
    for bits in (10, 12):
        frame = gray.astype(np.uint16) << (bits - 8)
        assert cv2.imwrite(str(tmp_path / f"mono{bits}.png"), frame)
        for source in (frame, tmp_path / f"mono{bits}.png"):
            result = detector.detect(source)
            assert len(result) == len(expected), (bits, source)
            assert nearest_distances(result.xy, expected.xy.astype(np.float64)).max() < 0.05


def test_the_alpha_channel_does_not_set_a_16_bit_frames_bit_depth():
    gray = np.array([[0, 1023, 512]], np.uint16)  # 10-bit data
    opaque = np.full_like(gray, 65535)
    expected = to_gray(gray)
    np.testing.assert_array_equal(expected, [[0, 255, 128]])
    np.testing.assert_array_equal(to_gray(np.dstack([gray, opaque])), expected)
    np.testing.assert_array_equal(to_gray(np.dstack([gray, gray, gray, opaque])), expected)


def test_float_frames_in_the_0_255_range_are_refused_not_blanked(detector, examples):
    gray = cv2.imread(str(examples["board"]["path"]), cv2.IMREAD_GRAYSCALE)
    assert len(detector.detect(gray.astype(np.float32) / 255)) == 54
    with pytest.raises(ImageError, match=r"array: float image values reach 2\d\d; floats must lie in \[0, 1\]"):
        detector.detect(gray.astype(np.float32))  # clipped to [0, 1] it was a blank frame: 0 corners, no error


def test_detector_refuses_bad_arrays_with_a_message(detector):
    cases = [
        (np.zeros((8, 8), np.int32), "unsupported dtype int32"),
        (np.zeros((8, 8), np.complex64), "unsupported dtype complex64"),
        (np.full((8, 8), np.nan, np.float32), "NaN or infinity"),
        (np.array([[0.5, np.inf]]), "NaN or infinity"),
        (np.zeros((8, 8, 5), np.uint8), "got shape (8, 8, 5)"),
        (np.zeros((2, 8, 8, 3), np.uint8), "got shape (2, 8, 8, 3)"),
        (np.zeros(8, np.uint8), "got shape (8,)"),
        (np.zeros((0, 8), np.uint8), "empty image"),
        ([[0, 1], [1, 0]], "expected a path or a numpy array"),
        (None, "expected a path or a numpy array"),
    ]
    for value, message in cases:
        with pytest.raises(ImageError, match=message.replace("(", r"\(").replace(")", r"\)")):
            detector.detect(value)


def test_non_contiguous_views_give_the_same_detection_as_copies(detector):
    board = checkerboard(120, 90, seed=3)
    bgr = np.ascontiguousarray(cv2.cvtColor(board, cv2.COLOR_GRAY2BGR)[:, :, ::-1])[:, :, ::-1]  # reversed channel stride
    padded = np.zeros((90, 240), np.uint8)
    padded[:, ::2] = board
    for view in (bgr, padded[:, ::2], np.ascontiguousarray(board.T).T):
        assert not view.flags.c_contiguous
        expected = detector.detect(np.ascontiguousarray(view))
        result = detector.detect(view)
        np.testing.assert_array_equal(result.xy, expected.xy)
        np.testing.assert_array_equal(result.score, expected.score)


def test_float_and_uint16_inputs_detect_like_uint8(detector):
    board = checkerboard(120, 90, seed=4)
    expected = detector.detect(board)
    assert len(expected) > 0
    for variant in (board / 255.0, board.astype(np.float32) / 255, board.astype(np.uint16) * 257):
        result = detector.detect(variant)
        np.testing.assert_array_equal(result.xy, expected.xy)
