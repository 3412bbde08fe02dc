"""One closed-loop landing's configuration (benchmarks.closed_loop), checked before any process starts: the world,
the start point, the autopilot and how it is started, and the edge-run flags the landing runs with."""
from __future__ import annotations

import shlex
import shutil
import sys
from dataclasses import dataclass
from typing import List

from edge_landing.cli.common import check_choice, check_number, check_seed, check_threads
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.io.mavlink_link import Autopilot

__all__ = ["GIMBAL_CHOICES", "MAX_START_M", "MODEL_CMD", "LoopConfig", "edge_args", "sitl_argv"]

# The tests' autopilot model (tests/autopilot_model.py, a documented test double), started per landing.
MODEL_CMD = ("{python} -m tests.autopilot_model --style {style} --seed {seed} --out udpout:127.0.0.1:{port0} "
             "--out udpout:127.0.0.1:{port1} --out udpout:127.0.0.1:{port2}")


MAX_START_M = 1000.0
GIMBAL_CHOICES = ("none", "mavlink", "unread")


def edge_args(text: str) -> List[str]:
    """``--edge-args`` split as a shell would, or one InputError naming it."""
    try:
        return shlex.split(text)
    except ValueError as exc:
        raise InputError(f"--edge-args {text!r}: {exc}") from None


def sitl_argv(cfg: LoopConfig) -> List[str]:
    """``--sitl-cmd`` with its placeholders filled in, split, its program found; or one InputError naming it."""
    ports = dict(port0=cfg.base_port, port1=cfg.base_port + 1, port2=cfg.base_port + 2)
    try:
        cmd = cfg.sitl_cmd.format(python=shlex.quote(sys.executable), style=cfg.style, seed=cfg.seed, **ports)
    except (KeyError, IndexError, ValueError) as exc:
        raise InputError(f"--sitl-cmd {cfg.sitl_cmd!r}: bad placeholder {exc} (known: {{python}} {{style}} {{seed}} "
                         f"{{port0}} {{port1}} {{port2}})") from None
    try:
        argv = shlex.split(cmd)
    except ValueError as exc:
        raise InputError(f"--sitl-cmd {cfg.sitl_cmd!r}: {exc}") from None
    if not argv:
        raise InputError("--sitl-cmd is empty")
    if shutil.which(argv[0]) is None:
        raise InputError(f"--sitl-cmd: program {argv[0]} not found or not executable")
    return argv


@dataclass(frozen=True)
class LoopConfig:
    """One closed-loop landing (lengths in metres, angles in degrees as typed, times in seconds)."""

    style: str = "suburban"
    seed: int = 0
    out: str = "closed_loop_out"
    base_port: int = 14560          # driver, edge-run and camera listen on base, base+1, base+2 (udpin)
    autopilot: Autopilot = Autopilot.ARDUPILOT
    sitl_cmd: str = ""              # started per landing; {python} {style} {seed} {port0} {port1} {port2}
    altitude_m: float = 50.0
    start_north_m: float = 40.0     # start point, local NED from home
    start_east_m: float = 0.0
    start_yaw_deg: float = 0.0
    vehicle_radius_m: float = 1.0
    margin_m: float = 1.0
    max_land_time_s: float = 180.0
    # At the start point the driver flies survey passes across the heading (the camera gets baseline across
    # its line of sight: motion geometry confirms nothing while hovering, ARCHITECTURE.md §11) until edge-run
    # has committed a geometry-confirmed spot, at most target_wait_s; then LAND.
    survey_m: float = 20.0          # passes run this far either side of the start point
    target_wait_s: float = 90.0
    startup_timeout_s: float = 90.0
    hold_s: float = 20.0            # edge-run --hold (its default; the clock stops while over the spot)
    threads: int = 1                # edge-run --threads (ONNX Runtime)
    edge_args: str = ""             # more edge-run flags, e.g. "--int8"
    # none: the camera is fixed to the body; mavlink: on a stabilised gimbal the autopilot reports and edge-run
    # reads (--gimbal mavlink); unread: on that gimbal, but edge-run assumes the fixed mount (a misconfiguration).
    gimbal: str = "none"

    def __post_init__(self) -> None:
        from edge_landing.sim.world import Style

        if not 5.0 <= self.altitude_m <= 120.0:
            raise InputError(f"--altitude must be in [5, 120] m, got {self.altitude_m}")
        if not 1024 <= self.base_port <= 65533:
            raise InputError(f"--base-port must be in [1024, 65533], got {self.base_port}")
        check_choice("--style", Style.from_string, self.style)
        check_seed("--seed", self.seed)
        # The start point is flown to and judged in the world around home: within 1 km is plenty.
        check_number("--start NORTH", self.start_north_m, -MAX_START_M, MAX_START_M, unit="metres")
        check_number("--start EAST", self.start_east_m, -MAX_START_M, MAX_START_M, unit="metres")
        check_number("--start YAW_DEG", self.start_yaw_deg, -360.0, 360.0, unit="degrees")
        # edge-run's own limits (cli/run.py), checked here before any process starts; an upper bound too, since
        # the judge casts rays over the clearance disc.
        check_number("--vehicle-radius", self.vehicle_radius_m, 0.0, 20.0, lo_open=True, unit="metres")
        check_number("--margin", self.margin_m, 0.0, 20.0, unit="metres")
        check_number("--hold", self.hold_s, 0.0, 3600.0, unit="seconds")
        check_threads("--threads", self.threads)
        edge_args(self.edge_args)
        if self.gimbal not in GIMBAL_CHOICES:
            raise InputError(f"--gimbal must be one of {', '.join(GIMBAL_CHOICES)}, got {self.gimbal!r}")
        if self.sitl_cmd:
            sitl_argv(self)

    @property
    def clearance_m(self) -> float:
        return self.vehicle_radius_m + self.margin_m

    def url(self, k: int) -> str:
        return f"udpin:127.0.0.1:{self.base_port + k}"
