"""Batch detection of files and folders: parallel, resumable, and not stopped by bad input.

- Inputs: files as given, folders searched recursively (hidden files and folders skipped, the output
  folder skipped, symlinked folders not followed), sorted by name: the output order is the input
  order whatever the number of workers, and the results are those of a serial run.
- Workers: `workers=1` runs in this process; `workers=N>1` starts N processes. Each worker has a
  Detector of `threads` (default 1) intra-op threads, so N workers use N cores without
  oversubscription: for throughput, processes beat threads, since peaks, refinement and grid
  recovery run in Python on one core. `ccdn detect` defaults to one worker per available CPU
  (default_workers). Each worker holds one decoded image at a time.
- Resume: an image whose result is already recorded (its JSON file, or its record in the JSON Lines
  or CSV log) is skipped unless `force`. Outputs are written in an order that makes the result the
  commit: overlay first, then the JSON file (atomically) or the log record (whole, flushed).
- Bad input: every per-image problem becomes an Outcome with a one-line reason and the batch goes
  on. A worker process that dies (a crashing decoder, the OOM killer) costs only the image it was
  working on: the images in flight are retried one at a time in a fresh worker.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import re
import signal
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from fnmatch import fnmatchcase
from pathlib import Path

import cv2

from .detector import Detector
from .image import DEFAULT_MAX_PIXELS, ImageError
from .session import available_cpus
from .writers import CsvLog, JsonlLog, ResultLog, remove_stale_temps, result_record, write_json, write_overlay

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm", ".pbm", ".jp2"}
FORMATS = ("json", "jsonl", "csv")
LOG_FILES = {"jsonl": "detections.jsonl", "csv": "corners.csv"}
OVERLAY_SUFFIX = ".overlay.jpg"


@dataclass(frozen=True)
class Item:
    """One input image: its path, and its name in the outputs (relative to its input folder, with /)."""

    path: Path
    name: str


@dataclass(frozen=True)
class Outcome:
    """What became of one image: its result record, or the one-line reason it failed."""

    item: Item
    record: dict | None = None
    reason: str | None = None

    @property
    def corners(self) -> int:
        return len(self.record["corners"]) if self.record else 0


@dataclass(frozen=True)
class WorkerDied:
    """In place of a result: the worker process died on this task."""

    reason: str


MAX_DEFAULT_WORKERS = 8


@dataclass(frozen=True)
class BatchOptions:
    """Settings of a batch run (see the module docstring and `ccdn detect --help`)."""

    out: Path
    format: str = "json"
    overlay: bool = True
    force: bool = False
    workers: int = 1
    threads: int | None = None
    model: str | os.PathLike | None = None
    max_pixels: int = DEFAULT_MAX_PIXELS
    exhaustive: bool = False  # Detector(exhaustive=True): more found, at more time per frame
    coarse_model: str | os.PathLike | None = None  # Detector(coarse_model=...): the shrunk passes' model

    def detector(self, **extra) -> Detector:
        """The Detector these options describe (one session thread by default), with `extra` settings
        of Detector's own: the batch's in-process detector and each worker's are built here alike."""
        return Detector(self.model, self.threads or 1, coarse_model=self.coarse_model, exhaustive=self.exhaustive,
                        max_pixels=self.max_pixels, **extra)


def default_workers() -> int:
    """One worker per CPU this process may run on, capped at MAX_DEFAULT_WORKERS."""
    return min(available_cpus(), MAX_DEFAULT_WORKERS)


def one_line(text: str) -> str:
    """`text` with control characters (newlines in file names, say) escaped: one line, always."""
    return re.sub(r"[\x00-\x1f\x7f]", lambda m: repr(m.group())[1:-1], text)


