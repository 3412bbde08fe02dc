"""Models shipped inside the package (trained by us on our own synthetic scenes; see README).

``default_model_path()`` is what ``edge-run`` and ``edge-calibrate`` use when no model is given.
"""
from __future__ import annotations

from pathlib import Path

from edge_landing.runtime.core.errors import EdgeError

MODELS_DIR = Path(__file__).resolve().parent
DEFAULT_MODEL_NAME = "edgenet.onnx"
DEFAULT_INT8_MODEL_NAME = "edgenet.int8.onnx"


def default_model_path(int8: bool = False) -> Path:
    """Path of the shipped joint depth+HVO model (FP32, or INT8 when ``int8``)."""
    path = MODELS_DIR / (DEFAULT_INT8_MODEL_NAME if int8 else DEFAULT_MODEL_NAME)
    if not path.is_file():
        raise EdgeError(f"the shipped model {path} is missing from this installation; "
                        f"pass a model explicitly (--model FILE.onnx) or reinstall the package")
    return path
