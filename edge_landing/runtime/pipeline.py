"""The streaming pipeline: source -> inference -> scale -> fusion -> link, with per-stage timings.

Each stage is a small object or callable; ``Pipeline.run`` glues them, prints a status line every second,
logs every decision, and returns a :class:`RunSummary`. Per-frame code never raises: a model fault, a link
fault or a camera fault becomes an invalid frame or a counted error, and the loop goes on.
"""
from __future__ import annotations

import json
import logging
import math
import queue
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Callable, Deque, Dict, List, Optional, Protocol, TextIO

import numpy as np

from edge_landing.runtime.core.errors import ContractError
from edge_landing.runtime.core.messages import Frame, Prediction, Target, VehicleState
from edge_landing.runtime.io.mavlink_link import target_ned
from edge_landing.runtime.perception.inference import OnnxModel

log = logging.getLogger(__name__)
FuseFn = Callable[[Prediction, Optional[VehicleState], float], Target]
STAGES = ("wait", "telemetry", "inference", "scale", "fusion", "link", "record", "total")


class Inference(Protocol):
    name: str

    def predict(self, frame: Frame) -> Prediction: ...


def _require_head(model: OnnxModel, head: str, role: str) -> None:
    """Fail at start-up, not on every frame: landing needs metric depth, and an HVO model needs its head."""
    task = model.contract.task
    if not (task.has_depth if head == "depth" else task.has_hvo):
        raise ContractError(f"{role} {model.path} has no {head} head (edge.task = {task.value}); edge-run needs "
                            f"a depth+hvo model, or --depth-model with a depth head and --hvo-model with an HVO head")


class JointInference:
    """One model with both heads (or a single head)."""

    def __init__(self, model: OnnxModel):
        _require_head(model, "depth", "the model")
        self.model = model
        self.name = model.path.name

    def predict(self, frame: Frame) -> Prediction:
        try:
            return self.model.predict(frame.rgb, frame.frame_id, frame.capture_time_s)
        except Exception as exc:  # a model fault marks the frame invalid; it never stops the loop
            return Prediction(frame.frame_id, frame.capture_time_s, None, None, False, f"model fault: {exc}")


class PairInference:
    """A depth model and an HVO model run one after the other; HVO is resampled to the depth grid."""

    def __init__(self, depth_model: OnnxModel, hvo_model: OnnxModel):
        _require_head(depth_model, "depth", "the depth model")
        _require_head(hvo_model, "hvo", "the HVO model")
        self.depth_model, self.hvo_model = depth_model, hvo_model
        self.name = f"{depth_model.path.name} + {hvo_model.path.name}"

    def predict(self, frame: Frame) -> Prediction:
        try:
            d = self.depth_model.predict(frame.rgb, frame.frame_id, frame.capture_time_s)
            h = self.hvo_model.predict(frame.rgb, frame.frame_id, frame.capture_time_s,
                                       out_hw=None if d.depth_m is None else d.depth_m.shape)
        except Exception as exc:
            return Prediction(frame.frame_id, frame.capture_time_s, None, None, False, f"model fault: {exc}")
        timings = {k: d.timings_s.get(k, 0.0) + h.timings_s.get(k, 0.0) for k in d.timings_s}
        return Prediction(frame.frame_id, frame.capture_time_s, d.depth_m, h.hvo_prob, d.valid and h.valid,
                          d.reason or h.reason, 1.0, timings)


class ScaleStage:
    """Metric scale: the in-flight altitude estimate when it is valid, else the scene calibration, else 1.

    ``estimator`` is an ``edge_runtime.scale.AltitudeScaleEstimator`` (or None); it needs the camera
    ``intrinsics`` and ``mount`` and a telemetry height above ground.
    """

    def __init__(self, calibration_scale: Optional[float] = None, estimator=None, intrinsics=None, mount=None):
        self.calibration_scale = calibration_scale
        self.estimator = estimator
        self.intrinsics, self.mount = intrinsics, mount
        self.source = "calibration" if calibration_scale else "none"
        self.last_reason = ""

    def apply(self, pred: Prediction, state: Optional[VehicleState]) -> Prediction:
        if not pred.valid or pred.depth_m is None:
            return pred
        scale, source = self.calibration_scale or 1.0, "calibration" if self.calibration_scale else "none"
        if self.estimator is not None and state is not None and state.agl_m is not None:
            h, w = pred.depth_m.shape
            est = self.estimator.update(pred.depth_m, pred.hvo_prob, self.intrinsics.scaled(w, h), self.mount,
                                        state.attitude, state.agl_m)
            self.last_reason = est.reason
            if est.valid and math.isfinite(est.scale) and est.scale > 0:
                scale, source = float(est.scale), f"altitude ({state.agl_source})"
        self.source = source
        if scale == 1.0:
            return pred
        return replace(pred, depth_m=pred.depth_m * np.float32(scale), scale=pred.scale * scale)


