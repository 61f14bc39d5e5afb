"""The batch engine: input collection, resume, ordered parallel work, crash isolation, bounded memory."""

from __future__ import annotations

import gc
import os
import weakref
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pytest

import ccdn
from ccdn.batch import Batch, BatchOptions, Item, WorkerDied, collect_inputs, ordered_map
from imagefiles import checkerboard, encode
from workerfns import slow_square, square_or_die

REAL_DEV = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real-dev" / "images"


def make_tree(root: Path, names: list[str]) -> None:
    data = encode(checkerboard(48, 36))
    for name in names:
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_bytes(data)


def names(items: list[Item]) -> list[str]:
    return [item.name for item in items]


def test_folders_are_searched_recursively_in_name_order_skipping_hidden_and_non_images(tmp_path):
    make_tree(tmp_path, ["b.png", "a.JPG", "sub/c.png", "sub/deeper/d.tif", ".hidden.png", ".cache/e.png",
                         "notes.txt", "sub/f.png.bak"])
    items, failures = collect_inputs([tmp_path])
    assert names(items) == ["a.JPG", "b.png", "sub/c.png", "sub/deeper/d.tif"] and not failures
    assert items[2].path == tmp_path / "sub" / "c.png"


def test_include_and_exclude_match_names_or_relative_paths_case_insensitively(tmp_path):
    make_tree(tmp_path, ["cam0/a.png", "cam0/b.jpg", "cam1/a.png", "cam1/skip-me.png", "x.raw"])
    items, _ = collect_inputs([tmp_path], include=["*.PNG"], exclude=["skip-*"])
    assert names(items) == ["cam0/a.png", "cam1/a.png"]
    items, _ = collect_inputs([tmp_path], include=["cam0/*"])
    assert names(items) == ["cam0/a.png", "cam0/b.jpg"]
    items, _ = collect_inputs([tmp_path], include=["*.raw"])  # --include replaces the suffix filter
    assert names(items) == ["x.raw"]


def test_output_folder_inside_an_input_folder_is_not_searched(tmp_path):
    make_tree(tmp_path, ["a.png", "out/a.png.overlay.png"])
    items, _ = collect_inputs([tmp_path], skip=tmp_path / "out")
    assert names(items) == ["a.png"]


def test_several_inputs_keep_their_folder_name_and_clashing_names_fail(tmp_path):
    make_tree(tmp_path, ["left/a.png", "right/a.png", "single.png", "other/single.png"])
    items, failures = collect_inputs([tmp_path / "left", tmp_path / "right", tmp_path / "single.png",
                                      tmp_path / "other" / "single.png", tmp_path / "missing.png"])
    assert names(items) == ["left/a.png", "right/a.png", "single.png", "missing.png"]
    assert len(failures) == 1 and "same output name 'single.png'" in failures[0].reason


def test_unlistable_folder_is_a_failure_not_a_crash(tmp_path):
    make_tree(tmp_path, ["ok/a.png", "locked/b.png"])
    (tmp_path / "locked").chmod(0)
    try:
        if os.access(tmp_path / "locked", os.R_OK):
            pytest.skip("running as root: folder permissions are not enforced")
        items, failures = collect_inputs([tmp_path])
    finally:
        (tmp_path / "locked").chmod(0o755)
    assert names(items) == ["ok/a.png"]
    assert len(failures) == 1 and "cannot list folder" in failures[0].reason


def run_all(batch: Batch, items: list[Item]) -> list:
    todo, _ = batch.plan(items)
    return list(batch.run(todo))


@pytest.mark.parametrize("fmt", ["json", "jsonl", "csv"])
def test_resume_skips_recorded_images_and_force_redoes_them(tmp_path, fmt):
    make_tree(tmp_path / "in", [f"{i}.png" for i in range(5)])
    items, _ = collect_inputs([tmp_path / "in"])
    options = BatchOptions(tmp_path / "out", fmt, overlay=False, threads=1)
    first = Batch(options).run(Batch(options).plan(items)[0])
    assert [(o.item.name, o.reason) for o in (next(first) for _ in range(3))] == [
        ("0.png", None), ("1.png", None), ("2.png", None)]
    first.close()  # stopped after three images, as by Ctrl-C
    batch = Batch(options)
    todo, skipped = batch.plan(items)
    # a CSV cannot prove its last image complete, so that one is redone
    expected = ["2.png", "3.png", "4.png"] if fmt == "csv" else ["3.png", "4.png"]
    assert names(todo) == expected and skipped == 5 - len(expected)
    assert [o.reason for o in batch.run(todo)] == [None] * len(expected)
    todo, skipped = Batch(options).plan(items)
    assert names(todo) == (["4.png"] if fmt == "csv" else [])
    forced = BatchOptions(tmp_path / "out", fmt, overlay=False, force=True, threads=1)
    assert len(run_all(Batch(forced), items)) == 5
    if fmt != "json":
        log = tmp_path / "out" / ("detections.jsonl" if fmt == "jsonl" else "corners.csv")
        text = log.read_text()
        assert all(text.count(f"{i}.png") == (text.count("0.png")) for i in range(5))  # nothing twice


