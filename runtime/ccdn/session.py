"""One onnxruntime CPU session per Detector: explicit threads, metadata checked, scores out."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort

from .models import ModelError, model_path

KNOWN_PREPROCESSING = {"gray_u8_div255"}
MAX_DEFAULT_THREADS = 4
STRIP_PIXELS = 1 << 20  # frames above this run in horizontal strips of about this many pixels, each
# with extra rows above and below beyond the network's receptive radius (metadata; 11 px for the
# paper net), so the stitched map equals the whole-frame map while the network's memory (some 20
# float32 maps per pixel) stays bounded for any frame size
DEFAULT_RECEPTIVE_RADIUS = 16  # for models whose metadata does not say
OPTIMIZATION_LEVELS = {"basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
                       "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
                       "all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL}


def available_cpus() -> int:
    """The CPUs this process may run on (physical cores are not visible portably)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def default_threads() -> int:
    """Intra-op threads by default: the available CPUs, capped."""
    return min(available_cpus(), MAX_DEFAULT_THREADS)


@dataclass(frozen=True)
class ModelInfo:
    """A loaded model's identity, from its ONNX metadata_props."""

    path: Path
    name: str
    version: str
    preprocessing: str
    metadata: dict[str, str]


def _load(path: Path, options: ort.SessionOptions, disabled_optimizers: list[str] | None = None) -> ort.InferenceSession:
    try:
        return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"],
                                    disabled_optimizers=disabled_optimizers)
    except Exception as exc:  # onnxruntime raises its own exception types for bad models
        raise ModelError(f"{path}: onnxruntime cannot load it ({exc})") from exc


def _metadata(path: Path) -> dict[str, str]:
    """The model's metadata_props, read by an unoptimised session (cheap for these small graphs)."""
    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    options.log_severity_level = 3
    return dict(_load(path, options).get_modelmeta().custom_metadata_map)


class ScoreSession:
    """Runs the network on a gray uint8 frame and returns its (H, W) float32 score map.

    Thread-safe: onnxruntime's InferenceSession.run may be called from several threads at once.
    """

    def __init__(self, model: str | os.PathLike | None = None, threads: int | None = None, spinning: bool = True) -> None:
        path = model_path(model)
        meta = _metadata(path)
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads or default_threads()
        options.inter_op_num_threads = 1
        options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        # ALL lays convs out in blocks of 16 channels and fuses QDQ pairs into integer kernels: the
        # int8 models ask for it; the paper net's 20-channel fp32 convs are slower there (measured)
        options.graph_optimization_level = OPTIMIZATION_LEVELS.get(meta.get("graph_optimization", ""),
                                                                   ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED)
        options.log_severity_level = 3
        if not spinning:
            options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        # workers spin between a run's nodes only, not after it: a detector runs two sessions (the shrunk
        # passes' and the full frame's), each with its own pool, and one's workers still spinning slowed
        # the other's runs on 2 cores (measured: stress renders that need the full-frame pass, mean 37-38
        # -> 30 ms, p90 94-95 -> 71-73; frames the shrunk pass serves, median within noise, best-of ~0.3 ms
        # more when they come back to back: its worker now sleeps between them)
        options.add_session_config_entry("session.force_spinning_stop", "1")
        # e.g. the int8 models keep their first pool in float32 and name the transformer that would undo it
        disabled = [name for name in meta.get("disabled_optimizers", "").split(",") if name]
        self._session = _load(path, options, disabled or None)
        preprocessing = meta.get("preprocessing")
        if preprocessing not in KNOWN_PREPROCESSING:
            raise ModelError(f"{path}: unknown preprocessing {preprocessing!r}; this runtime knows {sorted(KNOWN_PREPROCESSING)}")
        self.info = ModelInfo(path, meta.get("name", path.stem), meta.get("version", "unknown"), preprocessing, meta)
        self.threads = options.intra_op_num_threads
        self._input = self._session.get_inputs()[0].name
        self.multiple = int(meta.get("input_multiple", 1))  # H, W must be multiples of this
        radius = int(meta.get("receptive_radius", DEFAULT_RECEPTIVE_RADIUS))
        self.halo = -(-(radius + 1) // self.multiple) * self.multiple

    def scores(self, gray: np.ndarray, strip_pixels: int = STRIP_PIXELS) -> np.ndarray:
        """(H, W) uint8 -> (H, W) float32 corner scores; big frames go in overlapping strips."""
        h, w = gray.shape
        rows = max(4 * self.halo, strip_pixels // max(w, 1)) // self.multiple * self.multiple
        if h <= rows + 2 * self.halo:
            return self._run(gray)
        out = np.empty((h, w), np.float32)
        for top in range(0, h, rows):
            bottom = min(top + rows, h)
            a, b = max(top - self.halo, 0), min(bottom + self.halo, h)
            out[top:bottom] = self._run(gray[a:b])[top - a : bottom - a]
        return out

    def scores_in(self, gray: np.ndarray, boxes: list[tuple[int, int, int, int]]) -> np.ndarray:
        """(H, W) float32 scores computed only inside `boxes` (top, bottom, left, right), 0 elsewhere.

        Each box runs with its receptive halo around it, from an origin on the model's input
        multiple, so its scores equal the whole frame's."""
        h, w = gray.shape
        out = np.zeros((h, w), np.float32)
        for top, bottom, left, right in boxes:
            a = max(top - self.halo, 0) // self.multiple * self.multiple
            c = max(left - self.halo, 0) // self.multiple * self.multiple
            b, d = min(bottom + self.halo, h), min(right + self.halo, w)
            out[top:bottom, left:right] = self.scores(gray[a:b, c:d])[top - a : bottom - a, left - c : right - c]
        return out

    def _run(self, gray: np.ndarray) -> np.ndarray:
        """The network on one frame, padded (edge pixels repeated) to the model's input multiple."""
        h, w = gray.shape
        pad_h, pad_w = -h % self.multiple, -w % self.multiple
        x = np.pad(gray, ((0, pad_h), (0, pad_w)), mode="edge") if pad_h or pad_w else gray
        x = x.astype(np.float32)
        x *= 1.0 / 255.0
        return self._session.run(None, {self._input: x[None, None]})[0][0, 0, :h, :w]
