"""Finding the bundled ONNX models by name (the runtime reads their metadata in session.py)."""

from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path

INT8_MODEL = "paper-int8"  # the default where the CPU has 8-bit dot products (default_model)
FLOAT_MODEL = "paper"  # the default elsewhere: the same network and figures in float32
COARSE_INT8_MODEL = "fast-int8"  # the default cascade's shrunk passes there (default_coarse_model)
COARSE_FLOAT_MODEL = "fast"  # ... and elsewhere
DEFAULT_HELP = "default: fast on shrunk frames, then paper (their int8 variants on CPUs with VNNI)"  # for --model help texts
COARSE_MODEL_HELP = ("the shrunk passes' model (bundled name or .onnx path), --model then serving the full frame only, "
                     "e.g. --model fine-int8 --coarse-model fast-int8 (default: --model itself, or the default cascade's)")
_INT8_DOT_FEATURES = ("AVX512VNNI", "AVX512_CLX", "AVX512_ICL", "AVX512_SPR")  # numpy's names for x86 VNNI
_INT8_DOT_FLAGS = ("avx512_vnni", "avx_vnni", "amx_int8")  # /proc/cpuinfo's, incl. AVX-VNNI, which numpy does not name


class ModelError(ValueError):
    """A model could not be found, or its metadata is missing or unknown to this runtime."""


def models_dir() -> Path:
    """The bundled models: inside the installed wheel, or the repository's models/ in a checkout
    (beside the package's files: importlib.resources would find the same directory for ~8 ms of imports)."""
    package = Path(__file__).resolve().parent
    packaged = package / "models"
    if packaged.is_dir():
        return packaged
    return package.parents[1] / "models"


def available_models() -> list[str]:
    """Names of the bundled models, sorted."""
    return sorted(p.stem for p in models_dir().glob("*.onnx"))


def default_model() -> str:
    """The bundled model used when none is named: INT8_MODEL on x86 CPUs with VNNI (8-bit dot
    products), where onnxruntime's integer kernels run the paper net in about half its float32
    network time (measured on an AVX-512 VNNI Xeon), FLOAT_MODEL elsewhere: without VNNI the int8
    graph is slower than float32 (AVX2-only AMD EPYC, 2 threads, 640x480: network 286 vs 216 ms);
    Intel CPUs with AVX2 but no VNNI, and ARM, are unmeasured and get float32, the safe choice. Both
    give the same detections within the quantisation's noise (models/paper-int8.md)."""
    return INT8_MODEL if _has_int8_dot_product() else FLOAT_MODEL


def default_coarse_model() -> str:
    """The bundled model of the default cascade's shrunk passes (ccdn.detector): COARSE_INT8_MODEL
    on x86 CPUs with VNNI (network 1.8 -> 1.1 ms on a halved 640x480 frame, 1.2 -> 0.7 ms on a
    2000x1500 frame shrunk 8x: AMD EPYC Zen 4, 2 threads; models/fast-int8.md), COARSE_FLOAT_MODEL
    elsewhere, for default_model's reason."""
    return COARSE_INT8_MODEL if _has_int8_dot_product() else COARSE_FLOAT_MODEL


@lru_cache(maxsize=1)
def _has_int8_dot_product() -> bool:
    """Whether the CPU has x86 VNNI: numpy's runtime CPU-feature table, or /proc/cpuinfo on Linux
    (cached: both default models ask)."""
    try:
        from numpy._core._multiarray_umath import __cpu_features__ as features  # numpy >= 2
    except ImportError:  # numpy 1.x
        from numpy.core._multiarray_umath import __cpu_features__ as features
    if any(features.get(name) for name in _INT8_DOT_FEATURES):
        return True
    try:
        flags = next((line.split(":", 1)[1].split() for line in Path("/proc/cpuinfo").read_text().splitlines()
                      if line.startswith("flags")), [])
    except OSError:  # not Linux
        return False
    return any(flag in flags for flag in _INT8_DOT_FLAGS)


def model_path(model: str | os.PathLike | None) -> Path:
    """A bundled model's name (None: default_model()) or a path to an .onnx file -> the file."""
    if model is None:
        model = default_model()
    path = Path(model)
    if path.suffix == ".onnx":
        if not path.is_file():
            raise ModelError(f"{path}: no such model file")
        return path
    path = models_dir() / f"{model}.onnx"
    if not path.is_file():
        raise ModelError(f"unknown model {str(model)!r}; bundled models: {', '.join(available_models()) or 'none'}")
    return path