def collect_inputs(paths: Sequence[Path], include: Sequence[str] = (), exclude: Sequence[str] = (),
                   skip: Path | None = None) -> tuple[list[Item], list[Outcome]]:
    """Items for the files given and the images under the folders given, and the failures met.

    With one folder, names are relative to it; with several paths, each folder's name is kept as a
    prefix. Patterns (case-insensitive globs, `*` also matches `/`) are matched against the file
    name, or against the path relative to the folder when they contain a `/`; without `include`,
    files with a known image suffix are taken. Files given by name are always taken; missing ones
    fail when processed. Two inputs with the same output name: the second one fails.
    """
    items: list[Item] = []
    failures: list[Outcome] = []

    def unreadable(exc: OSError) -> None:
        reason = f"{exc.filename}: cannot list folder ({exc.strerror})"
        failures.append(Outcome(Item(Path(exc.filename), ""), reason=one_line(reason)))

    skip_real = os.path.realpath(skip) if skip is not None else None
    for root in paths:
        if not root.is_dir():
            items.append(Item(root, root.name or str(root)))
            continue
        prefix = (os.path.basename(os.path.realpath(root)) or "root") + "/" if len(paths) > 1 else ""
        found = []
        for folder, dirs, files in os.walk(root, onerror=unreadable):
            dirs[:] = [d for d in dirs if not d.startswith(".") and os.path.realpath(os.path.join(folder, d)) != skip_real]
            for name in files:
                rel = Path(folder, name).relative_to(root).as_posix()
                if not name.startswith(".") and _selected(rel, include, exclude):
                    found.append(Item(Path(folder, name), prefix + rel))
        items += sorted(found, key=lambda item: item.name)
    unique: dict[str, Item] = {}
    for item in items:
        if item.name in unique:
            failures.append(Outcome(item, reason=one_line(f"{item.path}: same output name {item.name!r} as {unique[item.name].path}")))
        else:
            unique[item.name] = item
    return list(unique.values()), failures


def _selected(rel: str, include: Sequence[str], exclude: Sequence[str]) -> bool:
    def match(pattern: str) -> bool:
        subject = rel if "/" in pattern else rel.rsplit("/", 1)[-1]
        return fnmatchcase(subject.lower(), pattern.lower())

    taken = any(map(match, include)) if include else Path(rel).suffix.lower() in IMAGE_SUFFIXES
    return taken and not any(map(match, exclude))


class Batch:
    """One batch run into one output folder: plan() what is left to do, then run() it.

    Raises ModelError (model missing or unknown), OSError (output folder unusable) and ValueError
    (an existing results file that is not ccdn's, or bad options) up front, before any image.
    """

    def __init__(self, options: BatchOptions) -> None:
        if options.format not in FORMATS:
            raise ValueError(f"unknown format {options.format!r}; choose from {', '.join(FORMATS)}")
        if options.workers < 1:
            raise ValueError(f"workers must be at least 1, got {options.workers}")
        self.options = options
        in_process = options.workers == 1
        # The model is loaded here even for worker processes, so that a bad model fails up front.
        detector = options.detector()
        self._detector = detector if in_process else None
        options.out.mkdir(parents=True, exist_ok=True)
        self.log_name = LOG_FILES.get(options.format)  # None: one JSON file per image
        self._log: ResultLog | None = None
        if options.format == "jsonl":
            self._log = JsonlLog(options.out / LOG_FILES["jsonl"])
        elif options.format == "csv":
            self._log = CsvLog(options.out / LOG_FILES["csv"])

    def json_path(self, item: Item) -> Path:
        return self.options.out / (item.name + ".json")

    def overlay_path(self, item: Item) -> Path:
        return self.options.out / (item.name + OVERLAY_SUFFIX)

    def plan(self, items: Sequence[Item]) -> tuple[list[Item], int]:
        """(items still to do, number skipped as already done); repairs what a killed run left."""
        remove_stale_temps(self.options.out)
        if self._log is not None:
            finished = self._log.recover(redo={item.name for item in items} if self.options.force else set())
            todo = [item for item in items if item.name not in finished]
        elif self.options.force:
            todo = list(items)
        else:
            todo = [item for item in items if not self.json_path(item).exists()]
        return todo, len(items) - len(todo)

    def run(self, todo: Sequence[Item]) -> Iterator[Outcome]:
        """Detect `todo` and record each result; yields one Outcome per item, in input order."""
        o = self.options
        tasks = [(item, self.overlay_path(item) if o.overlay else None) for item in todo]
        pool = None
        if self._detector is None:
            pool = ordered_map(_work, tasks, min(o.workers, max(len(tasks), 1)), _init_worker,
                               (o, os.getpid()))
        outcomes: Iterator[Outcome | WorkerDied] = pool or map(_Worker(self._detector), tasks)
        try:
            for (item, _), outcome in zip(tasks, outcomes):
                if isinstance(outcome, WorkerDied):
                    outcome = Outcome(item, reason=one_line(f"{item.path}: {outcome.reason}"))
                yield self._record(outcome)
        finally:  # also when the caller stops early (Ctrl-C): stop the workers, close the log
            if pool is not None:
                pool.close()
            if self._log is not None:
                self._log.close()

    def _record(self, outcome: Outcome) -> Outcome:
        if outcome.record is None:
            return outcome
        try:
            if self._log is not None:
                self._log.append(outcome.record)
            else:
                write_json(self.json_path(outcome.item), outcome.record)
        except OSError as exc:
            return Outcome(outcome.item, reason=one_line(f"{outcome.item.path}: cannot write the result ({exc})"))
        return outcome


