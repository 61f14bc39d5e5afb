"""`ccdn detect`: flags, exit codes, a corrupted corpus, and a run killed and resumed."""

from __future__ import annotations

import csv
import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

import ccdn
from ccdn import batch, cli, image
from ccdn.cli import main
from imagefiles import checkerboard, encode, png_bytes

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
FAILED = "ccdn: failed: "


def summary(stderr: str) -> dict[str, str]:
    return {line[len(FAILED) :].split(": ", 1)[0]: line for line in stderr.splitlines() if line.startswith(FAILED)}


def base_images() -> list[np.ndarray]:
    """A few small real-looking images: the bundled examples shrunk, or rendered boards."""
    if EXAMPLES.is_dir() and sorted(EXAMPLES.glob("*.jpg")):
        return [cv2.resize(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE), (160, 120), interpolation=cv2.INTER_AREA)
                for p in sorted(EXAMPLES.glob("*.jpg"))[:3]]
    return [checkerboard(160, 120, seed) for seed in range(3)]


def corrupted_corpus(root: Path) -> tuple[set[str], dict[str, str], set[str]]:
    """Write 100+ files into `root`: (names that must work, names that must fail -> reason, either)."""
    rng = np.random.default_rng(2024)
    good: set[str] = set()
    bad: dict[str, str] = {}
    either: set[str] = set()

    def put(name: str, data: bytes, expect: str | None = None, ok: bool | None = None) -> None:
        (root / name).write_bytes(data)
        if ok:
            good.add(name)
        elif expect is not None:
            bad[name] = expect
        else:
            either.add(name)

    for b, gray in enumerate(base_images()):
        for suffix in (".png", ".jpg"):
            data = encode(gray, suffix)
            put(f"b{b}{suffix}", data, ok=True)
            for frac in (0.01, 0.05, 0.2, 0.4, 0.6, 0.8, 0.95):
                put(f"b{b}-cut{int(frac * 100)}{suffix}", data[: int(len(data) * frac)], "cannot decode")
            put(f"b{b}-cut-tail{suffix}", data[:-2], "cannot decode")
            for k in range(4):  # a few bytes flipped past the header: may decode (garbled) or not
                flipped = bytearray(data)
                for pos in rng.integers(200, len(data) - 20, k + 1):
                    flipped[pos] ^= 0xFF
                put(f"b{b}-flip{k}{suffix}", bytes(flipped))
            put(f"b{b}-magic{suffix}", b"\x00" * 8 + data[8:], "not an image")
        png = bytearray(encode(gray, ".png"))
        png[16:20] = (0).to_bytes(4, "big")
        put(f"b{b}-zero-width.png", bytes(png), "size of 0x120")
        png[16:24] = (60_000).to_bytes(4, "big") * 2
        put(f"b{b}-huge.png", bytes(png), "over the limit")
        put(f"b{b}.bmp", encode(gray, ".bmp"), ok=True)
        put(f"b{b}-gray-alpha.png", png_bytes(np.dstack([gray, gray]), 4), ok=True)
        put(f"b{b}-rgba.png", png_bytes(np.dstack([gray] * 3 + [np.full_like(gray, 200)]), 6), ok=True)
        put(f"b{b}-gray16.png", png_bytes(gray.astype(np.uint16) * 257, 0, 16), ok=True)
        put(f"b{b}-palette.png", png_bytes(gray // 16, 3, palette=np.repeat(np.arange(16, dtype=np.uint8)[:, None] * 17, 3, 1)), ok=True)
    for i in range(6):
        put(f"empty{i}.{['png', 'jpg', 'tif'][i % 3]}", b"", "empty file")
        put(f"text{i}.jpg", f"line {i}: this is a text file, not a JPEG\n".encode() * (i + 1), "not an image")
        put(f"noise{i}.png", rng.integers(0, 256, 100 * (i + 1), dtype=np.uint8).tobytes(), "not an image")
        put(f"png-then-garbage{i}.png", b"\x89PNG\r\n\x1a\n" + rng.integers(0, 256, 64, dtype=np.uint8).tobytes(), "PNG")
    for suffix in (".png", ".jpg", ".bmp"):
        put(f"one-pixel{suffix}", encode(np.full((1, 1), 90, np.uint8), suffix), ok=True)
    for name in ("-leading-dash.png", "with space.png", "ünïcødé 图像.png"):
        put(name, encode(base_images()[0]), ok=True)
    os.mkfifo(root / "fifo.png")
    bad["fifo.png"] = "not a regular file"
    os.symlink(root / "nowhere.png", root / "dangling.png")
    bad["dangling.png"] = "no such file"
    locked = root / "locked.png"
    locked.write_bytes(encode(base_images()[0]))
    locked.chmod(0)
    if os.access(locked, os.R_OK):  # root ignores permissions: then the file simply works
        good.add("locked.png")
    else:
        bad["locked.png"] = "permission denied"
    return good, bad, either


def check_corpus_run(out: Path, stderr: str, good: set[str], bad: dict[str, str], either: set[str], fmt: str) -> set[str]:
    """Every file accounted for exactly once, with its reason; returns the names that got a result."""
    failures = summary(stderr)
    if fmt == "json":
        done = {p.name[: -len(".json")] for p in out.glob("*.json")}
        for name in done:
            record = json.loads((out / f"{name}.json").read_text())
            assert record["image"] == name and len(record["corners"]) == len(record["score"])
    else:
        done = {json.loads(line)["image"] for line in (out / "detections.jsonl").read_text().splitlines()}
    names = {Path(f).name for f in failures}
    assert done | names == good | set(bad) | either and not done & names
    assert good <= done
    for name, reason in bad.items():
        assert name in names and reason in failures[str(out.parent / "in" / name)], (name, failures.get(name))
    assert not [p for p in out.rglob("*") if p.name.endswith(".ccdn-tmp")]
    return done


def test_corrupted_corpus_every_file_gets_a_result_or_a_reason(tmp_path, capsys):
    (tmp_path / "in").mkdir()
    good, bad, either = corrupted_corpus(tmp_path / "in")
    assert len(good) + len(bad) + len(either) >= 100
    code = main(["detect", str(tmp_path / "in"), "--out", str(tmp_path / "out"), "--no-overlay"])
    stderr = capsys.readouterr().err
    assert code == 1
    done = check_corpus_run(tmp_path / "out", stderr, good, bad, either, "json")
    assert all("\n" not in line for line in summary(stderr).values())
    assert f"ccdn: {len(done)} images done, 0 already done, {len(bad) + len(either) - len(done & either)} failed" in stderr
    # the same corpus through the installed command, in two worker processes, to a JSON Lines file
    proc = subprocess.run([sys.executable, "-m", "ccdn.cli", "detect", str(tmp_path / "in"), "--out",
                           str(tmp_path / "out2"), "--format", "jsonl", "--workers", "2"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1
    assert check_corpus_run(tmp_path / "out2", proc.stderr, good, bad, either, "jsonl") == done


def make_inputs(root: Path, count: int, size: tuple[int, int] = (96, 72)) -> list[str]:
    root.mkdir(parents=True, exist_ok=True)
    names = [f"img{i:03d}.png" for i in range(count)]
    for i, name in enumerate(names):
        (root / name).write_bytes(encode(checkerboard(*size, seed=i % 7)))
    return names


def child_pids(pid: int) -> set[int]:
    """Processes whose parent is `pid` (Linux /proc)."""
    found = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # the process is gone
            continue
        if int(fields[1]) == pid:
            found.add(int(stat.parent.name))
    return found


def running(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux /proc")
@pytest.mark.parametrize("fmt, workers", [("json", 1), ("jsonl", 2)])
def test_killed_run_resumes_without_redoing_or_corrupting_anything(tmp_path, capsys, fmt, workers):
    names = make_inputs(tmp_path / "in", 60, (128, 96))
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "ccdn.cli", "detect", str(tmp_path / "in"), "--out", str(out),
                             "--format", fmt, "--threads", "1", "--workers", str(workers)], stderr=subprocess.DEVNULL)

    def finished() -> int:
        if fmt == "json":
            return len(list(out.glob("*.json")))
        log = out / "detections.jsonl"
        return log.read_bytes().count(b"\n") if log.exists() else 0

    deadline = time.monotonic() + 60
    while finished() < 5 and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.005)
    workers_pids = child_pids(proc.pid)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL, "the run ended before it could be killed"
    assert len(workers_pids) >= (workers if workers > 1 else 0)
    deadline = time.monotonic() + 10
    while any(map(running, workers_pids)) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(map(running, workers_pids)), "worker processes outlived their killed parent"
    before = {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in out.iterdir() if not p.name.startswith(".")}
    killed_at = finished()
    assert 5 <= killed_at < len(names)

    assert main(["detect", str(tmp_path / "in"), "--out", str(out), "--format", fmt]) == 0
    stderr = capsys.readouterr().err
    assert f"{killed_at} of {len(names)} images already done" in stderr
    assert f"ccdn: {len(names) - killed_at} images done" in stderr
    if fmt == "json":
        finished = [name[: -len(".json")] for name in before if name.endswith(".json")]
        for name in finished:  # a finished image's JSON and overlay are not written again
            for path in (out / f"{name}.json", out / f"{name}.overlay.jpg"):
                assert (path.stat().st_mtime_ns, path.read_bytes()) == before[path.name], path.name
        records = {n: json.loads((out / f"{n}.json").read_text()) for n in names}
    else:
        log = before["detections.jsonl"][1]
        lines = (out / "detections.jsonl").read_text().splitlines()
        assert (out / "detections.jsonl").read_bytes().startswith(log[: log.rfind(b"\n") + 1])
        records = {r["image"]: r for r in map(json.loads, lines)}
        assert len(lines) == len(names) == len(records)  # each image once
    assert sorted(records) == names
    assert not [p for p in out.iterdir() if p.name.endswith(".ccdn-tmp")]
    detector = ccdn.Detector()
    for name in (names[0], names[killed_at], names[-1]):  # before, at and after the kill: same as a direct call
        assert records[name]["corners"] == detector.detect(tmp_path / "in" / name).to_dict()["corners"]


def test_exit_code_is_2_for_usage_and_model_errors(tmp_path, capsys):
    make_inputs(tmp_path / "in", 1)
    (tmp_path / "empty").mkdir()
    (tmp_path / "a-file").write_text("x")
    (tmp_path / "foreign").mkdir()
    (tmp_path / "foreign" / "detections.jsonl").write_text("my own notes\n")
    cases = [
        (["--model", str(tmp_path / "missing.onnx")], "no such model file"),
        (["--model", "no-such-model"], "unknown model"),
        (["--out", str(tmp_path / "a-file" / "out")], "a-file"),
        (["--out", str(tmp_path / "foreign"), "--format", "jsonl"], "not a ccdn results file"),
        (["--include", "*.nothing"], "no images found"),
    ]
    for extra, message in cases:
        args = ["detect", str(tmp_path / "in"), "--out", str(tmp_path / "out"), *extra]
        assert main(args) == 2, extra
        assert message in capsys.readouterr().err, extra
    assert main(["detect", str(tmp_path / "empty"), "--out", str(tmp_path / "out")]) == 2
    for bad_flag in (["--workers", "0"], ["--format", "xml"], ["--max-pixels", "-5"]):
        with pytest.raises(SystemExit) as info:
            main(["detect", str(tmp_path / "in"), "--out", str(tmp_path / "out"), *bad_flag])
        assert info.value.code == 2
    assert (tmp_path / "foreign" / "detections.jsonl").read_text() == "my own notes\n"


def test_all_good_exits_0_and_a_missing_input_exits_1_after_the_rest(tmp_path, capsys):
    make_inputs(tmp_path / "in", 2)
    assert main(["detect", str(tmp_path / "in"), "--out", str(tmp_path / "out")]) == 0
    stderr = capsys.readouterr().err
    assert "ccdn: 2 images done, 0 already done, 0 failed" in stderr and "img/s" not in stderr  # no bar: not a terminal
    missing = tmp_path / "nope.png"
    assert main(["detect", str(missing), str(tmp_path / "in" / "img000.png"), "--out", str(tmp_path / "o2")]) == 1
    assert f"{FAILED}{missing}: no such file" in capsys.readouterr().err
    assert (tmp_path / "o2" / "img000.png.json").exists()


def test_overlays_default_on_for_json_and_off_for_logs(tmp_path):
    make_inputs(tmp_path / "in", 2)
    runs = {"json": [], "csv": [], "csv-overlay": ["--overlay"], "json-no-overlay": ["--no-overlay"]}
    for name, extra in runs.items():
        fmt = name.split("-")[0]
        assert main(["detect", str(tmp_path / "in"), "--out", str(tmp_path / name), "--format", fmt, "--quiet", *extra]) == 0
    overlays = {name: len(list((tmp_path / name).glob("*.overlay.jpg"))) for name in runs}
    assert overlays == {"json": 2, "csv": 0, "csv-overlay": 2, "json-no-overlay": 0}
    rows = list(csv.reader((tmp_path / "csv" / "corners.csv").open()))
    assert rows[0] == ["image", "x", "y", "score"] and {r[0] for r in rows[1:]} == {"img000.png", "img001.png"}
    image_at = cv2.imread(str(tmp_path / "json" / "img000.png.overlay.jpg"))
    assert image_at.shape == (72, 96, 3)


def test_quickstart_command_writes_json_and_overlays_for_the_examples(tmp_path, monkeypatch):
    if not EXAMPLES.is_dir():
        pytest.skip("no bundled examples")
    monkeypatch.chdir(EXAMPLES.parent)
    assert main(["detect", "examples", "--out", str(tmp_path / "out"), "--quiet"]) == 0
    for path in EXAMPLES.glob("*.jpg"):
        assert json.loads((tmp_path / "out" / f"{path.name}.json").read_text())["path"] == f"examples/{path.name}"
        assert (tmp_path / "out" / f"{path.name}.overlay.jpg").stat().st_size > 0


def test_coarse_model_reaches_the_workers_with_the_full_frame_model(tmp_path):
    """--model serves the full frame and --coarse-model the shrunk passes, in worker processes too:
    the board is found on the halved frame (the coarse model's pass), the boardless frame runs the
    full-frame pass (its model's)."""
    if not EXAMPLES.is_dir():
        pytest.skip("no bundled examples")
    out = tmp_path / "out"
    assert main(["detect", str(EXAMPLES / "board.jpg"), str(EXAMPLES / "no-board.jpg"), "--out", str(out),
                 "--model", "fine-int8", "--coarse-model", "fast-int8", "--workers", "2", "--quiet"]) == 0
    board, empty = (json.loads((out / f"{name}.json").read_text()) for name in ("board.jpg", "no-board.jpg"))
    assert board["model"].startswith("fast-int8 ") and len(board["corners"]) == 54
    assert empty["model"].startswith("fine-int8 ") and empty["corners"] == []


def test_names_starting_with_a_dash_work_after_double_dash(tmp_path, monkeypatch, capsys):
    make_inputs(tmp_path, 1)
    (tmp_path / "img000.png").rename(tmp_path / "-dash.png")
    monkeypatch.chdir(tmp_path)
    assert main(["detect", "--out", "out", "--", "-dash.png"]) == 0
    assert (tmp_path / "out" / "-dash.png.json").exists()


def test_max_pixels_and_patterns_reach_the_batch(tmp_path, capsys):
    make_inputs(tmp_path / "in", 3)
    code = main(["detect", str(tmp_path / "in"), "--out", str(tmp_path / "out"), "--max-pixels", "1000",
                 "--exclude", "img002*"])
    stderr = capsys.readouterr().err
    assert code == 1
    assert len(summary(stderr)) == 2 and "96x72 = 6912 pixels, over the limit of 1000" in stderr
    assert "img002" not in stderr


def test_quiet_prints_failures_but_no_summary(tmp_path, capsys):
    make_inputs(tmp_path / "in", 1)
    (tmp_path / "in" / "bad.png").write_bytes(b"")
    assert main(["detect", str(tmp_path / "in"), "--out", str(tmp_path / "out"), "--quiet"]) == 1
    stderr = capsys.readouterr().err
    assert stderr.strip().splitlines() == [f"{FAILED}{tmp_path / 'in' / 'bad.png'}: empty file (0 bytes)"]


def test_parser_repeats_of_library_constants_have_not_drifted():
    assert cli.FORMATS == list(batch.FORMATS)
    assert cli.MAX_PIXELS_HELP == str(image.DEFAULT_MAX_PIXELS)


class FakeTerminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_bar_shows_count_and_rate_on_a_terminal_only(tmp_path, monkeypatch):
    make_inputs(tmp_path / "in", 2)
    for quiet, out in ((False, "a"), (True, "b")):
        terminal = FakeTerminal()
        monkeypatch.setattr(sys, "stderr", terminal)
        assert main(["detect", str(tmp_path / "in"), "--out", str(tmp_path / out), *(["--quiet"] if quiet else [])]) == 0
        shown = "2/2" in terminal.getvalue() and "img/s" in terminal.getvalue()
        assert shown is not quiet
