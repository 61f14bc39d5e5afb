"""Batch benchmark: `ccdn detect` throughput with 1 and 2 workers, and peak memory on large frames.

Throughput: the real command (a fresh process: imports, model load, worker start-up included) over a
folder, the real-dev photos by default (or the bundled examples when ../shared is absent), JSON
results without overlays; images/s = images / wall time, median over `--repeat` runs (after
`--warmup` untimed runs that fill the file cache). Peak memory: the command on one synthetic frame of
2000x1500 and of 4000x3000 (and a 64x48 baseline: imports and session alone), with and without the
overlay, as the process's own VmHWM (Linux; one worker, so one process). Load average and CPU count are recorded:
on a shared machine the figures are only comparable with the load noted.

    python benchmarks/batch.py [--folder DIR] [--limit N] [--repeat 1] [--warmup 1] [--json out/batch.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from machine import cpu_name

ROOT = Path(__file__).resolve().parents[1]
REAL_DEV = ROOT.parent / "shared" / "data" / "real-dev" / "images"
MEMORY_SIZES = [(64, 48), (2000, 1500), (4000, 3000)]


# The child reports its own high-water mark on exit (machine.own_peak_rss_mb): ru_maxrss from wait4
# would also count the parent's, which Linux carries into a vforked child across exec.
PEAK_REPORTER = """import atexit, runpy, sys
sys.path.insert(0, sys.argv.pop(1))
from machine import own_peak_rss_mb
atexit.register(lambda: print(int(own_peak_rss_mb())))
sys.argv = ["ccdn", *sys.argv[1:]]
runpy.run_module("ccdn.cli", run_name="__main__")
"""


def ccdn_command(*args: str) -> list[str]:
    return [sys.executable, "-c", PEAK_REPORTER, str(Path(__file__).parent), "detect", *args, "--quiet"]


def run_measured(command: list[str]) -> tuple[float, int, int]:
    """(wall seconds, exit status, the process's own peak RSS in MiB) of a `ccdn_command`."""
    t0 = time.perf_counter()
    proc = subprocess.run(command, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    return time.perf_counter() - t0, proc.returncode, int(proc.stdout.split()[-1])


def throughput(images: list[Path], workers: int, repeat: int, warmup: int, scratch: Path) -> dict:
    walls = []
    for i in range(repeat + warmup):
        out = scratch / f"w{workers}-{i}"
        wall, code, rss = run_measured(ccdn_command(*map(str, images), "--out", str(out), "--no-overlay",
                                                    "--workers", str(workers)))
        if code != 0:
            raise SystemExit(f"ccdn detect exited with {code} on {len(images)} images")
        shutil.rmtree(out)
        if i >= warmup:  # warm-up runs only fill the file cache
            walls.append(wall)
    wall = statistics.median(walls)
    return {"workers": workers, "images": len(images), "wall_s": round(wall, 2), "runs_s": [round(w, 2) for w in walls],
            "images_per_s": round(len(images) / wall, 2)}


def board_frame(width: int, height: int) -> np.ndarray:
    """A large gray frame with a checkerboard filling the middle."""
    cell = max(8, width // 16)
    board = ((np.indices((height, width)) // cell).sum(0) % 2 * 180 + 40).astype(np.uint8)
    frame = np.full((height, width), 128, np.uint8)
    y0, x0 = height // 6, width // 6
    frame[y0 : height - y0, x0 : width - x0] = board[y0 : height - y0, x0 : width - x0]
    return cv2.GaussianBlur(frame, (0, 0), 1.0)


def peak_memory(scratch: Path) -> list[dict]:
    rows = []
    for width, height in MEMORY_SIZES:
        path = scratch / f"frame-{width}x{height}.png"
        cv2.imwrite(str(path), board_frame(width, height))
        for overlay in (False, True):
            out = scratch / f"mem-{width}-{overlay}"
            wall, code, rss = run_measured(ccdn_command(str(path), "--out", str(out), "--workers", "1",
                                                        "--overlay" if overlay else "--no-overlay"))
            rows.append({"size": f"{width}x{height}", "megapixels": round(width * height / 1e6, 2), "overlay": overlay,
                         "peak_rss_mib": rss, "wall_s": round(wall, 2), "exit": code})
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--folder", type=Path, default=REAL_DEV if REAL_DEV.is_dir() else ROOT / "examples")
    parser.add_argument("--limit", type=int, default=0, help="use only the first N images (0: all)")
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--warmup", type=int, default=1, help="untimed runs before the timed ones")
    parser.add_argument("--json", type=Path, default=ROOT / "out" / "batch.json")
    args = parser.parse_args(argv)
    images = sorted(p for p in args.folder.iterdir() if p.suffix.lower() in {".jpg", ".jpeg", ".png"})
    images = images[: args.limit] if args.limit else images
    megapixels = sum(np.prod(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE).shape) for p in images) / 1e6
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        scratch = Path(tmp)
        rates = [throughput(images, workers, args.repeat, args.warmup, scratch) for workers in (1, 2)]
        memory = peak_memory(scratch)
    result = {
        "folder": str(args.folder), "megapixels_total": round(megapixels, 1), "throughput": rates, "memory": memory,
        "cpu": cpu_name(), "cpus": os.cpu_count(),
        "load_average_before": [round(x, 2) for x in load_before],
        "load_average_after": [round(x, 2) for x in os.getloadavg()],
        "python": platform.python_version(), "opencv": cv2.__version__,
    }
    print(f"{len(images)} images, {megapixels:.1f} MP, from {args.folder}")
    print(f"{'workers':>8} {'wall s':>8} {'images/s':>9} {'MP/s':>6}")
    for r in rates:
        print(f"{r['workers']:>8} {r['wall_s']:>8.2f} {r['images_per_s']:>9.2f} {megapixels / r['wall_s']:>6.2f}")
    print(f"\n{'frame':>10} {'overlay':>8} {'peak RSS MiB':>13} {'wall s':>7}")
    for m in memory:
        print(f"{m['size']:>10} {str(m['overlay']):>8} {m['peak_rss_mib']:>13} {m['wall_s']:>7.2f}")
    print(f"\nload average before/after: {result['load_average_before']} / {result['load_average_after']} on {result['cpus']} CPUs")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=1) + "\n")
    print(f"written {args.json}")


if __name__ == "__main__":
    main()