class _Worker:
    """Load, detect and draw one image; every failure becomes a reason, never an exception."""

    def __init__(self, detector: Detector) -> None:
        self.detector = detector

    def __call__(self, task: tuple[Item, Path | None]) -> Outcome:
        item, overlay = task
        try:
            gray = self.detector.load(item.path)
            detection = self.detector.detect(gray)
            if overlay is not None:
                write_overlay(overlay, gray, detection)
            return Outcome(item, record=result_record(item.name, str(item.path), detection))
        except ImageError as exc:
            reason = str(exc)
        except MemoryError:
            reason = f"{item.path}: out of memory (lower --max-pixels or use fewer workers)"
        except OSError as exc:
            reason = f"{item.path}: cannot write the overlay ({exc})"
        except Exception as exc:  # a bug must cost one image, not the batch
            log.exception("unexpected error on %s", item.path)
            reason = f"{item.path}: unexpected {type(exc).__name__}: {exc}"
        return Outcome(item, reason=one_line(reason))


_worker: _Worker | None = None


def _init_worker(options: BatchOptions, parent: int) -> None:
    """Per-process set-up: one Detector (options.detector, not spinning), quiet OpenCV on one thread,
    Ctrl-C left to the parent.
    parent: the parent's pid, passed in: a parent killed while this worker was starting would
    already have left os.getppid() pointing at init."""
    global _worker
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    threading.Thread(target=_exit_with_parent, args=(parent,), daemon=True).start()
    cv2.setNumThreads(1)
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    _worker = _Worker(options.detector(spinning=False))


def _exit_with_parent(parent: int) -> None:
    """A killed parent leaves its workers blocked on their task queue forever: end them instead."""
    while os.getppid() == parent:
        time.sleep(0.5)
    os._exit(1)


def _work(task: tuple[Item, Path | None]) -> Outcome:
    assert _worker is not None, "worker used before _init_worker"
    return _worker(task)


def ordered_map(fn: Callable, tasks: Sequence, workers: int, initializer: Callable | None = None,
                initargs: tuple = (), window: int | None = None) -> Iterator[object]:
    """fn(task) for each task in `workers` spawned processes, yielded in task order.

    At most `window` (default 2 x workers) tasks are in flight, so results do not pile up. When a
    worker process dies, the tasks then in flight are retried one at a time in a fresh process; the
    one that kills it again yields a WorkerDied instead of a result, and the rest go on.
    """
    window = window or 2 * workers
    context = multiprocessing.get_context("spawn")  # no fork: the parent may hold onnxruntime threads

    def pool(n: int) -> ProcessPoolExecutor:
        return ProcessPoolExecutor(n, mp_context=context, initializer=initializer, initargs=initargs)

    executor = pool(workers)
    pending: deque[tuple[int, Future]] = deque()
    next_task = 0
    try:
        while next_task < len(tasks) or pending:
            try:
                while next_task < len(tasks) and len(pending) < window:
                    pending.append((next_task, executor.submit(fn, tasks[next_task])))  # raises once broken
                    next_task += 1
                result = pending[0][1].result()
            except BrokenProcessPool:
                executor.shutdown(wait=True, cancel_futures=True)
                suspects = [tasks[i] for i, _ in pending]
                pending.clear()
                yield from _isolate(fn, suspects, pool)
                executor = pool(workers)
                continue
            pending.popleft()
            yield result
    finally:
        executor.shutdown(wait=False, cancel_futures=True)


def _isolate(fn: Callable, tasks: Sequence, pool: Callable[[int], ProcessPoolExecutor]) -> Iterator[object]:
    """Run `tasks` one by one in a single-process pool, replacing the pool after each crash."""
    executor = pool(1)
    try:
        for task in tasks:
            try:
                yield executor.submit(fn, task).result()
            except BrokenProcessPool:
                yield WorkerDied("worker process died on this image (a crash in a decoder, or out of memory)")
                executor.shutdown(wait=True)
                executor = pool(1)
    finally:
        executor.shutdown(wait=False, cancel_futures=True)
