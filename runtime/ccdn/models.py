"""Finding the bundled ONNX models by name (the runtime reads their metadata in session.py)."""

from __future__ import annotations

import os
from importlib import resources
from pathlib import Path

DEFAULT_MODEL = "paper-int8"  # the paper net quantised: same figures, ~1.6x faster end to end (models/paper-int8.md)


class ModelError(ValueError):
    """A model could not be found, or its metadata is missing or unknown to this runtime."""


def models_dir() -> Path:
    """The bundled models: inside the installed wheel, or the repository's models/ in a checkout."""
    packaged = Path(str(resources.files("ccdn"))) / "models"
    if packaged.is_dir():
        return packaged
    return Path(__file__).resolve().parents[2] / "models"


def available_models() -> list[str]:
    """Names of the bundled models, sorted."""
    return sorted(p.stem for p in models_dir().glob("*.onnx"))


def model_path(model: str | os.PathLike | None) -> Path:
    """A bundled model's name (None: DEFAULT_MODEL) or a path to an .onnx file -> the file."""
    if model is None:
        model = DEFAULT_MODEL
    path = Path(model)
    if path.suffix == ".onnx":
        if not path.is_file():
            raise ModelError(f"{path}: no such model file")
        return path
    path = models_dir() / f"{model}.onnx"
    if not path.is_file():
        raise ModelError(f"unknown model {str(model)!r}; bundled models: {', '.join(available_models()) or 'none'}")
    return path
