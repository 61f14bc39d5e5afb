"""The `ccdn` command: a thin shell over the API (detect files and folders, write results)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .models import COARSE_MODEL_HELP, DEFAULT_HELP

FORMATS = ["json", "jsonl", "csv"]  # ccdn.batch.FORMATS, repeated so that the parser imports nothing heavy
MAX_PIXELS_HELP = "100000000"  # ccdn.image.DEFAULT_MAX_PIXELS, likewise (a test checks both)


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("ccdn")
    except PackageNotFoundError:
        return "unknown"


def positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def run_detect(args: argparse.Namespace) -> int:
    """`ccdn detect`: exit 0 when every image was done, 1 when some failed, 2 on a usage or model error."""
    import cv2
    from tqdm import tqdm

    from .batch import Batch, BatchOptions, collect_inputs, default_workers
    from .image import DEFAULT_MAX_PIXELS

    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)  # failures get their own reasons below
    overlay = args.format == "json" if args.overlay is None else args.overlay
    workers = args.workers or default_workers()
    options = BatchOptions(args.out, args.format, overlay, args.force, workers, args.threads, args.model,
                           args.max_pixels or DEFAULT_MAX_PIXELS, args.exhaustive, args.coarse_model)
    try:
        batch = Batch(options)
        items, failures = collect_inputs(args.paths, args.include, args.exclude, skip=args.out)
        if not items and not failures:
            print(f"ccdn: no images found in {', '.join(map(str, args.paths))} (see --include)", file=sys.stderr)
            return 2
        todo, skipped = batch.plan(items)
    except (OSError, ValueError) as exc:  # ModelError is a ValueError
        print(f"ccdn: {exc}", file=sys.stderr)
        return 2
    show_bar = not args.quiet and sys.stderr.isatty()
    if skipped and not args.quiet:
        print(f"ccdn: {skipped} of {len(items)} images already done (--force redoes them)", file=sys.stderr)
    done = corners = 0
    bar = tqdm(total=len(todo), unit="img", disable=not show_bar, file=sys.stderr, dynamic_ncols=True)
    try:
        for outcome in batch.run(todo):
            bar.update()
            if outcome.reason is None:
                done += 1
                corners += outcome.corners
            else:
                failures.append(outcome)
                if show_bar:
                    bar.write(f"ccdn: failed: {outcome.reason}", file=sys.stderr)
    except KeyboardInterrupt:
        bar.close()
        print(f"ccdn: interrupted after {done} images; run the same command again to resume", file=sys.stderr)
        return 130
    bar.close()
    if not args.quiet:
        where = args.out / batch.log_name if batch.log_name else args.out
        print(f"ccdn: {done} images done, {skipped} already done, {len(failures)} failed, {corners} corners; "
              f"results in {where}", file=sys.stderr)
    for outcome in failures:
        print(f"ccdn: failed: {outcome.reason}", file=sys.stderr)
    return 1 if failures else 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ccdn", description="Checkerboard corner detection (CCDN).")
    parser.add_argument("--version", action="version", version=f"ccdn {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser(
        "detect", help="detect corners in images and folders (parallel, resumable)",
        description="Detect checkerboard corners in image files and folders (searched recursively). Images "
                    "whose result is already in --out are skipped, so an interrupted run resumes where it "
                    "stopped. Exit status: 0 all images done, 1 some failed (listed at the end), 2 usage or "
                    "model error.")
    p.add_argument("paths", nargs="+", type=Path, help="image files and folders (use -- before names that start with -)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--format", choices=FORMATS, default="json",
                   help="json: <name>.json per image (default); jsonl: one detections.jsonl, a line per image; "
                        "csv: one corners.csv, a row per corner (image,x,y,score)")
    p.add_argument("--overlay", action=argparse.BooleanOptionalAction, default=None,
                   help="also draw the corners into <name>.overlay.jpg (default: on for json, off for jsonl/csv)")
    p.add_argument("--include", action="append", default=[], metavar="GLOB",
                   help="take only files matching GLOB (repeatable; case-insensitive; matched against the file "
                        "name, or the path inside the folder if GLOB has a /). Default: known image suffixes")
    p.add_argument("--exclude", action="append", default=[], metavar="GLOB", help="skip files matching GLOB (repeatable)")
    p.add_argument("--workers", type=positive_int, default=None, metavar="N",
                   help="worker processes, each with its own detector (default: one per CPU, capped at 8; "
                        "1 runs in this process)")
    p.add_argument("--threads", type=positive_int, default=None, metavar="N",
                   help="inference threads per worker (default 1: workers, not threads, use the cores)")
    p.add_argument("--max-pixels", type=positive_int, default=None, metavar="N",
                   help=f"refuse larger images, checked from the file header before decoding (default {MAX_PIXELS_HELP})")
    p.add_argument("--force", action="store_true", help="redo images that already have a result")
    p.add_argument("--exhaustive", action="store_true",
                   help="search harder: where the full frame is scored, look at every cluster of responses no board "
                        "covers, stretched, not only the sliver-shaped ones (more time per cluttered frame)")
    p.add_argument("--model", default=None,
                   help=f"bundled model name or .onnx path ({DEFAULT_HELP})")
    p.add_argument("--coarse-model", default=None, help=COARSE_MODEL_HELP)
    p.add_argument("--quiet", action="store_true", help="no progress bar and no summary line; failures are still listed")
    p.set_defaults(func=run_detect)
    c = sub.add_parser(
        "calibrate", help="calibrate a camera from a folder of checkerboard photos",
        description="Detect the board in every image of DIR, calibrate the camera (OpenCV pinhole or fisheye, "
                    "outlier views rejected) and write calibration.json, calibration.yaml (OpenCV), corners.vnl "
                    "(mrcal), points.npz (object/image points), residuals.png and residuals/<image>.jpg into "
                    "--out. Exit status: 0 calibrated, 1 calibration failed, 2 usage or model error.")
    c.add_argument("dir", type=Path, help="folder of images (searched recursively)")
    c.add_argument("--board", type=board_size, required=True, metavar="COLSxROWS", help="inner corners, e.g. 9x6")
    c.add_argument("--square", type=float, required=True, help="square side, in the unit wanted for poses")
    c.add_argument("--model-type", choices=["pinhole", "fisheye"], default="pinhole", help="lens model (default pinhole)")
    c.add_argument("--model", default=None,
                   help=f"bundled detector model name or .onnx path ({DEFAULT_HELP})")
    c.add_argument("--coarse-model", default=None, help=COARSE_MODEL_HELP)
    c.add_argument("--threads", type=positive_int, default=None, metavar="N", help="inference threads")
    c.add_argument("--exhaustive", action="store_true", help="search harder for boards (see ccdn detect --help)")
    c.add_argument("--out", type=Path, required=True, help="output folder")
    c.add_argument("--partial", action="store_true",
                   help="also use boards with whole rows or columns undetected (their offset on the board is "
                        "unknown: harmless to the calibration, but corners.vnl numbers them from 0)")
    c.add_argument("--quiet", action="store_true", help="no progress bar")
    c.set_defaults(func=run_calibrate)
    return parser


def board_size(text: str) -> tuple[int, int]:
    """'9x6' -> (9, 6): inner corners, columns x rows."""
    cols, sep, rows = text.lower().partition("x")
    if not (sep and cols.isdigit() and rows.isdigit() and int(cols) >= 2 and int(rows) >= 2):
        raise argparse.ArgumentTypeError(f"expected COLSxROWS inner corners such as 9x6, got {text!r}")
    return int(cols), int(rows)


def run_calibrate(args: argparse.Namespace) -> int:
    """`ccdn calibrate`: detect boards in a folder, calibrate, write the files, print a report."""
    from tqdm import tqdm

    from .batch import collect_inputs
    from .calibration import CalibrationError, View, calibrate, report, write_outputs
    from .detector import Detector
    from .sizing import fitted_board

    try:
        detector = Detector(args.model, args.threads, coarse_model=args.coarse_model, exhaustive=args.exhaustive)
        items, failures = collect_inputs([args.dir], skip=args.out)
    except (OSError, ValueError) as exc:  # ModelError is a ValueError
        print(f"ccdn: {exc}", file=sys.stderr)
        return 2
    reasons = [f.reason for f in failures]
    views, missing, sizes, paths = [], [], set(), {}
    for item in tqdm(items, unit="img", disable=args.quiet or not sys.stderr.isatty(), file=sys.stderr):
        try:
            gray = detector.load(item.path)
            result = detector.detect(gray)
        except (OSError, ValueError) as exc:  # ImageError is a ValueError
            reasons.append(str(exc))
            continue
        # the detection's boards fitted to the size (ccdn.sizing), the largest first
        board = next(filter(None, (fitted_board(gray, b, args.board, args.partial) for b in result.boards)), None)
        sizes.add(result.image_size)
        paths[item.name] = item.path
        if board is not None:
            views.append(View.from_board(item.name, board))
        else:
            missing.append(item.name)
    for reason in reasons:
        print(f"ccdn: skipped: {reason}", file=sys.stderr)
    cols, rows = args.board
    print(f"ccdn: a {cols}x{rows} board found in {len(views)} of {len(items)} images", file=sys.stderr)
    if len(sizes) > 1:
        print(f"ccdn: the images differ in size ({', '.join(f'{w}x{h}' for w, h in sorted(sizes))})", file=sys.stderr)
        return 1
    try:
        calibration = calibrate(views, sizes.pop() if sizes else (0, 0), args.board, args.square, args.model_type)
    except CalibrationError as exc:
        print(f"ccdn: calibration failed: {exc}", file=sys.stderr)
        return 1
    try:
        write_outputs(args.out, calibration, views, missing, load=lambda name: detector.load(paths[name]))
    except (OSError, ValueError) as exc:
        print(f"ccdn: cannot write the results: {exc}", file=sys.stderr)
        return 1
    print(report(calibration))
    print(f"ccdn: results in {args.out}", file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
