"""Closed-loop landing check: autopilot -> vehicle pose -> sim-follow camera -> edge-run -> LANDING_TARGET -> autopilot.

Drives any MAVLink autopilot that does precision landing on LANDING_TARGET (ArduPilot, PX4 SITL, or the tests'
autopilot model): GUIDED, arm, take off, fly to a start point, LAND with precision landing; meanwhile
``edge-run --camera sim-follow`` renders the world from the vehicle's pose and sends targets. At touchdown
(the autopilot disarms) it reports the touchdown point, its distance to edge-run's last committed spot, whether the
world there is level and clear with the requested clearance and whether the path hit anything (ray casting), the
time to land, a top-down picture and a JSON report. Time is real time: edge-run uses the monotonic clock.

    # one landing against an autopilot already running (e.g. ArduPilot SITL + MAVProxy with three --out)
    python -m edge_landing.benchmarks.closed_loop --style urban --seed 3 --out /tmp/loop
    # the goal: 20 landings over unseen worlds with the tests' autopilot model (from a source checkout)
    python -m edge_landing.benchmarks.closed_loop --autopilot-model --runs 20 --seeds 200-219 --out /tmp/loop20

See docs/closed_loop.md for the ports and autopilot parameters.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import IO, Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

from edge_landing.benchmarks.closed_loop_config import MODEL_CMD, LoopConfig, edge_args, sitl_argv
from edge_landing.benchmarks.closed_loop_flight import Flight
from edge_landing.benchmarks.closed_loop_judge import (
    LandingResult,
    draw,
    judge,
    summarise,
    targets_safe_share,
    until_touchdown,
    write_json,
)
from edge_landing.benchmarks.closed_loop_log import last_committed, recently_committed, sent_targets
from edge_landing.cli.common import CliParser, output_folder, run_cli
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.io.mavlink_link import Autopilot

log = logging.getLogger("closed_loop")
def fly(cfg: LoopConfig, flight: Flight, has_target: Optional[Callable[[], bool]] = None) -> Tuple[float, float, float]:
    """Take off, fly to the start, survey passes there until ``has_target()`` (at most ``target_wait_s``), LAND;
    returns (take-off time, LAND time, touchdown time) on the local clock.

    ArduPilot: GUIDED, arm, MAV_CMD_NAV_TAKEOFF, position targets, LAND mode. PX4 (untested here): position
    targets streamed in OFFBOARD from the ground up, then MAV_CMD_NAV_LAND with precision landing required.
    """
    m = flight.mavutil.mavlink
    flight.wait("the autopilot's HEARTBEAT and LOCAL_POSITION_NED",
                lambda: flight.conn.target_system != 0 and flight.has_position(), cfg.startup_timeout_s)
    home = flight.position()
    yaw = math.radians(cfg.start_yaw_deg)
    above_home = np.array([home[0], home[1], -cfg.altitude_m])
    px4 = cfg.autopilot is Autopilot.PX4
    if px4:
        for _ in range(20):
            flight.goto(above_home, yaw)
            flight.pump(0.05)
    flight.set_mode("OFFBOARD" if px4 else "GUIDED")
    t_takeoff = time.monotonic()
    for _ in range(10):
        flight.command(m.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        deadline = time.monotonic() + 1.0
        while not flight.armed and time.monotonic() < deadline:
            flight.pump()
            if px4:
                flight.goto(above_home, yaw)
        if flight.armed:
            break
    flight.wait("arming", lambda: flight.armed, 1.0)
    if not px4:
        flight.command(m.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, cfg.altitude_m)

    def climbed() -> bool:
        if px4:
            flight.goto(above_home, yaw)
        return bool(-flight.position()[2] > cfg.altitude_m - 1.0)

    flight.wait(f"take-off to {cfg.altitude_m:.0f} m", climbed, 90.0)
    start = np.array([cfg.start_north_m, cfg.start_east_m, -cfg.altitude_m])

    def settled_at_start() -> bool:
        flight.goto(start, yaw)
        return bool(np.linalg.norm(flight.position() - start) < 1.5) and _speed(flight) < 0.3

    flight.wait("the flight to the start point", settled_at_start, 120.0)
    if has_target is not None:
        try:
            survey(cfg, flight, start, yaw, has_target)
        except InputError as exc:
            log.warning("%s; landing anyway", exc)
            flight.messages.append(f"LAND without a target: {exc}")
    t_land = time.monotonic()
    if px4:  # NAV_LAND param2 = 2: precision landing required
        flight.command(m.MAV_CMD_NAV_LAND, 0, 2, 0, math.nan, math.nan, math.nan, math.nan)
    else:
        flight.set_mode("LAND")
    flight.wait("touchdown (disarm)", lambda: not flight.armed, cfg.max_land_time_s + 60.0)
    return t_takeoff, t_land, time.monotonic()


def survey(cfg: LoopConfig, flight: Flight, start: np.ndarray, yaw_rad: float, has_target: Callable[[], bool]) -> None:
    """Fly passes across the heading through the start point until ``has_target()`` (edge-run has committed a
    geometry-confirmed spot), at most ``target_wait_s``; as a pilot would before LAND.

    Hovering gives motion geometry no baseline, so it confirms nothing (ARCHITECTURE.md §11); a sideways pass
    moves the camera across its line of sight, which is the largest parallax per metre flown for the ground
    ahead. Raises InputError when the time is up (the caller lands anyway and says so).
    """
    right = np.array([-math.sin(yaw_rad), math.cos(yaw_rad), 0.0])     # body right in local NED
    ends = [start + cfg.survey_m * right, start - cfg.survey_m * right]
    leg = [0]

    def pass_until_target() -> bool:
        end = ends[leg[0] % 2]
        if float(np.linalg.norm(flight.position()[:2] - end[:2])) < 2.0:
            leg[0] += 1
            end = ends[leg[0] % 2]
        flight.goto(end, yaw_rad)
        return has_target()

    flight.wait("a geometry-confirmed spot from edge-run during the survey passes", pass_until_target,
                cfg.target_wait_s)


def _speed(flight: Flight) -> float:
    if len(flight.path) < 5:
        return math.inf
    (t0, *p0), (t1, *p1) = flight.path[-5], flight.path[-1]
    return float(np.linalg.norm(np.subtract(p1, p0)) / max(t1 - t0, 1e-3))


def _start(cmd: List[str], log_file: IO[str]) -> subprocess.Popen[bytes]:
    return subprocess.Popen(cmd, stdout=log_file, stderr=subprocess.STDOUT, start_new_session=True)


def _stop(proc: Optional[subprocess.Popen[bytes]]) -> None:
    if proc is None or proc.poll() is not None:
        return
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def land_once(cfg: LoopConfig) -> LandingResult:
    """One closed-loop landing; writes report.json, path.csv, flight.png, targets.jsonl and logs under ``cfg.out``."""
    from edge_landing import sim
    from edge_landing.sim.follow import place_home

    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    world = sim.build_world(cfg.style, cfg.seed)
    home_world = place_home(world)
    result = LandingResult(cfg.style, cfg.seed, [round(float(v), 2) for v in
                                                 home_world + (cfg.start_north_m, cfg.start_east_m, -cfg.altitude_m)])
    sitl: Optional[subprocess.Popen[bytes]] = None
    edge: Optional[subprocess.Popen[bytes]] = None
    flight = Flight(cfg.url(0), cfg.autopilot)
    logs = contextlib.ExitStack()
    try:
        if cfg.sitl_cmd:
            sitl = _start(sitl_argv(cfg), logs.enter_context(open(out / "autopilot.log", "w")))
        on_gimbal = "" if cfg.gimbal == "none" else ":gimbal"
        read_gimbal = ["--gimbal", "mavlink"] if cfg.gimbal == "mavlink" else []
        edge = _start([sys.executable, "-m", "edge_landing.cli.run", "--camera",
                       f"sim-follow:{cfg.style}:{cfg.seed}{on_gimbal}@{cfg.url(2)}", "--mav", cfg.url(1), *read_gimbal,
                       "--autopilot", cfg.autopilot.value, "--log", str(out / "targets.jsonl"),
                       "--vehicle-radius", str(cfg.vehicle_radius_m), "--margin", str(cfg.margin_m),
                       "--hold", str(cfg.hold_s), "--threads", str(cfg.threads), *edge_args(cfg.edge_args)],
                      logs.enter_context(open(out / "edge-run.log", "w")))
        flight.heartbeat()
        running = edge

        def edge_ready() -> bool:
            decisions = out / "targets.jsonl"
            return running.poll() is not None or (decisions.is_file() and decisions.stat().st_size > 0)

        flight.wait("edge-run's first decision", edge_ready, cfg.startup_timeout_s)
        if edge.poll() is not None:
            raise InputError(f"closed loop: edge-run exited with {edge.returncode}; see {out / 'edge-run.log'}")
        t_takeoff, t_land, t_down = fly(cfg, flight, lambda: recently_committed(out / "targets.jsonl"))
        result.land_time_s, result.flight_time_s = t_down - t_land, t_down - t_takeoff
    except InputError as exc:
        result.notes.append(str(exc))
    finally:
        _stop(edge)
        _stop(sitl)
        flight.close()
        logs.close()
    targets_world = home_world + sent_targets(out / "targets.jsonl")
    result.targets_sent = len(targets_world)
    result.targets_safe_share = targets_safe_share(world, targets_world, cfg.clearance_m)
    committed = last_committed(out / "targets.jsonl")
    target_world = None if committed is None else home_world + committed
    result.notes += flight.messages[-20:]
    if flight.path:
        path_world = until_touchdown(world, home_world + np.array([p[1:] for p in flight.path]))
        times = [p[0] - flight.path[0][0] for p in flight.path[: len(path_world)]]
        np.savetxt(out / "path.csv", np.column_stack([times, path_world]),
                   delimiter=",", header="t_s,north_m,east_m,down_m (world NED)", fmt="%.3f")
        if result.notes and not math.isfinite(result.land_time_s):
            result.safe_why = "no touchdown: " + result.notes[0]
        else:
            judge(world, path_world, target_world, cfg.clearance_m, result)
        draw(world, path_world, target_world, home_world, result, cfg.clearance_m, str(out / "flight.png"))
    write_json(str(out / "report.json"), result.to_json())
    return result


def random_start(cfg: LoopConfig, rng: np.random.Generator) -> LoopConfig:
    """A start 30–60 m from home at a random bearing and heading whose straight path at altitude, and the survey
    passes across the heading, are clear of everything by 15 m."""
    from edge_landing import sim
    from edge_landing.sim.follow import place_home

    world = sim.build_world(cfg.style, cfg.seed)
    home = place_home(world)
    for _ in range(200):
        dist, bearing, yaw = rng.uniform(30, 60), rng.uniform(0, 2 * math.pi), rng.uniform(-180, 180)
        n, e = dist * math.cos(bearing), dist * math.sin(bearing)
        s = np.linspace(0, 1, 40)
        across = np.linspace(-cfg.survey_m, cfg.survey_m, 40)
        right = (-math.sin(math.radians(yaw)), math.cos(math.radians(yaw)))
        below = world.surface_z(home[0] + np.r_[n * s, n + right[0] * across],
                                home[1] + np.r_[e * s, e + right[1] * across])
        if np.min(below - (home[2] - cfg.altitude_m)) > 15.0:
            return replace(cfg, start_north_m=round(n, 1), start_east_m=round(e, 1), start_yaw_deg=round(yaw, 1))
    raise InputError(f"no clear start point at {cfg.altitude_m:.0f} m in the {cfg.style} world of seed {cfg.seed}")


def parse_seeds(text: str) -> List[int]:
    seeds: List[int] = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        if not a.strip().isdigit() or (b and not b.strip().isdigit()):
            raise InputError(f"--seeds '{text}': expected numbers and ranges like 100-109,120")
        if b and int(b) < int(a):
            raise InputError(f"--seeds '{text}': the range {part.strip()} is reversed (expected LOW-HIGH)")
        seeds += list(range(int(a), int(b) + 1)) if b else [int(a)]
    return seeds


def run_many(cfg: LoopConfig, runs: int, seeds: Sequence[int], out: IO[str] = sys.stdout) -> Dict[str, Any]:
    """``runs`` landings from random starts; styles alternate, seeds cycle; a summary JSON at the end."""
    results: List[LandingResult] = []
    for k in range(runs):
        style = ("suburban", "urban")[k % 2]
        seed = seeds[k % len(seeds)]
        run_cfg = random_start(replace(cfg, style=style, seed=seed, out=str(Path(cfg.out) / f"run{k:02d}_{style}_{seed}")),
                               np.random.default_rng([seed, k, 0xC105]))
        r = land_once(run_cfg)
        results.append(r)
        print(f"run {k}: {style} seed {seed}: {'OK' if r.ok(cfg.max_land_time_s) else 'FAIL'} touchdown "
              f"{r.touchdown_to_target_m:.2f} m from target, safe {r.safe} ({r.safe_why}), hit {r.hit}, "
              f"land {r.land_time_s:.0f} s", file=out, flush=True)
    summary = summarise(results, cfg.max_land_time_s)
    write_json(str(Path(cfg.out) / "summary.json"), {"summary": summary, "runs": [r.to_json() for r in results]})
    print(json.dumps(summary), file=out, flush=True)
    return summary


def _main(argv: Optional[Sequence[str]] = None) -> int:
    p = CliParser(prog="closed_loop", description=__doc__.split("\n\n")[0],
                  formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 1)[1])
    p.add_argument("--style", default="suburban")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="closed_loop_out", help="folder for the report, picture and logs")
    p.add_argument("--base-port", type=int, default=14560, help="driver, edge-run, camera listen on udpin "
                   "127.0.0.1 at this port, +1, +2 (default 14560)")
    p.add_argument("--autopilot", default="ardupilot", help="ardupilot or px4 (targets and modes)")
    p.add_argument("--sitl-cmd", default="", help="command started for each landing ({python} {style} {seed} "
                   "{port0} {port1} {port2} are filled in)")
    p.add_argument("--autopilot-model", action="store_true", help="start the tests' autopilot model (a test "
                   "double; needs a source checkout, run from its root)")
    p.add_argument("--altitude", type=float, default=50.0)
    p.add_argument("--start", type=float, nargs=3, default=(40.0, 0.0, 0.0), metavar=("NORTH", "EAST", "YAW_DEG"))
    p.add_argument("--vehicle-radius", type=float, default=1.0)
    p.add_argument("--margin", type=float, default=1.0)
    p.add_argument("--hold", type=float, default=20.0, help="edge-run --hold (s, default 20)")
    p.add_argument("--threads", type=int, default=1, help="edge-run --threads (default 1)")
    p.add_argument("--edge-args", default="", help="more edge-run flags, quoted")
    p.add_argument("--gimbal", default="none", help="none: camera fixed to the body; mavlink: on a stabilised "
                   "gimbal (45° below the horizon) the autopilot reports, read by edge-run; unread: on that gimbal, "
                   "edge-run not told (the autopilot model reports it; a SITL needs its own mount set up)")
    p.add_argument("--runs", type=int, default=0, help="N landings from random starts (styles alternate)")
    p.add_argument("--seeds", default="200-219", help="world seeds for --runs (default 200-219: no test uses them)")
    a = p.parse_args(argv)
    sitl_cmd = a.sitl_cmd
    if a.autopilot_model:
        if not Path("tests/autopilot_model.py").is_file():
            raise InputError("--autopilot-model needs a source checkout: run from the repository root "
                             "(tests/autopilot_model.py not found)")
        sitl_cmd = MODEL_CMD + (" --gimbal-pitch -45" if a.gimbal != "none" else "")
    if a.runs < 0:
        raise InputError(f"--runs must be >= 0 (0: one landing from --start), got {a.runs}")
    seeds = parse_seeds(a.seeds) if a.runs else []
    cfg = LoopConfig(a.style, a.seed, a.out, a.base_port, Autopilot.from_string(a.autopilot), sitl_cmd, a.altitude,
                     a.start[0], a.start[1], a.start[2], a.vehicle_radius, a.margin, hold_s=a.hold, threads=a.threads,
                     edge_args=a.edge_args, gimbal=a.gimbal)
    output_folder(cfg.out, "the --out folder")
    if a.runs:
        summary = run_many(cfg, a.runs, seeds)
        return 0 if summary["goal_met"] else 1
    r = land_once(cfg)
    print(json.dumps(r.to_json()))
    return 0 if r.ok(cfg.max_land_time_s) else 1


def main(argv: Optional[Sequence[str]] = None) -> int:
    return run_cli(_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
