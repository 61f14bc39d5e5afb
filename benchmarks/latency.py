"""Latency benchmark: per-stage times of Detector.detect at 640x480 and 2000x1500 (--sizes: others), 1 and 2 threads.

Frames are the real-dev photos (or the bundled examples when ../shared is absent) converted to gray
and resized to each size, decoded once up front: the timed call goes from a uint8 frame to refined
corners. Each configuration gets a warm-up, then the configurations take turns, one pass over all
frames each, `--repeat` rounds; we report the median and the 10th/90th percentiles per stage, and
("best") the median over frames of each frame's fastest pass, which a shared machine's passing
load disturbs far less. OpenCV's findChessboardCornersSB, given the true board size, runs on the
same frames for comparison. Cold start (import + session + first detect) is timed in fresh
processes (median of 5, bytecode cached), and so is peak RSS (a process that detects every frame at
one size with one detector). Frames without a board run the full-resolution pass: the bundled
cluttered one (examples/no-board.jpg) is timed at each size with the default detector, without and
with its fast check (median of --repeat runs).

    python benchmarks/latency.py [--models default paper fast] [--repeat 3] [--sizes 640x480 4000x3000] [--json out/latency.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

import ccdn

from machine import cpu_name

ROOT = Path(__file__).resolve().parents[1]
REAL_DEV = ROOT.parent / "shared" / "data" / "real-dev"
SIZES = [(640, 480), (2000, 1500)]


def iter_frames(limit: int) -> Iterator[tuple[np.ndarray, tuple[int, int] | None]]:
    """Gray frames with their board size (cols, rows), from real-dev or the bundled examples, decoded
    one at a time."""
    if (REAL_DEV / "labels.json").is_file():
        for m in json.loads((REAL_DEV / "labels.json").read_text())["images"][:limit]:
            yield (cv2.imread(str(REAL_DEV / "images" / m["file"]), cv2.IMREAD_GRAYSCALE),
                   (m["boards"][0]["cols"], m["boards"][0]["rows"]))
    else:
        for p in sorted((ROOT / "examples").glob("*.jpg")):
            yield cv2.imread(str(p), cv2.IMREAD_GRAYSCALE), None


def load_frames(limit: int) -> list[tuple[np.ndarray, tuple[int, int] | None]]:
    """iter_frames' frames, all decoded."""
    return list(iter_frames(limit))


