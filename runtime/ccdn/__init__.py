"""ccdn: checkerboard corner detection with a small CNN (the CCDN paper) and a lean CPU runtime.

    import ccdn
    result = ccdn.detect("board.jpg")          # or ccdn.Detector(model="paper", threads=2).detect(img)
    result.xy, result.score                    # (N, 2) float32 (x, y), (N,) float32 in [0, 1]

Names are imported on first use, so `import ccdn` (and `ccdn --version`) stays cheap: onnxruntime
and OpenCV load only when a detector is built.
"""

from importlib import import_module

__version__ = "0.1.0"

_PUBLIC = {
    "Detector": "detector", "detect": "detector", "Detection": "result", "Board": "board",
    "ImageError": "image", "ModelError": "models", "available_models": "models",
}
__all__ = sorted(_PUBLIC) + ["__version__"]


def __getattr__(name: str):
    if name in _PUBLIC:
        value = getattr(import_module(f".{_PUBLIC[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'ccdn' has no attribute {name!r}")


def __dir__() -> list[str]:
    return __all__
