"""Image odometry for the motion stage (ARCHITECTURE.md §11): a frame without a telemetry position is placed by
the images' translation from the newest keyframe (fusion.image_motion), at the metric scale of a height above
ground carried through the chain. While a telemetry position is recent the frames stay in the telemetry's frame
(``anchored``); otherwise they are in an odometry frame of their own, numbered by ``epoch``.

Frames: local NED (the telemetry's, or the odometry frame's, whose origin is the frame it started with). Pure
numpy/OpenCV, no I/O; the state is a few numbers (the keyframes are the motion stage's).
"""
from __future__ import annotations

import math
from dataclasses import replace
from typing import NamedTuple, Optional

import numpy as np

from edge_landing.runtime.fusion.image_motion import ImagePose, carried_height_m, estimate_translation
from edge_landing.runtime.fusion.keyframes import Keyframe
from edge_landing.runtime.fusion.motion_config import POSE_TELEMETRY, MotionConfig
from edge_landing.runtime.fusion.parallax import CameraPose

__all__ = ["ImageOdometry"]


class _Refusal(NamedTuple):
    """A reported height refused since ``since_s``: longer or shorter than the carried one, and where the vehicle
    was then (north, east, m)."""

    since_s: float
    longer: bool
    at_ne_m: np.ndarray


