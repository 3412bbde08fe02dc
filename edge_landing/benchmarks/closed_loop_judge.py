"""Judging a closed-loop landing against the synthetic world (ray casting), and its top-down picture.

Frames: the world's own local NED (``sim.World``); the autopilot's local NED is the world's minus the
home offset of ``sim.follow.place_home``. A flight path is a list of (t_s, world NED) samples.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from edge_landing.benchmarks.landing_truth import TruthConfig, check_target

BODY_RADIUS_M = 0.5          # a small quad's arms: rays at this offset sweep the body along the path


@dataclass
class LandingResult:
    """What one closed-loop landing gave (lengths in metres, world NED; times in seconds)."""

    style: str
    seed: int
    start_world_ned_m: List[float]
    touchdown_world_ned_m: Optional[List[float]] = None
    target_world_ned_m: Optional[List[float]] = None
    touchdown_to_target_m: float = math.nan
    safe: bool = False
    safe_why: str = "no touchdown"
    hit: bool = False
    hit_why: str = ""
    land_time_s: float = math.nan        # LAND command to touchdown
    flight_time_s: float = math.nan      # take-off command to touchdown
    targets_sent: int = 0
    targets_safe_share: float = math.nan  # of the sent targets, the share on ground-truth safe ground
    notes: List[str] = field(default_factory=list)

    def ok(self, max_land_time_s: float) -> bool:
        return self.safe and not self.hit and self.land_time_s <= max_land_time_s

    def to_json(self) -> Dict[str, Any]:
        d = dict(self.__dict__)
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()}


def path_hits(world: Any, path_world: np.ndarray, radius_m: float = BODY_RADIUS_M) -> Tuple[bool, str]:
    """Does the body (centre and four points at ``radius_m``) sweep through a surface between samples?

    The segment that ends at touchdown ends on the surface: a hit counts only when it comes more than
    10 cm before the segment's end.
    """
    if len(path_world) < 2:
        return False, ""
    p0, p1 = path_world[:-1], path_world[1:]
    seg = p1 - p0
    length = np.linalg.norm(seg, axis=1)
    move = length > 1e-3
    p0, seg, length = p0[move], seg[move], length[move]
    offsets = [np.zeros(3)] + [radius_m * np.array([math.cos(a), math.sin(a), 0.0])
                               for a in np.arange(4) * math.pi / 2]
    for off in offsets:
        t, prim = world.intersect(p0 + off, seg / length[:, None])
        hit = (prim >= 0) & (t < length - 0.1)
        if hit.any():
            k = int(np.flatnonzero(hit)[0])
            where = np.round(p0[k] + off + seg[k] / length[k] * t[k], 1).tolist()
            return True, f"the body met a surface at world NED {where}"
    return False, ""


def until_touchdown(world: Any, path_world: np.ndarray, airborne_m: float = 1.0, contact_m: float = 0.05) -> np.ndarray:
    """The path up to its first contact with the world's surface after it was airborne.

    An autopilot's simulator (ArduPilot or PX4 SITL) has its own flat ground at home height; the world's
    terrain and roofs differ from it, so the touchdown in the world is where the path first meets its surface.
    """
    agl = world.surface_z(path_world[:, 0], path_world[:, 1]) - path_world[:, 2]
    up = np.flatnonzero(agl > airborne_m)
    if len(up) == 0:
        return path_world
    down = np.flatnonzero(agl[up[0]:] <= contact_m)
    return path_world if len(down) == 0 else path_world[: up[0] + int(down[0]) + 1]


def judge(world: Any, path_world: np.ndarray, target_world: Optional[np.ndarray], clearance_m: float,
          result: LandingResult) -> LandingResult:
    """Fill the touchdown verdicts of ``result`` from the flown path and the last committed target."""
    touchdown = path_world[-1]
    result.touchdown_world_ned_m = [round(float(v), 3) for v in touchdown]
    ok, why = check_target(world, float(touchdown[0]), float(touchdown[1]), TruthConfig(log="", clearance_m=clearance_m))
    result.safe, result.safe_why = bool(ok), why
    result.hit, result.hit_why = path_hits(world, path_world)
    if target_world is not None:
        result.target_world_ned_m = [round(float(v), 3) for v in target_world]
        result.touchdown_to_target_m = float(np.linalg.norm(touchdown[:2] - target_world[:2]))
    return result


def targets_safe_share(world: Any, targets_world: np.ndarray, clearance_m: float) -> float:
    """Share of sent targets (N×3 world NED) on level, clear ground with the clearance: were the targets
    themselves safe, whatever the autopilot made of them?"""
    if len(targets_world) == 0:
        return math.nan
    cfg = TruthConfig(log="", clearance_m=clearance_m)
    return float(np.mean([check_target(world, float(n), float(e), cfg)[0] for n, e in targets_world[:, :2]]))


def draw(world: Any, path_world: np.ndarray, target_world: Optional[np.ndarray], home_world: np.ndarray,
         result: LandingResult, clearance_m: float, png: str) -> None:
    """Top-down map: surface height (ray cast), flight path, home, committed target and touchdown."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.patches
    import matplotlib.pyplot as plt

    pts = np.vstack([path_world[:, :2], home_world[None, :2]] +
                    ([target_world[None, :2]] if target_world is not None else []))
    lo, hi = pts.min(axis=0) - 20.0, pts.max(axis=0) + 20.0
    side = float(max(hi - lo))
    centre = (lo + hi) / 2
    n = np.linspace(centre[0] - side / 2, centre[0] + side / 2, 300)
    e = np.linspace(centre[1] - side / 2, centre[1] + side / 2, 300)
    nn, ee = np.meshgrid(n, e, indexing="ij")
    height = -(world.surface_z(nn.ravel(), ee.ravel()) - world.terrain.z_at(nn.ravel(), ee.ravel())).reshape(nn.shape)
    fig, ax = plt.subplots(figsize=(7, 7), dpi=110)
    im = ax.imshow(height, origin="lower", extent=(e[0], e[-1], n[0], n[-1]), cmap="gray_r", vmin=0, vmax=20)
    fig.colorbar(im, ax=ax, shrink=0.7, label="height above terrain (m)")
    ax.plot(path_world[:, 1], path_world[:, 0], "-", color="tab:blue", lw=1.5, label="flight path")
    ax.plot(*home_world[[1, 0]], "s", color="tab:green", ms=8, label="home (take-off)")
    ax.plot(path_world[-1, 1], path_world[-1, 0], "o", mfc="none", mec="tab:red", ms=12, mew=2, label="touchdown")
    if target_world is not None:
        ax.plot(*target_world[[1, 0]], "x", color="tab:orange", ms=12, mew=2.5, label="last committed target")
        ax.add_patch(matplotlib.patches.Circle((target_world[1], target_world[0]), clearance_m, fill=False, color="tab:orange",
                                ls="--", label=f"clearance {clearance_m:.1f} m"))
    ax.set_xlabel("east (m, world)")
    ax.set_ylabel("north (m, world)")
    verdict = "safe" if result.safe else f"NOT safe ({result.safe_why})"
    ax.set_title(f"{result.style} seed {result.seed}: touchdown {result.touchdown_to_target_m:.2f} m from target, "
                 f"{verdict}\n{'path hit: ' + result.hit_why if result.hit else 'path clear'}, "
                 f"landed {result.land_time_s:.0f} s after LAND", fontsize=9)
    ax.legend(loc="upper right", fontsize=8)
    ax.set_aspect("equal")
    fig.tight_layout()
    fig.savefig(png)
    plt.close(fig)