class StageTimes:
    """Durations (seconds) of every stage: all of them for the summary, the last second for the status line.

    Two threads add to it (inference in the main loop, fusion in the worker), so access is locked.
    """

    def __init__(self):
        self.all: Dict[str, List[float]] = {s: [] for s in STAGES}
        self.recent: Dict[str, Deque[float]] = {s: deque(maxlen=512) for s in STAGES}
        self._lock = threading.Lock()

    def add(self, stage: str, seconds: float) -> None:
        with self._lock:
            self.all.setdefault(stage, []).append(seconds)
            self.recent.setdefault(stage, deque(maxlen=512)).append(seconds)

    def percentiles_ms(self, stage: str, qs=(50, 99), recent: bool = False) -> List[float]:
        with self._lock:
            values = list(self.recent.get(stage, ())) if recent else list(self.all.get(stage, ()))
        if not values:
            return [float("nan")] * len(qs)
        return [float(v) * 1e3 for v in np.percentile(values, qs)]

    def clear_recent(self) -> None:
        with self._lock:
            for d in self.recent.values():
                d.clear()


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


@dataclass
class RunSummary:
    frames: int = 0
    targets: int = 0
    sent: int = 0
    wall_s: float = 0.0
    drops: int = 0
    camera_faults: int = 0
    link: Dict[str, int] = field(default_factory=dict)
    times: StageTimes = field(default_factory=StageTimes)
    model_name: str = ""
    stopped_by: str = ""

    @property
    def images_per_s(self) -> float:
        return self.frames / self.wall_s if self.wall_s > 0 else 0.0

    @property
    def model_images_per_s(self) -> float:
        t = self.times.all.get("inference", [])
        return len(t) / sum(t) if t and sum(t) > 0 else 0.0

    def _pacing_note(self) -> List[str]:
        """Say so when the source, not the CPU, set the pace (a live camera or the sim at its frame rate)."""
        wait, work = self.times.all.get("wait"), self.times.all.get("total")
        if not wait or not work or np.median(wait) <= np.median(work):
            return []
        return ["The source paced this run (the pipeline waited longer for frames than it worked on them), so "
                "pipeline images/s is the camera's rate; the ratio says how much CPU headroom is left.", ""]

    def table(self) -> str:
        """A Table 1-style report (images/s, 2 threads) plus per-stage latency."""
        rows = ["| model | frames | pipeline images/s | model-only images/s | ratio |", "|---|---|---|---|---|",
                f"| {self.model_name} | {self.frames} | {self.images_per_s:.2f} | {self.model_images_per_s:.2f} | "
                f"{self.images_per_s / self.model_images_per_s if self.model_images_per_s else 0:.0%} |", "",
                *self._pacing_note(),
                "| stage | p50 ms | p90 ms | p99 ms |", "|---|---|---|---|"]
        for stage in STAGES:
            if self.times.all.get(stage):
                p = self.times.percentiles_ms(stage, (50, 90, 99))
                rows.append(f"| {stage} | {p[0]:.1f} | {p[1]:.1f} | {p[2]:.1f} |")
        rows.append("")
        rows.append(f"targets {self.targets}/{self.frames} frames, LANDING_TARGET sent {self.sent}, drops {self.drops}, "
                    f"camera faults {self.camera_faults}, link {self.link}, stopped by {self.stopped_by or 'end'}")
        return "\n".join(rows)


