"""ccdn: checkerboard corner detection with a small CNN (the CCDN paper) and a lean CPU runtime.

    import ccdn
    result = ccdn.detect("board.jpg")          # or ccdn.Detector(model="paper", threads=2).detect(img)
    result.xy, result.score                    # (N, 2) float32 (x, y), (N,) float32 in [0, 1]
"""

from .detector import Detector, detect
from .image import ImageError
from .models import ModelError, available_models
from .result import Detection

__version__ = "0.1.0"
__all__ = ["Detection", "Detector", "ImageError", "ModelError", "available_models", "detect", "__version__"]
