"""The streaming loop: source -> inference -> scale -> fusion -> trust -> link, with per-stage timings.

``Pipeline.run`` glues the stages (typed by runtime/pipeline/protocols.py), prints a status line every
second, logs every decision and returns a :class:`RunSummary`. Per-frame code never raises: a model fault,
a link fault or a camera fault becomes an invalid frame or a counted error, and the loop goes on.
The trust rules of ARCHITECTURE.md §12 are applied here: with a telemetry source, a frame without fresh
telemetry is not fused and gets no target (its reason says why); a committed spot is re-sent from memory
(runtime/pipeline/trust.py); telemetry is checked again right before sending. Between frames slower than
ArduPilot's estimator needs, the newest frame's sent target is re-sent at the newest pose
(runtime/pipeline/bridge.py).
"""
from __future__ import annotations

import json
import logging
import queue
import sys
import threading
import time
from dataclasses import dataclass, replace
from typing import Optional, TextIO, Tuple

import numpy as np

from edge_landing.runtime.core.camera import Mount
from edge_landing.runtime.core.messages import Frame, Prediction, Target, TelemetryMatch, VehicleState
from edge_landing.runtime.core.target_frames import aim_at_pose, aimed, target_ned
from edge_landing.runtime.fusion.result import FusionResult
from edge_landing.runtime.pipeline.bridge import DEFAULT_PERIOD_S, TargetBridge
from edge_landing.runtime.pipeline.mount_watch import MountWatch
from edge_landing.runtime.pipeline.protocols import (
    FrameSource,
    FrameWork,
    Fuse,
    Inference,
    Recorder,
    TargetSink,
    TelemetrySource,
)
from edge_landing.runtime.pipeline.records import decision_record, describe_target
from edge_landing.runtime.pipeline.stages import FrameCheck, ScaleStage, invalid
from edge_landing.runtime.pipeline.stats import RunSummary
from edge_landing.runtime.pipeline.trust import Continuity, ContinuityConfig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PipelineOptions:
    max_frames: int = 0          # 0 = no limit
    duration_s: float = 0.0      # 0 = no limit
    status_period_s: float = 1.0
    statustext: bool = True
    statustext_stable_frames: int = 3  # a found/lost change is announced once it held this many frames
    overlap: bool = True         # fuse/send frame N in a worker thread while frame N+1 is in inference
    world_grid: bool = True      # give fusion the vehicle position (grid kept in local NED across frames);
                                 # False: a fresh vehicle-centred grid per frame (the link still gets the position)
    continuity: ContinuityConfig = ContinuityConfig()
    fresh_s: float = 0.4         # telemetry older than this at send time holds the target back
    mount: Optional[Mount] = None  # the camera's: angles of targets re-expressed at a newer pose (kept without)
    fusion_max_hz: float = 0.0   # 0: fuse every frame. Else fuse a frame only when its capture time is at least
                                 # 1/fusion_max_hz after the last fused one's; the others are inferred but give
                                 # no target, so the model keeps the cores while targets still update at this
                                 # rate (§9). A file is read as fast as the loop goes, so which of its frames
                                 # are fused depends on the CPU: leave it 0 for reproducible replays
    bridge_s: float = DEFAULT_PERIOD_S  # with telemetry: when no target has left for this long, re-send the newest
                                        # frame's sent target at the newest pose (pipeline/bridge.py); 0 = off