class Pipeline:
    def __init__(self, grabber, inference: Inference, scale: ScaleStage, fuse: FuseFn, telemetry=None, link=None,
                 options: PipelineOptions = PipelineOptions(), decision_log: Optional[TextIO] = None,
                 recorder=None, out: Optional[TextIO] = None):
        self.grabber, self.inference, self.scale, self.fuse = grabber, inference, scale, fuse
        self.telemetry, self.link, self.options = telemetry, link, options
        self.decision_log, self.recorder, self.out = decision_log, recorder, out or sys.stdout
        self.stop_event = threading.Event()
        self.summary = RunSummary(model_name=inference.name)
        self.last_target: Optional[Target] = None
        self._had_target: Optional[bool] = None
        self._candidate: Optional[bool] = None
        self._candidate_frames = 0
        self._queue: queue.Queue = queue.Queue(maxsize=1)
        self._worker: Optional[threading.Thread] = None

    def stop(self, why: str = "request") -> None:
        self.summary.stopped_by = self.summary.stopped_by or why
        self.stop_event.set()

    def run(self) -> RunSummary:
        s, opt = self.summary, self.options
        start = time.monotonic()
        next_status, last_status = start + opt.status_period_s, start
        status_frames = 0
        if opt.overlap:
            self._worker = threading.Thread(target=self._work, name="fusion", daemon=True)
            self._worker.start()
        try:
            while not self.stop_event.is_set():
                t0 = time.perf_counter()
                frame = self.grabber.next(timeout_s=0.2)
                now = time.monotonic()
                if frame is not None:
                    s.times.add("wait", time.perf_counter() - t0)
                    self._process(frame)
                    s.frames += 1
                    status_frames += 1
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
                s.link = dict(self.link.counts)
        return s

    def _process(self, frame: Frame) -> None:
        """Telemetry match and inference here; scale, fusion, link, record and log in ``_finish``."""
        times = self.summary.times
        t0 = time.perf_counter()
        state = self.telemetry.state_at(frame.capture_time_s) if self.telemetry is not None else None
        t1 = time.perf_counter()
        pred = self.inference.predict(frame)
        times.add("telemetry", t1 - t0)
        times.add("inference", time.perf_counter() - t1)
        item = (frame, state, pred, t0)
        if self._worker is None:
            self._finish(item)
        else:
            self._queue.put(item)  # waits while the worker still fuses the previous frame (back-pressure)

    def _work(self) -> None:
        while (item := self._queue.get()) is not None:
            try:
                self._finish(item)
            except Exception:  # e.g. the decision log's disk is full: say so, keep flying
                log.exception("frame %d: output stage failed", item[0].frame_id)

    def _finish(self, item) -> None:
        frame, state, pred, t_start = item
        s = self.summary
        t = time.perf_counter()

        def lap(stage: str) -> None:
            nonlocal t
            t1 = time.perf_counter()
            s.times.add(stage, t1 - t)
            t = t1

        pred = self.scale.apply(pred, state)
        lap("scale")
        fusion_state = state
        if state is not None and not self.options.world_grid:
            fusion_state = replace(state, position_ned_m=None)
        try:
            target = self.fuse(pred, fusion_state, time.monotonic())
        except Exception as exc:  # a fusion bug must not stop the drone's loop: no target, and why
            log.exception("fusion failed on frame %d", frame.frame_id)
            target = Target.none(frame.frame_id, frame.capture_time_s, f"fusion fault: {exc}")
        if target.valid and target.position_ned_m is None and state is not None and state.position_ned_m is not None:
            target = replace(target, position_ned_m=target_ned(target, state))  # vehicle position + rotated body
        lap("fusion")
        sent, why = (False, "no link")
        if self.link is not None:
            sent, why = self.link.send_target(target, state)
            self._statustext(target)
        s.targets += target.valid
        s.sent += sent
        lap("link")
        if self.recorder is not None:
            self.recorder.write(frame, pred, target, state)
            lap("record")
        s.times.add("total", time.perf_counter() - t_start)
        self.last_target = target
        if self.decision_log is not None:
            self.decision_log.write(json.dumps(decision_record(target, pred, state, sent, why,
                                                               self.scale.source)) + "\n")

    def _statustext(self, target: Target) -> None:
        """STATUSTEXT on found/lost, debounced so that a flickering target does not flood the ground station."""
        if not self.options.statustext:
            return
        if target.valid != self._candidate:
            self._candidate, self._candidate_frames = target.valid, 0
        self._candidate_frames += 1
        if self._candidate == self._had_target or self._candidate_frames < self.options.statustext_stable_frames:
            return
        if target.valid:
            self.link.send_status(f"edge: landing target found, clear {target.clearance_m:.1f} m")
        elif self._had_target is not None:
            self.link.send_status(f"edge: target lost: {target.reason}"[:50], severity=5)
        self._had_target = target.valid

    def _status(self, fps: float) -> None:
        s = self.summary
        parts = [f"fps {fps:5.1f}"]
        for stage in ("inference", "fusion", "total"):
            p50, p99 = s.times.percentiles_ms(stage, recent=True)
            parts.append(f"{stage} {p50:.0f}/{p99:.0f} ms")
        parts.append(f"drops {self.grabber.drops}")
        if self.link is not None:
            parts.append(f"link {'up' if self.link.up else 'DOWN'} sent {s.sent}")
        parts.append(describe_target(self.last_target))
        s.times.clear_recent()
        print(" | ".join(parts), file=self.out, flush=True)


def describe_target(target: Optional[Target]) -> str:
    if target is None:
        return "target: none yet"
    if not target.valid:
        return f"target: none ({target.reason})"
    x, y, z = (float(v) for v in target.position_body_frd_m)
    return f"target FRD ({x:.1f}, {y:.1f}, {z:.1f}) m, range {target.range_m:.1f} m, clear {target.clearance_m:.1f} m"


def decision_record(target: Target, pred: Prediction, state: Optional[VehicleState], sent: bool, why: str,
                    scale_source: str) -> dict:
    def vec(v):
        return None if v is None else [round(float(x), 4) for x in v]

    return {"frame": target.frame_id, "capture_time_s": round(target.capture_time_s, 6), "valid": target.valid,
            "reason": target.reason or ("ok" if target.valid else pred.reason), "body_frd_m": vec(target.position_body_frd_m),
            "ned_m": vec(target.position_ned_m), "range_m": _num(target.range_m), "clearance_m": _num(target.clearance_m),
            "confidence": _num(target.confidence), "scale": _num(pred.scale), "scale_source": scale_source,
            "telemetry": state is not None, "agl_m": None if state is None else state.agl_m,
            "sent": sent, "not_sent_because": "" if sent else why}


def _num(v: float):
    return round(float(v), 4) if v is not None and math.isfinite(float(v)) else None
