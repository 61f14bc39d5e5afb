"""Output writers: atomic files, overlays, and the JSON Lines / CSV logs with their crash recovery."""

from __future__ import annotations

import csv
import io
import json
import os

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ccdn.result import Detection
from ccdn.writers import (CSV_HEADER, CsvLog, JsonlLog, draw_overlay, remove_stale_temps, result_record,
                          write_atomic, write_json, write_overlay)

# Names as file systems give them: any text, including commas, quotes, newlines and (from undecodable
# bytes, via os.fsdecode) lone surrogates.
NAMES = st.one_of(st.text(min_size=1, max_size=12),
                  st.binary(min_size=1, max_size=12).map(os.fsdecode)).filter(lambda s: "\x00" not in s)


def detection(n: int, seed: int = 0) -> Detection:
    rng = np.random.default_rng(seed)
    return Detection(rng.uniform(0, 500, (n, 2)), np.sort(rng.uniform(0, 1, n))[::-1], (640, 480), "test 1.0")


RECORDS = st.lists(st.tuples(NAMES, st.integers(0, 5), st.integers(0, 1000)), min_size=1, max_size=6,
                   unique_by=lambda r: r[0]).map(
    lambda rows: [result_record(name, f"in/{name}", detection(n, seed)) for name, n, seed in rows])


@settings(max_examples=60, deadline=None)
@given(records=RECORDS)
def test_jsonl_log_round_trips_every_record(tmp_path_factory, records):
    path = tmp_path_factory.mktemp("jsonl") / "detections.jsonl"
    log = JsonlLog(path)
    for record in records:
        log.append(record)
    log.close()
    assert [json.loads(line) for line in path.read_bytes().split(b"\n")[:-1]] == records
    assert JsonlLog(path).recover() == {r["image"] for r in records}


@settings(max_examples=60, deadline=None)
@given(records=RECORDS)
def test_csv_log_round_trips_every_corner(tmp_path_factory, records):
    path = tmp_path_factory.mktemp("csv") / "corners.csv"
    log = CsvLog(path)
    for record in records:
        log.append(record)
    log.close()
    text = path.read_bytes().decode("utf-8", "surrogateescape")
    rows = list(csv.reader(io.StringIO(text, newline="")))
    expected = [CSV_HEADER]
    for r in records:
        expected += [[r["image"], str(x), str(y), str(s)] for (x, y), s in zip(r["corners"], r["score"])] or [[r["image"], "", "", ""]]
    assert rows == expected
    # the last image is always redone on resume: its rows cannot prove they are all there
    assert CsvLog(path).recover() == {r["image"] for r in records[:-1]}


def test_csv_values_are_those_of_the_json_record(tmp_path):
    record = result_record("a.png", "in/a.png", detection(4))
    CsvLog(tmp_path / "c.csv").append(record)
    rows = list(csv.reader(io.StringIO((tmp_path / "c.csv").read_text())))[1:]
    assert [[float(x), float(y)] for _, x, y, _ in rows] == record["corners"]
    assert [float(s) for *_, s in rows] == record["score"]


