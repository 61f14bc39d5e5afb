"""The `ccdn` command: a thin shell over the API (detect files and folders, write results)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm", ".pbm", ".jp2"}



def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("ccdn")
    except PackageNotFoundError:
        return "unknown"


def collect_inputs(paths: list[Path]) -> list[tuple[Path, Path]]:
    """(file, name relative to its input) for each file given and each image file under each folder."""
    items = []
    for root in paths:
        if root.is_dir():
            for p in sorted(root.rglob("*")):
                if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES:
                    items.append((p, p.relative_to(root)))
        else:
            items.append((root, Path(root.name)))  # missing files are reported when processed
    return items


def run_detect(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from .detector import Detector
    from .image import ImageError
    from .models import ModelError
    from .writers import write_json, write_overlay

    try:
        detector = Detector(args.model, args.threads)
    except ModelError as exc:
        print(f"ccdn: {exc}", file=sys.stderr)
        return 2
    items = collect_inputs(args.paths)
    if not items:
        print("ccdn: no images found in " + ", ".join(map(str, args.paths)), file=sys.stderr)
        return 1
    failures: list[tuple[Path, str]] = []
    total_corners = 0
    bar = tqdm(items, unit="img", disable=args.quiet or not sys.stderr.isatty(), file=sys.stderr)
    for path, name in bar:
        try:
            gray = detector.load(path)
            result = detector.detect(gray)
            write_json(args.out / name.with_suffix(".json"), result, str(path))
            if not args.no_overlay:
                write_overlay(args.out / name.with_name(name.stem + ".overlay.jpg"), gray, result)
        except (ImageError, OSError) as exc:
            failures.append((path, str(exc)))
            tqdm.write(f"ccdn: skipped {exc}", file=sys.stderr)
            continue
        total_corners += len(result)
    done = len(items) - len(failures)
    print(f"ccdn: {done} of {len(items)} images done, {total_corners} corners, results in {args.out}", file=sys.stderr)
    for path, reason in failures:
        print(f"  failed: {reason}", file=sys.stderr)
    return 1 if failures else 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ccdn", description="Checkerboard corner detection (CCDN).")
    parser.add_argument("--version", action="version", version=f"ccdn {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("detect", help="detect corners in images and folders; one JSON (+ overlay) per image")
    p.add_argument("paths", nargs="+", type=Path, help="image files and folders (searched recursively)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--model", default=None, help="bundled model name or .onnx path (default: paper)")
    p.add_argument("--threads", type=int, default=None, help="inference threads (default: CPUs, capped at 4)")
    p.add_argument("--no-overlay", action="store_true", help="write JSON results only")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_detect)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
