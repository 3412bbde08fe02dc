"""Bounded per-stage timing statistics and the run summary (ARCHITECTURE.md §9).

Memory is bounded in time: each stage keeps an exact count and sum plus the last ``window`` durations
(a rolling window for percentiles) in a numpy ring allocated and written once at start, so a day-long
flight uses the same memory as a minute (a deque of Python floats would grow for the first 11 minutes).
"""
from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Deque, Dict, List, Optional, Sequence

import numpy as np

STAGES = ("wait", "telemetry", "inference", "scale", "fusion", "link", "record", "total", "capture_to_send")
SUMMARY_WINDOW = 20_000   # ~11 min at 30 fps: the summary's percentiles are over the last this many frames
RECENT_WINDOW = 512


class _Ring:
    """The last ``size`` values, in a preallocated float64 array (pages touched up front: RSS does not creep)."""

    def __init__(self, size: int):
        self._a = np.full(size, np.nan)
        self._n = 0

    def append(self, value: float) -> None:
        self._a[self._n % self._a.shape[0]] = value
        self._n += 1

    def values(self) -> np.ndarray:
        out: np.ndarray = self._a[:min(self._n, self._a.shape[0])].copy()
        return out

    def __len__(self) -> int:
        return min(self._n, self._a.shape[0])


class StageTimes:
    """Durations (seconds) of every stage: a bounded window for the summary, the last second for the status line.

    Two threads add to it (inference in the main loop, fusion in the worker), so access is locked.
    """

    def __init__(self, window: int = SUMMARY_WINDOW):
        self._window = window
        self._all: Dict[str, _Ring] = {s: _Ring(window) for s in STAGES}
        self.recent: Dict[str, Deque[float]] = {s: deque(maxlen=RECENT_WINDOW) for s in STAGES}
        self._count: Dict[str, int] = {s: 0 for s in STAGES}
        self._sum: Dict[str, float] = {s: 0.0 for s in STAGES}
        self._lock = threading.Lock()

    def add(self, stage: str, seconds: float) -> None:
        with self._lock:
            if stage not in self._all:
                self._all[stage] = _Ring(self._window)
            self._all[stage].append(seconds)
            self.recent.setdefault(stage, deque(maxlen=RECENT_WINDOW)).append(seconds)
            self._count[stage] = self._count.get(stage, 0) + 1
            self._sum[stage] = self._sum.get(stage, 0.0) + seconds

    @property
    def all(self) -> Dict[str, List[float]]:
        """The summary window of every stage (a copy)."""
        with self._lock:
            return {k: v.values().tolist() for k, v in self._all.items()}

    def count(self, stage: str) -> int:
        with self._lock:
            return self._count.get(stage, 0)

    def total_s(self, stage: str) -> float:
        with self._lock:
            return self._sum.get(stage, 0.0)

    def percentiles_ms(self, stage: str, qs: Sequence[float] = (50, 99), recent: bool = False) -> List[float]:
        with self._lock:
            if recent:
                values = np.asarray(self.recent.get(stage, ()), dtype=np.float64)
            else:
                ring = self._all.get(stage)
                values = ring.values() if ring is not None else np.empty(0)
        if not values.size:
            return [float("nan")] * len(qs)
        return [float(v) * 1e3 for v in np.percentile(values, qs)]

    def clear_recent(self) -> None:
        with self._lock:
            for d in self.recent.values():
                d.clear()