def summarise(results: Sequence[LandingResult], max_land_time_s: float) -> Dict[str, Any]:
    """The goal's figures over many landings, and whether the goal holds: >= 95 % on safe ground (19 of 20),
    none hit anything, median touchdown <= 0.5 m from the committed target, every landing within the time."""
    n = len(results)
    dist = [r.touchdown_to_target_m for r in results if math.isfinite(r.touchdown_to_target_m)]
    shares = [r.targets_safe_share for r in results if math.isfinite(r.targets_safe_share)]
    s: Dict[str, Any] = {
        "landings": n, "touched_down": sum(r.touchdown_world_ned_m is not None for r in results),
        "safe": sum(r.safe for r in results), "hit": sum(r.hit for r in results),
        "within_time": sum(r.land_time_s <= max_land_time_s for r in results),
        "median_touchdown_to_target_m": float(np.median(dist)) if dist else None,
        "max_touchdown_to_target_m": float(np.max(dist)) if dist else None,
        "median_land_time_s": float(np.median([r.land_time_s for r in results])) if results else None,
        "sent_targets_safe_share_median": float(np.median(shares)) if shares else None}
    s["goal_met"] = bool(n and s["safe"] >= math.ceil(0.95 * n) and s["hit"] == 0 and s["within_time"] == n
                         and len(dist) == n and s["median_touchdown_to_target_m"] <= 0.5)
    return s


def write_json(path: str, data: Dict[str, Any]) -> None:
    with open(path, "w") as f:
        json.dump(data, f, indent=1)