def test_outcomes_come_in_input_order_with_failures_in_place(tmp_path):
    make_tree(tmp_path, ["a.png", "c.png"])
    (tmp_path / "b.png").write_bytes(b"not a png")
    items, _ = collect_inputs([tmp_path])
    outcomes = run_all(Batch(BatchOptions(tmp_path / "out", threads=1)), items)
    assert [o.item.name for o in outcomes] == ["a.png", "b.png", "c.png"]
    assert [o.reason is None for o in outcomes] == [True, False, True]
    assert "b.png: not an image" in outcomes[1].reason
    assert (tmp_path / "out" / "a.png.overlay.jpg").exists() and not (tmp_path / "out" / "b.png.json").exists()


def test_in_process_batch_holds_one_decoded_image_at_a_time(tmp_path, monkeypatch):
    make_tree(tmp_path, [f"{i}.png" for i in range(4)])
    items, _ = collect_inputs([tmp_path])
    alive: list[weakref.ref] = []
    load = ccdn.Detector.load

    def tracked_load(self, image):
        gray = load(self, image)
        if not isinstance(image, np.ndarray):  # decoded from a file (detect() re-validates arrays too)
            alive.append(weakref.ref(gray))
        return gray

    monkeypatch.setattr(ccdn.Detector, "load", tracked_load)
    batch = Batch(BatchOptions(tmp_path / "out", threads=1))
    for outcome in batch.run(batch.plan(items)[0]):
        gc.collect()
        assert outcome.reason is None
        assert sum(ref() is not None for ref in alive) == 0  # the image is dropped once its outcome is out
    assert len(alive) == 4


def test_ordered_map_yields_in_task_order_whatever_finishes_first():
    assert list(ordered_map(slow_square, list(range(12)), workers=2)) == [n * n for n in range(12)]


def test_a_task_that_kills_its_worker_fails_alone_and_the_rest_go_on():
    tasks = [1, 2, -1, 3, 4, 5, -2, 6]
    results = list(ordered_map(square_or_die, tasks, workers=2))
    assert [r for r in results if not isinstance(r, WorkerDied)] == [1, 4, 9, 16, 25, 36]
    assert [i for i, r in enumerate(results) if isinstance(r, WorkerDied)] == [2, 6]


def test_one_detector_shared_by_threads_matches_serial_calls():
    detector = ccdn.Detector(threads=2)
    images = [checkerboard(128, 96, seed) for seed in range(8)]
    serial = [detector.detect(im) for im in images]
    serial_scores = [detector.scores(im) for im in images]
    assert sum(len(d) for d in serial) > 0
    with ThreadPoolExecutor(4) as pool:
        threaded = list(pool.map(detector.detect, images * 2))
        threaded_scores = list(pool.map(detector.scores, images))
    for expected, got in zip(serial * 2, threaded):
        np.testing.assert_array_equal(got.xy, expected.xy)
        np.testing.assert_array_equal(got.score, expected.score)
    for expected, got in zip(serial_scores, threaded_scores):
        np.testing.assert_array_equal(got, expected)


def outputs(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_two_workers_write_exactly_what_one_writes(tmp_path):
    make_tree(tmp_path / "in", [f"s{i}.png" for i in range(4)])
    (tmp_path / "in" / "s2.png").write_bytes(encode(checkerboard(64, 48, seed=9), ".jpg"))
    (tmp_path / "in" / "t.png").write_bytes(b"\x89PNG\r\n\x1a\n broken")
    paths = [tmp_path / "in"]
    if REAL_DEV.is_dir():  # real photos too, the two smallest
        paths += sorted(REAL_DEV.iterdir(), key=lambda p: p.stat().st_size)[:2]
    items, _ = collect_inputs(paths)
    runs = {}
    for workers in (1, 2):  # JSON Lines: one file whose line order is the output order
        out = tmp_path / f"out-{workers}"
        outcomes = run_all(Batch(BatchOptions(out, "jsonl", overlay=True, workers=workers)), items)
        runs[workers] = (outputs(out), [(o.item.name, o.reason) for o in outcomes])
    assert runs[1] == runs[2]
    assert sum(reason is not None for _, reason in runs[1][1]) == 1


def test_bad_options_and_models_fail_before_any_image(tmp_path):
    with pytest.raises(ValueError, match="unknown format"):
        Batch(BatchOptions(tmp_path, "xml"))
    with pytest.raises(ccdn.ModelError):
        Batch(BatchOptions(tmp_path, model=tmp_path / "missing.onnx"))
    (tmp_path / "file").write_text("x")
    with pytest.raises(OSError):
        Batch(BatchOptions(tmp_path / "file" / "out"))
    assert cv2.imread(str(tmp_path / "file")) is None  # untouched