@dataclass
class RunSummary:
    frames: int = 0
    targets: int = 0
    sent: int = 0
    held: int = 0
    wall_s: float = 0.0
    drops: int = 0
    camera_faults: int = 0
    not_fused: int = 0           # frames inferred but not fused (PipelineOptions.fusion_max_hz)
    bridged: int = 0             # targets re-sent between frames (pipeline/bridge.py), beside the frames' ``sent``
    link: Dict[str, int] = field(default_factory=dict)
    autopilot_setup: Optional[Dict[str, Any]] = None   # the PLND_* parameters read (io.autopilot_setup)
    mount_line: str = ""         # the camera's orientation measured from the images (pipeline.mount_watch)
    rejected_telemetry: Dict[str, int] = field(default_factory=dict)
    # Samples kept but held, not carried along their rate, at a capture time past them (io.telemetry)
    telemetry_rates_refused: Dict[str, int] = field(default_factory=dict)
    telemetry_samples: int = 0
    times: StageTimes = field(default_factory=StageTimes)
    model_name: str = ""
    stopped_by: str = ""

    @property
    def images_per_s(self) -> float:
        return self.frames / self.wall_s if self.wall_s > 0 else 0.0

    @property
    def model_images_per_s(self) -> float:
        n, total = self.times.count("inference"), self.times.total_s("inference")
        return n / total if n and total > 0 else 0.0

    def _pacing_note(self) -> List[str]:
        """Say so when the source, not the CPU, set the pace (a live camera or the sim at its frame rate)."""
        wait, work = self.times.percentiles_ms("wait", (50,)), self.times.percentiles_ms("total", (50,))
        if not np.isfinite(wait[0]) or not np.isfinite(work[0]) or wait[0] <= work[0]:
            return []
        return ["The source paced this run (the pipeline waited longer for frames than it worked on them), so "
                "pipeline images/s is the camera's rate; the ratio says how much CPU headroom is left.", ""]

    def plnd_lag_line(self) -> str:
        """What ArduPilot's PLND_LAG should be set to: the median age, at send time, of the pose a target's body
        vector is expressed in (the newest telemetry when the target has a local position, else its capture),
        beside the value the autopilot was read to have."""
        p50 = self.times.percentiles_ms("pose_to_send", (50,))[0]
        capture = self.times.percentiles_ms("capture_to_send", (50,))[0]
        if not np.isfinite(p50):
            return "capture-to-send latency: no target was sent"
        lag_s = min(max(p50 / 1e3, 0.02), 0.25)
        has = (self.autopilot_setup or {}).get("values", {}).get("PLND_LAG")
        if has is None:
            advice = f"with ArduPilot set PLND_LAG = {lag_s:.2f} (0.02-0.25 s, needs a reboot)"
        elif abs(has - lag_s) <= 0.02:
            advice = f"the autopilot's PLND_LAG = {has:.2f} matches it"
        else:
            advice = f"the autopilot has PLND_LAG = {has:.2f}: set {lag_s:.2f} (0.02-0.25 s, needs a reboot)"
        return (f"capture-to-send latency median {capture:.0f} ms; targets are expressed at a pose {p50:.0f} ms old "
                f"at send time: {advice}")

    def setup_lines(self) -> List[str]:
        """The autopilot's precision-landing setup as read, when it was checked."""
        setup = self.autopilot_setup
        if setup is None:
            return []
        values = " ".join(f"{k}={v:g}" for k, v in setup["values"].items()) or "nothing read"
        lines = [f"autopilot setup ({setup['check']}): {values}"]
        lines += [f"  {p}" for p in setup["problems"]]
        if setup["unanswered"]:
            lines.append(f"  not answered: {', '.join(setup['unanswered'])}")
        return lines

    def table(self) -> str:
        """A Table 1-style report (images/s, 2 threads) plus per-stage latency."""
        ratio = self.images_per_s / self.model_images_per_s if self.model_images_per_s else 0
        rows = ["| model | frames | pipeline images/s | model-only images/s | ratio |", "|---|---|---|---|---|",
                f"| {self.model_name} | {self.frames} | {self.images_per_s:.2f} | {self.model_images_per_s:.2f} | "
                f"{ratio:.0%} |", "", *self._pacing_note(),
                "| stage | p50 ms | p90 ms | p99 ms |", "|---|---|---|---|"]
        for stage in STAGES:
            if self.times.count(stage):
                p = self.times.percentiles_ms(stage, (50, 90, 99))
                rows.append(f"| {stage} | {p[0]:.1f} | {p[1]:.1f} | {p[2]:.1f} |")
        rows.append("")
        fused = f" ({self.not_fused} inferred but not fused: --fusion-hz)" if self.not_fused else ""
        rows.append(f"targets {self.targets}/{self.frames} frames{fused} ({self.held} held from memory), LANDING_TARGET sent "
                    f"{self.sent} (+{self.bridged} between frames: --bridge), drops {self.drops}, "
                    f"camera faults {self.camera_faults}, link {self.link}, "
                    f"rejected telemetry {self.rejected_telemetry}, stopped by {self.stopped_by or 'end'}")
        if self.telemetry_rates_refused:
            rows.append(f"telemetry rates not used to carry samples to a capture time (they disagreed with the series): "
                        f"{self.telemetry_rates_refused} of {self.telemetry_samples} samples")
        rows += self.setup_lines()
        if self.mount_line:
            rows.append(self.mount_line)
        rows.append(self.plnd_lag_line())
        return "\n".join(rows)