class ImageOdometry:
    """Places frames that have no telemetry position; ``estimate`` is the last image-only estimate (None: none
    this frame)."""

    def __init__(self, config: MotionConfig, k_cv: np.ndarray):
        self.config = config
        self.k_cv = k_cv
        self.epoch = 0                       # + 1 each time the odometry starts a new frame
        self.anchored = False                # chained from a telemetry position less than history_s ago
        self.estimate: Optional[ImagePose] = None
        self._telemetry_s = -math.inf        # when the last frame with a telemetry position came
        self._delta: Optional[np.ndarray] = None          # the last chained translation (the next one's prior)
        self._velocity: Optional[tuple[np.ndarray, float]] = None   # of the last chained step (m/s, its 1-σ)
        self._refused: Optional[_Refusal] = None          # the reported height's refusal under way, if any

    def reset(self) -> None:
        self.anchored, self.estimate, self._telemetry_s = False, None, -math.inf
        self._delta, self._refused, self._velocity = None, None, None

    def telemetry_seen(self, time_s: float) -> None:
        """A frame came with a telemetry position: the next frames without one are chained from it."""
        self._telemetry_s, self.anchored = time_s, False

    def chain(self, grey: np.ndarray, pose: CameraPose, time_s: float, prev: Optional[Keyframe]
              ) -> tuple[CameraPose, Optional[str]]:
        """(``pose`` placed by its translation from ``prev``, the newest keyframe; None) or, when the chain cannot
        go on, (``pose`` at the origin of a new odometry frame, why: "" for a first frame). The caller drops its
        keyframes then: they are in the old frame.

        Chained from a telemetry position less than ``history_s`` ago, the frame stays in the telemetry's frame
        (a short dropout, or a flickering position, keeps its evidence). Past that the odometry's drift counts: a
        new odometry frame starts (``epoch`` + 1) where the chain is. The first frame, or the first after the
        chain broke (blank view, too few features, a height that stayed changed), starts one at the origin.
        """
        if prev is None:
            return self._start_over(pose), ""
        _, est = self.locate(grey, pose, prev, self._delta)
        if not est.ok:
            return self._start_over(pose), est.describe()
        height, why = self._carry_height(pose.agl_m, prev, est, time_s)
        if height is None:
            return self._start_over(pose), why
        if height != pose.agl_m:         # the pair at the carried height's scale
            est = self.estimate = est.rescaled(height / pose.agl_m)
        jump = self._implausible_step(est, time_s - prev.time_s)
        if jump:
            return self._start_over(pose), jump
        self._delta = est.delta_ned_m
        was = self.anchored or prev.source == POSE_TELEMETRY
        self.anchored = was and time_s - self._telemetry_s <= self.config.history_s
        if was and not self.anchored:
            self.epoch += 1
        return replace(pose, position_ned_m=prev.pose.position_ned_m + est.delta_ned_m, agl_m=height), None

    def locate(self, grey: np.ndarray, pose: CameraPose, ref: Keyframe, prior: Optional[np.ndarray] = None
               ) -> tuple[CameraPose, ImagePose]:
        """``pose`` placed at the keyframe's position + the images' translation, at the scale of ``pose.agl_m``
        (unchanged when the estimate fails)."""
        if prior is None and np.all(np.isfinite(pose.position_ned_m)):
            prior = pose.position_ned_m - ref.pose.position_ned_m
        est = estimate_translation(ref.grey, grey, self.k_cv, ref.pose.r_nc, pose.r_nc, pose.agl_m,
                                   self.config.image_pose, prior)
        self.estimate = est
        if not est.ok:
            return pose, est
        return replace(pose, position_ned_m=ref.pose.position_ned_m + est.delta_ned_m), est

    def _start_over(self, pose: CameraPose) -> CameraPose:
        self.anchored, self._delta, self._refused, self._velocity = False, None, None, None
        self.epoch += 1
        return replace(pose, position_ned_m=np.zeros(3))

    def _implausible_step(self, est: ImagePose, step_s: float) -> str:
        """Why the pair's translation is a step no multirotor flies after the previous one ('' when it is not):
        the velocity changes by more than ``max_accel_mps2`` × the interval + 3 σ of the two steps."""
        if not step_s > 0:
            return ""
        velocity, sigma = est.delta_ned_m / step_s, est.sigma_m / step_s
        last, self._velocity = self._velocity, (velocity, sigma)
        if last is None or not math.isfinite(sigma):
            return ""
        change = float(np.linalg.norm(velocity - last[0]))
        limit = self.config.image_pose.max_accel_mps2
        if change <= limit * step_s + 3.0 * math.hypot(sigma, last[1]):
            return ""
        return (f"the images' step changes the velocity by {change:.1f} m/s in {step_s:.2f} s, more than "
                f"{limit:g} m/s² (a plane other than the ground taken for it)")

    def _carry_height(self, agl_m: float, prev: Keyframe, est: ImagePose, time_s: float
                      ) -> tuple[Optional[float], str]:
        """(the height above ground that sets this frame's metric scale, ""), or (None, why) when the chain must
        start over.

        The images carry the previous frame's height over (image_motion.carried_height_m). A reported height
        within ``agl_gate_m`` + 3 σ of it is used (it follows the terrain). One shorter read something standing on
        the ground, a rangefinder over a tree or a car, whose error would scale every pair (10 % short puts a frame
        3 m off over a 30 m pair): the carried height is used instead until it has been refused for
        ``agl_refused_max_s`` and ``agl_refused_travel_m`` of flight; past both the ground's level itself changed,
        and the odometry starts over. One longer (nothing on the ground reads long) means the carried height was
        the one read off something: past ``agl_longer_max_s`` the odometry starts over at the reported height."""
        cfg = self.config.image_pose
        carried = carried_height_m(prev.scale_agl_m, est.delta_ned_m, agl_m)
        if not math.isfinite(carried) or abs(agl_m - carried) <= cfg.agl_gate_m + 3.0 * est.sigma_m:
            self._refused = None
            return agl_m, ""
        longer = agl_m > carried
        here_m = prev.pose.position_ned_m[:2] + est.delta_ned_m[:2] * (carried / agl_m)   # at the carried scale
        if self._refused is None or longer != self._refused.longer:
            self._refused = _Refusal(time_s, longer, here_m)
        refused_for_s = time_s - self._refused.since_s
        if longer and refused_for_s >= cfg.agl_longer_max_s:
            return None, (f"height above ground {agl_m:.1f} m, longer than the {carried:.1f} m carried by the images "
                          f"for {cfg.agl_longer_max_s:.2f} s: the carried height was read off something standing on "
                          "the ground")
        travel_m = float(np.hypot(*(here_m - self._refused.at_ne_m)))
        if not longer and refused_for_s > cfg.agl_refused_max_s and travel_m >= cfg.agl_refused_travel_m:
            return None, (f"height above ground {agl_m:.1f} m against {carried:.1f} m carried by the images for more "
                          f"than {cfg.agl_refused_max_s:.1f} s and {travel_m:.0f} m")
        return carried, ""