def resized(frame: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """frame resized to size (w, h): area averaging to shrink, bilinear to enlarge."""
    return cv2.resize(frame, size, interpolation=cv2.INTER_AREA if frame.shape[1] > size[0] else cv2.INTER_LINEAR)


def stats(samples: list[float]) -> dict:
    a = np.asarray(samples)
    return {"median_ms": float(np.median(a)), "p10_ms": float(np.percentile(a, 10)), "p90_ms": float(np.percentile(a, 90))}


SETTLE_S = 0.1  # a pause before each pass, so that no thread of the configuration before still spins on the
# cores the next one's first frames need (onnxruntime's workers spun ~30 ms after a run, measured, until
# ccdn.session stopped them at the run's end; other pools, such as OpenCV's that SB uses, may still)


def time_detectors(detectors: list[ccdn.Detector], frames: list[np.ndarray], repeat: int) -> list[dict]:
    """For each detector, per-stage stats over every pass of every frame, and under "best_total" the
    median over frames of each frame's fastest pass. The detectors take turns, one pass over the
    frames each, `repeat` rounds: a shared machine's passing load then slows a pass of each rather
    than every pass of one (measured: run one after the other, a whole configuration's median and
    its best of 5 moved from ~13 to ~23 ms in one run while the next configuration's did not)."""
    for detector in detectors:
        for f in frames[:3]:
            detector.detect(f)
    stages: list[dict[str, list[float]]] = [{"total": []} for _ in detectors]
    for _ in range(repeat):
        for detector, samples in zip(detectors, stages):
            time.sleep(SETTLE_S)
            for f in frames:
                t0 = time.perf_counter()
                result = detector.detect(f)
                samples["total"].append((time.perf_counter() - t0) * 1e3)
                for k, v in result.timings_ms.items():
                    samples.setdefault(k, []).append(v)
    reports = []
    for samples in stages:
        report = {k: stats(v) for k, v in samples.items()}
        best = np.reshape(samples["total"], (repeat, len(frames))).min(0)
        report["best_total"] = {"median_ms": float(np.median(best))}
        reports.append(report)
    return reports


def time_opencv(frames: list[np.ndarray], sizes: list[tuple[int, int] | None], repeat: int) -> dict | None:
    pairs = [(f, s) for f, s in zip(frames, sizes) if s is not None]
    if not pairs:
        return None
    samples, found = [], 0
    for _ in range(repeat):
        for f, s in pairs:
            t0 = time.perf_counter()
            ok, _ = cv2.findChessboardCornersSB(f, s)
            samples.append((time.perf_counter() - t0) * 1e3)
            found += int(ok)
    return {"total": stats(samples), "found_fraction": found / len(samples)}


def time_boardless(threads: int, repeat: int, sizes: list[tuple[int, int]]) -> dict:
    """Median ms (time_detectors) of the default detector, without and with its fast check, on the
    bundled cluttered frame without a board (examples/no-board.jpg) resized to each of `sizes`: such
    frames run the full-resolution pass, which the fast check skips."""
    gray = cv2.imread(str(ROOT / "examples" / "no-board.jpg"), cv2.IMREAD_GRAYSCALE)
    names = {"default": False, "fast check": True}
    detectors = [ccdn.Detector(threads=threads, fast_check=check) for check in names.values()]
    out: dict[str, dict[str, float]] = {name: {} for name in names}
    for w, h in sizes:
        for name, stages in zip(names, time_detectors(detectors, [resized(gray, (w, h))], repeat)):
            out[name][f"{w}x{h}"] = stages["total"]["median_ms"]
    return out


def _size(text: str) -> tuple[int, int]:
    """A --sizes entry, "WxH", as (W, H)."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH, e.g. 640x480, got {text!r}") from None
    return w, h


def _detector_args(name: str) -> tuple[str | None, str | None]:
    """A --models entry as Detector's (model, coarse_model): 'default' is the default detector,
    'COARSE+FULL' a cascade of two named models (e.g. fast-int8+fine-int8), a lone name that model
    on every pass."""
    if name == "default":
        return None, None
    coarse, _, full = name.rpartition("+")
    return full, coarse or None


def _detector(name: str, threads: int) -> ccdn.Detector:
    """The detector a --models entry names (_detector_args), with `threads`."""
    model, coarse_model = _detector_args(name)
    return ccdn.Detector(model, threads, coarse_model=coarse_model)


def cold_start(detector_args: tuple[str | None, str | None], repeat: int = 5) -> float:
    """Seconds for import + Detector + first detect of a blank 640x480 frame in a fresh interpreter,
    median of `repeat`; detector_args: Detector's (model, coarse_model) (_detector_args). Python may
    cache bytecode, as it does by default and as pip does when it installs the wheel (an untimed
    first run writes the cache): this machine's environment sets PYTHONDONTWRITEBYTECODE, which
    would make every start compile ccdn's modules again (~35 ms)."""
    code = ("import time; t=time.perf_counter(); import numpy as np, ccdn; "
            f"d=ccdn.Detector({detector_args[0]!r}, coarse_model={detector_args[1]!r}); "
            "d.detect(np.zeros((480, 640), np.uint8)); "
            "print(time.perf_counter()-t)")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    runs = [subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env)
            for _ in range(repeat + 1)]
    return float(np.median([float(r.stdout.strip()) for r in runs[1:]]))


def peak_rss_mb(detector_args: tuple[str | None, str | None], size: tuple[int, int], frames: int,
                threads: int) -> float:
    """Peak RSS (MB) of a fresh process that builds the detector and detects every frame at `size`:
    what an app running that one detector holds (this process, with every configuration's detector
    alive at once, would hold them all)."""
    code = ("import sys, ccdn; sys.path.insert(0, sys.argv[1]); from latency import iter_frames, resized; "
            "from machine import own_peak_rss_mb; "
            f"d = ccdn.Detector({detector_args[0]!r}, {threads}, coarse_model={detector_args[1]!r}); "
            f"[d.detect(resized(f, {size!r})) for f, _ in iter_frames({frames})]; "
            "print(own_peak_rss_mb())")
    done = subprocess.run([sys.executable, "-c", code, str(Path(__file__).parent)], capture_output=True, text=True,
                          check=True)
    return float(done.stdout.strip())


