"""Output writers: per-image JSON and overlays (atomic), and resumable JSON Lines / CSV result logs.

Per-image files are written to a temp file and renamed, so a reader (or a resumed run) sees the old
file or the whole new one, never half (safe against a killed process, not against power loss).

The logs hold many images in one file, appended one image at a time and flushed, in input order:
- JSON Lines: one object per image, {"image": name, "path": source, ...Detection.to_dict()}.
- CSV: header `image,x,y,score`, one row per corner; an image without corners has one row with
  empty x, y and score, so that it is still recorded. Values are rounded as in Detection.to_dict.
Names are str and may hold any character a file name can (undecodable bytes round-trip through
JSON escapes and UTF-8 with surrogateescape). On resume, `ResultLog.recover()` drops what a crash
may have left half-written: a last line without its newline, and for CSV the last image's rows
(a CSV row cannot say whether all rows of its image were written, so that image is done again).
"""

from __future__ import annotations

import csv
import io
import json
import os
import tempfile
from abc import ABC, abstractmethod
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from .result import Detection

TEMP_SUFFIX = ".ccdn-tmp"
CSV_HEADER = ["image", "x", "y", "score"]
JSONL_START = b'{"image": '  # how every JSON Lines record begins (result_record puts the name first)


def write_atomic(path: Path, data: bytes) -> None:
    """Write `data` to `path` so that readers see the old file or the whole new one, never half."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=TEMP_SUFFIX)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def remove_stale_temps(folder: Path) -> int:
    """Delete temp files a killed run left in `folder` (recursively); returns how many."""
    removed = 0
    for root, _, files in os.walk(folder):
        for name in files:
            if name.startswith(".") and name.endswith(TEMP_SUFFIX):
                Path(root, name).unlink(missing_ok=True)
                removed += 1
    return removed


def result_record(name: str, source: str, detection: Detection) -> dict:
    """The JSON object written for one image: its output name, its path as given, the detection."""
    return {"image": name, "path": source, **detection.to_dict()}


def write_json(path: Path, record: dict) -> None:
    write_atomic(path, (json.dumps(record, indent=1) + "\n").encode())


def draw_overlay(gray: np.ndarray, detection: Detection) -> np.ndarray:
    """BGR copy of the image with each corner marked (green circle, red cross, size scaled to the image).

    Pixel convention: (0, 0) is the centre of the top-left pixel.
    """
    out = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    r = max(3, round(max(gray.shape) / 200))
    shift = 4  # sub-pixel drawing: coordinates in 1/16 px
    for x, y in detection.xy:
        c = (int(round(x * 16)), int(round(y * 16)))
        cv2.circle(out, c, r * 16, (0, 255, 0), 1, cv2.LINE_AA, shift)
        cv2.drawMarker(out, (int(round(x)), int(round(y))), (0, 0, 255), cv2.MARKER_CROSS, r, 1)
    return out


def write_overlay(path: Path, gray: np.ndarray, detection: Detection) -> None:
    ok, buf = cv2.imencode(path.suffix or ".jpg", draw_overlay(gray, detection))
    if not ok:
        raise OSError(f"{path}: OpenCV cannot encode this format")
    write_atomic(path, buf.tobytes())


class ResultLog(ABC):
    """A results file that grows by whole records, one image at a time, and survives being killed.

    Subclasses say how a record is encoded and how a file is split back into records.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self._file: io.BufferedWriter | None = None

    @abstractmethod
    def encode(self, record: dict) -> bytes:
        """One image's result_record as the bytes appended to the file."""

    @abstractmethod
    def parse(self, data: bytes) -> tuple[bytes, list[tuple[str, bytes]]]:
        """(preamble, [(image name, its bytes), ...]) for the whole, trustworthy records in `data`."""

    def recover(self, redo: set[str] = frozenset()) -> set[str]:
        """Repair the file after a crash, drop the records of images in `redo`; returns finished names.

        Raises ValueError when the file exists but is not a results file of this kind.
        """
        data = self.path.read_bytes() if self.path.exists() else b""
        preamble, records = self.parse(data)
        kept = [(name, block) for name, block in records if name not in redo]
        clean = preamble + b"".join(block for _, block in kept)
        if clean != data:
            if data.startswith(clean):
                os.truncate(self.path, len(clean))
            else:
                write_atomic(self.path, clean)
        return {name for name, _ in kept}

    def append(self, record: dict) -> None:
        """Add one image's record and flush it to the operating system."""
        if self._file is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = open(self.path, "ab")
            if self._file.tell() == 0:
                self._file.write(self.header())
        self._file.write(self.encode(record))
        self._file.flush()

    def header(self) -> bytes:
        return b""

    def _foreign(self) -> ValueError:
        return ValueError(f"{self.path}: exists and is not a ccdn results file; remove it or choose another --out")

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