def test_torn_jsonl_line_is_dropped_on_recovery_and_appending_goes_on(tmp_path):
    path = tmp_path / "d.jsonl"
    log = JsonlLog(path)
    for i in range(3):
        log.append(result_record(f"{i}.png", f"{i}.png", detection(i)))
    log.close()
    whole = path.read_bytes()
    torn = JsonlLog(path).encode(result_record("3.png", "3.png", detection(3)))
    path.write_bytes(whole + torn[: len(torn) // 2])
    assert JsonlLog(path).recover() == {"0.png", "1.png", "2.png"}
    assert path.read_bytes() == whole
    log = JsonlLog(path)
    log.append(result_record("3.png", "3.png", detection(3)))
    log.close()
    assert [json.loads(line)["image"] for line in path.read_text().splitlines()] == ["0.png", "1.png", "2.png", "3.png"]


def test_csv_recovery_drops_a_torn_row_and_the_last_image(tmp_path):
    path = tmp_path / "c.csv"
    log = CsvLog(path)
    records = [result_record(f"{i}.png", f"{i}.png", detection(3, i)) for i in range(3)]
    for record in records[:2]:
        log.append(record)
    log.close()
    first = CsvLog(path).header() + CsvLog(path).encode(records[0])
    path.write_bytes(path.read_bytes() + CsvLog(path).encode(records[2])[:25])
    assert CsvLog(path).recover() == {"0.png"}
    assert path.read_bytes() == first


def test_csv_recovery_copes_with_a_quoted_newline_cut_short(tmp_path):
    path = tmp_path / "c.csv"
    log = CsvLog(path)
    log.append(result_record("a.png", "a.png", detection(2)))
    log.append(result_record("b.png", "b.png", detection(2)))
    log.close()
    whole = path.read_bytes()
    path.write_bytes(whole + b'"line\nbreak.png",1.0,2.0,0.5\n"line\n')  # a crash inside a quoted name
    assert CsvLog(path).recover() == {"a.png", "b.png"}  # the multi-line name was the last image: redone
    assert path.read_bytes() == whole


def test_recover_with_redo_removes_those_images_only(tmp_path):
    path = tmp_path / "d.jsonl"
    log = JsonlLog(path)
    for i in range(4):
        log.append(result_record(f"{i}.png", f"{i}.png", detection(i)))
    log.close()
    assert JsonlLog(path).recover(redo={"1.png", "3.png"}) == {"0.png", "2.png"}
    assert [json.loads(line)["image"] for line in path.read_text().splitlines()] == ["0.png", "2.png"]


def test_a_results_file_that_is_not_ccdns_is_refused(tmp_path):
    (tmp_path / "d.jsonl").write_text('[1, 2, 3]\n{"image": "a.png"}\n')
    (tmp_path / "c.csv").write_text("name,value\na,1\n")
    (tmp_path / "notes.jsonl").write_text("no newline at the end")
    (tmp_path / "short.csv").write_text("a,b")
    for log in (JsonlLog(tmp_path / "d.jsonl"), CsvLog(tmp_path / "c.csv"), JsonlLog(tmp_path / "notes.jsonl"),
                CsvLog(tmp_path / "short.csv")):
        before = log.path.read_bytes()
        with pytest.raises(ValueError, match="not a ccdn results file"):
            log.recover()
        assert log.path.read_bytes() == before  # left as it was


def test_image_without_corners_still_gets_a_csv_row(tmp_path):
    log = CsvLog(tmp_path / "c.csv")
    log.append(result_record("empty.png", "empty.png", detection(0)))
    log.append(result_record("next.png", "next.png", detection(1)))
    log.close()
    assert (tmp_path / "c.csv").read_text().splitlines()[1] == "empty.png,,,"
    assert CsvLog(tmp_path / "c.csv").recover() == {"empty.png"}


def test_write_atomic_keeps_the_old_file_when_writing_fails(tmp_path):
    path = tmp_path / "r.json"
    write_atomic(path, b"old")
    with pytest.raises(TypeError):
        write_atomic(path, object())  # fails after the temp file is created
    assert path.read_bytes() == b"old"
    assert os.listdir(tmp_path) == ["r.json"]


def test_remove_stale_temps_removes_only_ccdn_temp_files(tmp_path):
    (tmp_path / "sub").mkdir()
    for name in [".a.png.json.x1.ccdn-tmp", "sub/.b.json.x2.ccdn-tmp", "keep.ccdn-tmp", ".keep.tmp", "a.png.json"]:
        (tmp_path / name).write_bytes(b"x")
    assert remove_stale_temps(tmp_path) == 2
    assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*") if p.is_file()) == [
        ".keep.tmp", "a.png.json", "keep.ccdn-tmp"]


def test_json_file_holds_the_record(tmp_path):
    record = result_record("sub/a.png", "in/sub/a.png", detection(3))
    write_json(tmp_path / "sub" / "a.png.json", record)
    assert json.loads((tmp_path / "sub" / "a.png.json").read_text()) == record
    assert record["corners"] == [[round(float(x), 3), round(float(y), 3)] for x, y in detection(3).xy]


def test_overlay_marks_each_corner_and_nothing_far_from_it(tmp_path):
    gray = np.full((60, 80), 128, np.uint8)
    found = Detection(np.array([[20.0, 30.0]]), np.array([0.9]), (80, 60))
    overlay = draw_overlay(gray, found)
    assert overlay.shape == (60, 80, 3)
    assert tuple(overlay[30, 20]) != (128, 128, 128)  # the cross is drawn on the corner's own pixel
    assert (overlay[:, 40:] == 128).all()
    write_overlay(tmp_path / "o.jpg", gray, found)
    assert cv2.imread(str(tmp_path / "o.jpg")).shape == (60, 80, 3)
