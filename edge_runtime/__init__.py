"""The drone-side runtime: model contract, camera geometry, inference, fusion, MAVLink, streaming.

No torch here (DESIGN.md §2). Importing this package has no side effects.

    from edge_runtime import OnnxModel
    model = OnnxModel.load("model.onnx", threads=2)
    pred = model.predict(rgb)          # rgb: uint8 H×W×3
    pred.depth_m, pred.hvo_prob
"""
from .camera import Attitude, Intrinsics, Mount
from .contract import DepthConvention, DepthSpec, HvoSpec, InputSpec, Layout, ModelContract, Task
from .errors import ContractError, EdgeError, InputError, SceneError
from .inference import OnnxModel, SessionConfig
from .messages import Frame, Prediction, Target, VehicleState
from .scene import Pose, Scene, SceneMeta, SceneWriter

__all__ = [
    "Attitude", "Intrinsics", "Mount", "DepthConvention", "DepthSpec", "HvoSpec", "InputSpec", "Layout",
    "ModelContract", "Task", "ContractError", "EdgeError", "InputError", "SceneError", "OnnxModel",
    "SessionConfig", "Frame", "Prediction", "Target", "VehicleState", "Pose", "Scene", "SceneMeta", "SceneWriter",
]
__version__ = "0.1.0"