class JsonlLog(ResultLog):
    """JSON Lines: one result_record per line."""

    def encode(self, record: dict) -> bytes:
        return (json.dumps(record) + "\n").encode()

    def parse(self, data: bytes) -> tuple[bytes, list[tuple[str, bytes]]]:
        records = []
        for i, line in enumerate(_lines(data)):
            if not line.endswith(b"\n"):  # a torn last line: ours only if it begins like a record
                if i == 0 and not JSONL_START.startswith(line[: len(JSONL_START)]):
                    raise self._foreign()
                break
            name = _jsonl_name(line)
            if name is None and i == 0:
                raise self._foreign()
            if name is not None:
                records.append((name, line))
        return b"", records


def _lines(data: bytes) -> list[bytes]:
    """`data` split after each newline (only \\n: a CSV field may hold a quoted \\r)."""
    lines = [line + b"\n" for line in data.split(b"\n")]
    lines[-1] = lines[-1][:-1]
    return lines if lines[-1] else lines[:-1]


def _jsonl_name(line: bytes) -> str | None:
    try:
        obj = json.loads(line)
    except ValueError:
        return None
    return obj["image"] if isinstance(obj, dict) and isinstance(obj.get("image"), str) else None


class CsvLog(ResultLog):
    """CSV: `image,x,y,score`, one row per corner (one row with empty values for no corners)."""

    def header(self) -> bytes:
        return _csv_bytes([CSV_HEADER])

    def encode(self, record: dict) -> bytes:
        rows = [[record["image"], x, y, s] for (x, y), s in zip(record["corners"], record["score"])]
        return _csv_bytes(rows or [[record["image"], "", "", ""]])

    def parse(self, data: bytes) -> tuple[bytes, list[tuple[str, bytes]]]:
        rows = list(_csv_rows(data))
        if not rows:  # nothing whole: empty, or a header cut short
            if not self.header().startswith(data[: len(self.header())]):
                raise self._foreign()
            return b"", []
        if rows[0][0] != CSV_HEADER:
            raise self._foreign()
        groups: list[tuple[str, int, int]] = []  # (name, start, end) of each image's run of rows
        for row, start, end in rows[1:]:
            if len(row) != len(CSV_HEADER):
                continue  # not a row of ours
            if groups and groups[-1][0] == row[0]:
                groups[-1] = (row[0], groups[-1][1], end)
            else:
                groups.append((row[0], start, end))
        header_end = rows[0][2]
        return data[:header_end], [(name, data[start:end]) for name, start, end in groups[:-1]]


def _csv_bytes(rows: list[list]) -> bytes:
    text = io.StringIO()
    plain = csv.writer(text, lineterminator="\n")
    quoted = csv.writer(text, lineterminator="\n", quoting=csv.QUOTE_NONNUMERIC)
    for row in rows:  # a name with a bare \r must be quoted, or readers would end the row there
        (quoted if "\r" in row[0] else plain).writerow(row)
    return text.getvalue().encode("utf-8", "surrogateescape")


def _csv_rows(data: bytes) -> Iterator[tuple[list[str], int, int]]:
    """(row, start byte, end byte) for each whole row: rows may span lines (quoted newlines)."""
    lines = _lines(data)
    if lines and not lines[-1].endswith(b"\n"):
        lines.pop()  # a torn last line
    consumed = 0

    def feed() -> Iterator[str]:
        nonlocal consumed
        for line in lines:
            consumed += len(line)
            yield line.decode("utf-8", "surrogateescape")

    reader = csv.reader(feed(), strict=True)
    start = 0
    while True:
        try:
            row = next(reader)
        except (StopIteration, csv.Error):  # csv.Error: a quoted field left open by a crash
            return
        yield row, start, consumed
        start = consumed
