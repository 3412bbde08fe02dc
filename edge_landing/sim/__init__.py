"""edge-sim: a synthetic AirSimNC-style bird's-eye-view benchmark generator (ARCHITECTURE.md §1, §3–4).

Procedural, seeded worlds (``suburban``: gabled/hipped houses, lawns, trees, roads, driveways, parked cars on
gentle terrain; ``urban``: flat-roofed blocks of many heights, streets, plazas, roof clutter) are ray cast
with Embree from a camera 45° down, 30–90 m above the surface below, giving per pixel planar z-depth (NaN
sky), camera-frame normals, HVO labels (thresholds in scene.json) and a shaded RGB image (sun and sky light,
cast shadows, textures; haze, rain, motion blur, noise and exposure vary with the seed). World frame is
local NED; the camera model is the runtime's own (``edge_landing.runtime.core.camera``).

Command line: ``edge-sim OUT --frames N --style suburban|urban --seed S [--flight] [--preview]``.

Python::

    import numpy as np
    from edge_landing import sim

    # a scene folder (the same files as the CLI writes)
    sim.generate(sim.SimConfig(out="scene", frames=20, style=sim.Style.URBAN, seed=3))

    # a live camera flying a landing approach (for edge-run --camera sim)
    cam = sim.SimCamera(style="suburban", seed=0, width=320, height=240, fps=10.0)
    rgb, pose, state = cam.read()        # uint8 H×W×3, runtime.io.poses.Pose, runtime.core.messages.VehicleState
    truth = cam.read_truth()             # SimFrame: .rgb, .pose, .state, .geometry.depth_m / .hvo / .normals
    cam.intrinsics, cam.mount            # what the runtime needs to back-project

    # one view, by hand
    world = sim.build_world("suburban", seed=0)
    renderer = sim.Renderer(world, sim.Intrinsics.from_hfov(320, 240))
    view = sim.random_view(world, np.random.default_rng(0))
    out = renderer.render(view.position_ned_m, view.attitude, sim.Effects(), np.random.default_rng(0))
    out.rgb, out.geometry.depth_m, out.geometry.hvo

Needs the ``sim`` extra (trimesh, embreex, tqdm): ``pip install 'edge-landing[sim]'``.
"""
from edge_landing.runtime.core.camera import Intrinsics

from .camera import SimCamera, SimFrame
from .effects import EffectOverrides, Effects, sample_effects
from .flight import Approach, VehicleSample, plan_flight, random_view
from .generate import SIM_VERSION, SimConfig, generate
from .render import Geometry, Renderer, Rendering
from .world import Material, Style, World, build_world

__version__ = SIM_VERSION
__all__ = [
    "SimCamera", "SimFrame", "EffectOverrides", "Effects", "sample_effects", "Approach", "VehicleSample",
    "plan_flight", "random_view", "SimConfig", "generate", "Geometry", "Renderer", "Rendering", "Material", "Style",
    "World", "build_world", "Intrinsics", "__version__",
]
