"""The drone-side runtime: model contract, camera geometry, inference, fusion, MAVLink, streaming.

No torch here (ARCHITECTURE.md §2). Importing this package has no side effects.

    from edge_landing.runtime import OnnxModel
    model = OnnxModel.load("model.onnx", threads=2)
    pred = model.predict(rgb)          # rgb: uint8 H×W×3
    pred.depth_m, pred.hvo_prob
"""
from edge_landing.runtime.core.camera import Attitude, Intrinsics, Mount
from edge_landing.runtime.core.errors import (
    ContractError,
    EdgeError,
    InputError,
    SceneError,
)
from edge_landing.runtime.core.messages import Frame, Prediction, Target, VehicleState
from edge_landing.runtime.io.poses import Pose
from edge_landing.runtime.perception.contract import (
    DepthConvention,
    DepthSpec,
    HvoSpec,
    InputSpec,
    Layout,
    ModelContract,
    Task,
)
from edge_landing.runtime.perception.inference import OnnxModel, SessionConfig

__all__ = [
    "Attitude", "Intrinsics", "Mount", "DepthConvention", "DepthSpec", "HvoSpec", "InputSpec", "Layout",
    "ModelContract", "Task", "ContractError", "EdgeError", "InputError", "SceneError", "OnnxModel",
    "SessionConfig", "Frame", "Prediction", "Target", "VehicleState", "Pose",
]
__version__ = "0.1.0"