class Pipeline:
    def __init__(self, grabber: FrameSource, inference: Inference, scale: ScaleStage, fuse: Fuse,
                 telemetry: Optional[TelemetrySource] = None, link: Optional[TargetSink] = None,
                 options: PipelineOptions = PipelineOptions(), decision_log: Optional[TextIO] = None,
                 recorder: Optional[Recorder] = None, out: Optional[TextIO] = None,
                 frame_check: Optional[FrameCheck] = None):
        self.grabber, self.inference, self.scale, self.fuse = grabber, inference, scale, fuse
        self.telemetry, self.link, self.options = telemetry, link, options
        self.decision_log, self.recorder, self.out = decision_log, recorder, out or sys.stdout
        self.frame_check = frame_check
        self.stop_event = threading.Event()
        self.summary = RunSummary(model_name=inference.name)
        self.continuity = Continuity(options.continuity, options.mount)
        self.last_target: Optional[Target] = None
        self._had_target: Optional[bool] = None
        self._candidate: Optional[bool] = None
        self._candidate_frames = 0
        self._telemetry_fresh: Optional[bool] = None
        self._telemetry_lost_s = 0.0
        self._queue: queue.Queue[Optional[FrameWork]] = queue.Queue(maxsize=1)
        self._worker: Optional[threading.Thread] = None
        self._last_fused_s: Optional[float] = None
        self._clock_lag_s = 0.0                 # the newest frame's Frame.clock_lag_s (its clock against ours)
        self.mount_watch = MountWatch(link.send_status if link is not None else None)
        self.bridge = TargetBridge(options.bridge_s)
        self._send_lock = threading.Lock()       # the fusion worker's sends and the bridge's, one at a time

    def stop(self, why: str = "request") -> None:
        self.summary.stopped_by = self.summary.stopped_by or why
        self.stop_event.set()

    def run(self) -> RunSummary:
        s, opt = self.summary, self.options
        start = time.monotonic()
        next_status, last_status = start + opt.status_period_s, start
        status_frames = 0
        wait_s = min(0.2, opt.bridge_s / 2) if self.bridge.enabled else 0.2
        if opt.overlap:
            self._worker = threading.Thread(target=self._work, name="fusion", daemon=True)
            self._worker.start()
        try:
            while not self.stop_event.is_set():
                t0 = time.perf_counter()
                frame = self.grabber.next(timeout_s=wait_s)
                now = time.monotonic()
                if frame is not None:
                    s.times.add("wait", time.perf_counter() - t0)
                    self._process(frame)
                    s.frames += 1
                    status_frames += 1
                self._bridge_gap()
                if now >= next_status:
                    self._status(status_frames / max(now - last_status, 1e-6))
                    status_frames, next_status, last_status = 0, now + opt.status_period_s, now
                if frame is None and self.grabber.ended:
                    s.stopped_by = s.stopped_by or "end of input"
                    break
                if opt.max_frames and s.frames >= opt.max_frames:
                    s.stopped_by = s.stopped_by or f"--max-frames {opt.max_frames}"
                    break
                if opt.duration_s and now - start >= opt.duration_s:
                    s.stopped_by = s.stopped_by or f"--duration {opt.duration_s:g}"
                    break
        finally:
            if self._worker is not None:
                self._queue.put(None)
                self._worker.join()
            s.wall_s = time.monotonic() - start
            s.drops = self.grabber.drops
            s.camera_faults = self.grabber.faults
            if self.link is not None:
                s.link = self.link.counters()
                s.autopilot_setup = self.link.setup_report()
            s.mount_line = self.mount_watch.line()
            if self.telemetry is not None:
                s.rejected_telemetry = self.telemetry.rejected()
                s.telemetry_rates_refused, s.telemetry_samples = self.telemetry.rates_refused(), self.telemetry.samples
        return s

    def _process(self, frame: Frame) -> None:
        """Frame check, inference and telemetry match here; scale, fusion, link, record and log in ``_finish``.

        The match comes after inference: telemetry measured around the capture time has had the model's time to
        arrive, so the attitude is interpolated between samples either side more often than held from the newest."""
        times = self.summary.times
        t0 = time.perf_counter()
        self._clock_lag_s = frame.clock_lag_s
        bad = self.frame_check.check(frame) if self.frame_check is not None else ("" if frame.valid else frame.reason)
        pred = invalid(frame, bad) if bad else self.inference.predict(frame)
        t1 = time.perf_counter()
        match = TelemetryMatch(None, "")
        if self.telemetry is not None:
            # Freshness is an age rule: judged on the frame's clock (Frame.clock_lag_s; 0 for a camera), so a
            # replayed telemetry log is as fresh as it was in flight however slowly the replay runs.
            match = self.telemetry.lookup(frame.capture_time_s, time.monotonic() - frame.clock_lag_s)
        times.add("inference", t1 - t0)
        times.add("telemetry", time.perf_counter() - t1)
        if not self._fusion_due(frame):
            self.summary.not_fused += 1
            return
        work = FrameWork(frame, match, pred, t0)
        if self._worker is None:
            self._finish(work)
        else:
            self._queue.put(work)  # waits while the worker still fuses the previous frame (back-pressure)

    def _fusion_due(self, frame: Frame) -> bool:
        """Whether this frame is fused under ``fusion_max_hz`` (always when it is 0)."""
        hz = self.options.fusion_max_hz
        last = self._last_fused_s
        # A small tolerance so a camera at exactly the cap's rate, with jitter, is not halved.
        if hz > 0 and last is not None and 0.0 <= frame.capture_time_s - last < 0.9 / hz:
            return False
        self._last_fused_s = frame.capture_time_s
        return True

    def _work(self) -> None:
        while (work := self._queue.get()) is not None:
            try:
                self._finish(work)
            except Exception:  # e.g. the decision log's disk is full: say so, keep flying
                log.exception("frame %d: output stage failed", work.frame.frame_id)

    def _fuse(self, work: FrameWork) -> Tuple[FusionResult, Prediction]:
        """Scale and fusion, unless telemetry is required and not fresh (then the grid is not touched at all).

        Returns the fusion result and the prediction with its metric scale applied."""
        frame, match = work.frame, work.telemetry
        if self.telemetry is not None and not match.fresh:
            return FusionResult(Target.none(frame.frame_id, frame.capture_time_s, f"held: {match.reason}")), work.pred
        state = match.state
        pred = self.scale.apply(work.pred, state)
        if work.pred.valid and not pred.valid:  # the scale rule held it back (no metric scale)
            return FusionResult(Target.none(frame.frame_id, frame.capture_time_s, f"held: {pred.reason}")), pred
        fusion_state = state
        if state is not None and not self.options.world_grid:
            fusion_state = replace(state, position_ned_m=None)
        try:
            # "now" on the frame's clock (a simulated flight's frames count their age from the hand-over)
            result = self.fuse(pred, fusion_state, time.monotonic() - frame.clock_lag_s, frame.rgb)
        except Exception as exc:  # a fusion bug must not stop the drone's loop: no target, and why
            log.exception("fusion failed on frame %d", frame.frame_id)
            result = FusionResult(Target.none(frame.frame_id, frame.capture_time_s, f"fusion fault: {exc}"))
        target = result.target
        if target.valid and target.position_ned_m is None and state is not None and state.position_ned_m is not None:
            target = replace(target, position_ned_m=target_ned(target, state))  # vehicle position + rotated body
        return replace(result, target=target), pred

    def _finish(self, work: FrameWork) -> None:
        frame, match = work.frame, work.telemetry
        s = self.summary
        t = time.perf_counter()

        def lap(stage: str) -> None:
            nonlocal t
            t1 = time.perf_counter()
            s.times.add(stage, t1 - t)
            t = t1

        result, pred = self._fuse(work)
        lap("fusion")
        self.mount_watch.update(result.mount)
        target, said = result.target, ""
        if self.telemetry is not None:
            target, said = self.continuity.step(target, match.state if match.fresh else None, result.grid,
                                                reached_fusion=work.pred.valid and match.fresh,
                                                placement=result.placement)
        sent, why = False, "no link"
        if self.link is not None:
            self._announce_telemetry(match)
            if said:
                self.link.send_status(said, severity=4)
            with self._send_lock:
                target = self._recheck(target, frame.clock_lag_s)
                target, pose_time_s = self._at_newest_pose(target, match.state)
                sent, why = self.link.send_target(target, match.state, clock_lag_s=frame.clock_lag_s,
                                                  stamp_s=pose_time_s)
                now = time.monotonic() - frame.clock_lag_s   # on the frame's clock (Frame.clock_lag_s)
                if sent:
                    s.times.add("capture_to_send", now - frame.capture_time_s)
                    s.times.add("pose_to_send", now - pose_time_s)
                if self.telemetry is not None:
                    self.bridge.decided(target, match.state, sent, now)
            self._statustext(target)
        s.targets += target.valid
        s.held += target.valid and target.reason.startswith("held")
        s.sent += sent
        lap("link")
        if self.recorder is not None:
            self.recorder.write(frame, work.pred, target, match.state, result.grid, result.geometry)
            lap("record")
        s.times.add("total", time.perf_counter() - work.started_s)
        self.last_target = target
        if self.decision_log is not None:
            spot = self.continuity.spot
            where = None if spot is None else spot.ned_m
            in_ned = self.continuity.in_telemetry_frame()
            record = decision_record(target, pred, match.state, sent, why, self.scale.source,
                                     level_assumed=self.telemetry is None,
                                     committed_ned_m=where if in_ned else None,
                                     committed_odometry_m=None if in_ned else where)
            self.decision_log.write(json.dumps(record) + "\n")

    def _bridge_gap(self) -> None:
        """Between frames: when no target has left for the bridge's period, re-send the newest frame's sent
        target at the newest pose, through the same checks as a frame's (fresh telemetry, the autopilot's frame
        unmoved, the link's age limit on its capture time). A refusal ends the bridge until the next frame."""
        if self.link is None or self.telemetry is None or not self.bridge.enabled:
            return
        with self._send_lock:
            lag = self._clock_lag_s
            now = time.monotonic() - lag                     # on the frames' clock (Frame.clock_lag_s)
            due = self.bridge.due(now)
            if due is None:
                return
            target, capture = due
            target = self._recheck(target, lag)
            target, pose_time_s = self._at_newest_pose(target, capture)
            sent, why = self.link.send_target(target, self.telemetry.newest_state(), clock_lag_s=lag,
                                              stamp_s=pose_time_s)
            if sent:
                self.bridge.resent_at(now)
                self.summary.bridged += 1
                self.summary.times.add("pose_to_send", now - pose_time_s)
            elif not why.startswith("rate cap"):
                self.bridge.clear()

    def _recheck(self, target: Target, clock_lag_s: float) -> Target:
        """Right before sending: telemetry must still be fresh (fusion took time since the match); judged on the
        frame's clock (Frame.clock_lag_s)."""
        if self.telemetry is None or not target.valid:
            return target
        age = time.monotonic() - clock_lag_s - self.telemetry.last_arrival_s()
        if age <= self.options.fresh_s:
            return target
        return Target.none(target.frame_id, target.capture_time_s,
                           f"held: telemetry stale at send time ({age:.2f} s old)", target.timings_s)

    def _at_newest_pose(self, target: Target, capture: Optional[VehicleState]) -> Tuple[Target, float]:
        """The target's body vector re-expressed from its local NED position at the newest telemetry, and the
        time of the pose it is expressed in (ARCHITECTURE.md §8, §12).

        ArduPilot rotates a BODY_FRD vector with its attitude of PLND_LAG ago (at most 0.25 s), whatever the
        capture time: a vector expressed at the capture pose is off by the vehicle's turn and travel over the
        capture-to-send latency beyond PLND_LAG. In the closed loop at 640×480 that latency was 0.44 s and the
        vehicle circled the spot, tilting back and forth, without ever descending (docs/closed_loop.md); at the
        newest pose the lag to set is the telemetry's age at send time. The spot itself is unchanged (it was
        placed with the pose at its capture); PX4's LOCAL_NED target is the same position either way. Range,
        angles and sizes follow the body vector (core/target_frames.aim_at_pose: the same rule as fusion's).
        """
        if self.telemetry is None or not target.valid or target.position_ned_m is None:
            return target, target.capture_time_s
        newest = self.telemetry.newest_state()
        if newest is not None and capture is not None and newest.position_epoch != capture.position_epoch:
            # The autopilot's frame moved between capture and send: the spot's NED point names another place.
            return Target.none(target.frame_id, target.capture_time_s, "held: the autopilot's frame moved (a "
                               "position or heading jump) since the frame was captured", target.timings_s), target.capture_time_s
        if newest is None or newest.position_ned_m is None or newest.time_s < target.capture_time_s:
            return target, target.capture_time_s
        aim = aim_at_pose(np.asarray(target.position_ned_m, np.float64), newest, target.clearance_m, self.options.mount)
        if aim is None:
            return target, target.capture_time_s
        return aimed(target, aim), newest.time_s

    def _announce_telemetry(self, match: TelemetryMatch) -> None:
        """STATUSTEXT and a log line when telemetry is lost or found (number first: a ground station that does not
        join STATUSTEXT chunks shows the first 50 characters on their own)."""
        if self.telemetry is None or self.link is None or match.fresh == self._telemetry_fresh:
            return
        now = time.monotonic()
        if match.fresh and self._telemetry_fresh is not None:
            gap = now - self._telemetry_lost_s
            log.info("telemetry is back after %.1f s; targets may be sent again", gap)
            self.link.send_status(f"{gap:.1f}s gap: edge telemetry back", severity=6)
        elif not match.fresh and self._telemetry_fresh:
            self._telemetry_lost_s = now
            log.warning("telemetry lost (%s): no targets are sent until it is back", match.reason)
            self.link.send_status(f"{self.summary.frames} frames: telemetry lost, no target ({match.reason})", severity=4)
        self._telemetry_fresh = match.fresh

    def _statustext(self, target: Target) -> None:
        """STATUSTEXT on found/lost, debounced so that a flickering target does not flood the ground station."""
        if not self.options.statustext or self.link is None:
            return
        if target.valid != self._candidate:
            self._candidate, self._candidate_frames = target.valid, 0
        self._candidate_frames += 1
        if self._candidate == self._had_target or self._candidate_frames < self.options.statustext_stable_frames:
            return
        if target.valid:
            self.link.send_status(f"{target.clearance_m:.1f}m clear: edge target found")
        elif self._had_target is not None:
            self.link.send_status(f"edge target lost: {target.reason}", severity=5)
        self._had_target = target.valid

    def _status(self, fps: float) -> None:
        s = self.summary
        parts = [f"fps {fps:5.1f}"]
        for stage in ("inference", "fusion", "total"):
            p50, p99 = s.times.percentiles_ms(stage, recent=True)
            parts.append(f"{stage} {p50:.0f}/{p99:.0f} ms")
        parts.append(f"drops {self.grabber.drops}")
        if self.telemetry is not None:
            age = time.monotonic() - self._clock_lag_s - self.telemetry.last_arrival_s()
            parts.append(f"telemetry {'ok' if age <= self.options.fresh_s else 'STALE'}")
        if self.link is not None:
            parts.append(f"link {'up' if self.link.up else 'DOWN'} sent {s.sent}")
        parts.append(describe_target(self.last_target))
        s.times.clear_recent()
        print(" | ".join(parts), file=self.out, flush=True)