STAGES = ("load", "network", "peaks", "refine", "boards", "edges")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", nargs="+", default=["default"],
                        help="bundled model names or .onnx paths (that model on every pass), COARSE+FULL for a "
                             "cascade of two (e.g. fast-int8+fine-int8); 'default': the default detector")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--frames", type=int, default=12, help="how many real-dev photos to use")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--sizes", type=_size, nargs="+", default=SIZES, help="frame sizes WxH (default: 640x480 2000x1500)")
    parser.add_argument("--no-opencv", action="store_true")
    parser.add_argument("--json", type=Path, default=ROOT / "out" / "latency.json")
    args = parser.parse_args(argv)

    loaded = load_frames(args.frames)
    board_sizes = [s for _, s in loaded]
    report = {"machine": {"cpu": cpu_name(), "cpus": os.cpu_count(),
                          "python": platform.python_version()},
              "frames": len(loaded), "repeat": args.repeat,
              "cold_start_ms": {m: cold_start(_detector_args(m)) * 1e3 for m in args.models}, "peak_rss_mb": {},
              "runs": []}
    for w, h in args.sizes:
        frames = [resized(f, (w, h)) for f, _ in loaded]
        detectors = [_detector(model, threads) for model in args.models for threads in args.threads]
        for detector, stages in zip(detectors, time_detectors(detectors, frames, args.repeat)):
            report["runs"].append({"size": f"{w}x{h}", "threads": detector.threads, "model": detector.models,
                                   "stages": stages})
        if not args.no_opencv:
            cv2.setNumThreads(max(args.threads))
            report["runs"].append({"size": f"{w}x{h}", "threads": max(args.threads), "model": "opencv-findChessboardCornersSB",
                                   "stages": time_opencv(frames, board_sizes, 1)})
        for model in args.models:
            rss = peak_rss_mb(_detector_args(model), (w, h), args.frames, max(args.threads))
            report["peak_rss_mb"].setdefault(model, {})[f"{w}x{h}"] = rss
    report["boardless_ms"] = time_boardless(max(args.threads), args.repeat, args.sizes)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=1))
    print(format_table(report))
    print(f"written {args.json}")


def format_table(report: dict) -> str:
    """Per-stage medians per run, then each model's speed-up over findChessboardCornersSB."""
    lines = [f"{'size':<11}{'thr':>4}  {'model':<30}{'total ms':>9}{'p10-p90':>14}{'best ms':>9}"
             + "".join(f"{k:>9}" for k in STAGES)]
    opencv = {r["size"]: r["stages"]["total"]["median_ms"] for r in report["runs"]
              if r["model"].startswith("opencv") and r["stages"]}
    ratios = []
    for run in report["runs"]:
        s = run["stages"]
        if s is None:
            continue
        t = s["total"]
        lines.append(f"{run['size']:<11}{run['threads']:>4}  {run['model']:<30}{t['median_ms']:>9.1f}"
                     f"{t['p10_ms']:>7.1f}-{t['p90_ms']:<6.1f}"
                     + (f"{s['best_total']['median_ms']:>9.1f}" if "best_total" in s else f"{'-':>9}")
                     + "".join(f"{s[k]['median_ms']:>9.1f}" if k in s else f"{'-':>9}" for k in STAGES))
        if run["size"] in opencv and not run["model"].startswith("opencv") and run["threads"] == max(r["threads"] for r in report["runs"]):
            ratios.append(f"{run['model']} at {run['size']}, {run['threads']} threads: "
                          f"{opencv[run['size']] / t['median_ms']:.1f}x faster than findChessboardCornersSB")
    lines += ratios
    lines += [f"cold start {m} (import + session + first detect of a blank 640x480 frame, median of 5): {v:.0f} ms"
              for m, v in report["cold_start_ms"].items()]
    lines += [f"boardless frame (examples/no-board.jpg), {name}: "
              + ", ".join(f"{v:.1f} ms at {size}" for size, v in sizes.items())
              for name, sizes in report["boardless_ms"].items()]
    lines += [f"peak RSS {m} ({max(r['threads'] for r in report['runs'])} threads, a fresh process detecting every "
              f"frame): " + ", ".join(f"{v:.0f} MB at {size}" for size, v in sizes.items())
              for m, sizes in report["peak_rss_mb"].items()]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
