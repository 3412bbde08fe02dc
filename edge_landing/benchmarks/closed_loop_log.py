"""Reading edge-run's ``--log`` (JSON lines) while a closed-loop flight runs and after it: the targets sent,
the committed spot, and whether the last decisions hold a freshly confirmed one (benchmarks.closed_loop).
The log is being written while it is read: a cut last line is skipped."""
from __future__ import annotations

import json
from pathlib import Path
from typing import List, Optional

import numpy as np

__all__ = ["last_committed", "recently_committed", "sent_targets"]


def sent_targets(log_path: Path) -> np.ndarray:
    """Local NED (N×3) of every target edge-run sent to the autopilot, in order, from its ``--log``."""
    out: List[List[float]] = []
    if log_path.is_file():
        for line in log_path.read_text().splitlines():
            try:
                r = json.loads(line)
            except ValueError:
                continue  # the last line may be cut by the stop
            if r.get("valid") and r.get("sent") and r.get("ned_m"):
                out.append([float(v) for v in r["ned_m"]])
    return np.array(out, np.float64).reshape(-1, 3)


def last_committed(log_path: Path) -> Optional[np.ndarray]:
    """Local NED of the last spot edge-run had committed (its ``--log``'s ``committed_ned_m``), or None."""
    last: Optional[np.ndarray] = None
    if log_path.is_file():
        for line in log_path.read_text().splitlines():
            try:
                committed = json.loads(line).get("committed_ned_m")
            except (ValueError, AttributeError):
                continue  # the last line may be cut by the stop
            if committed:
                last = np.array(committed, np.float64)
    return last


def recently_committed(log_path: Path, frames: int = 5, sent: int = 3) -> bool:
    """Did edge-run send a target in at least ``sent`` of its last ``frames`` decisions, the last of them with a
    committed spot, and one of them a fresh confirmation rather than the spot re-sent from memory (its ``--log``)?
    Only geometry-confirmed targets are committed (ARCHITECTURE.md §11-12). A spot held from memory may lie
    behind the vehicle, seen during the climb: in the closed loop two such spots, 68 and 100 m from where LAND
    began, expired (--hold, 20 s unconfirmed) before the vehicle reached them, and it came down where it was."""
    try:
        with open(log_path, "rb") as f:
            f.seek(max(0, f.seek(0, 2) - 8192))
            lines = f.read().decode(errors="replace").splitlines()[1:]
    except OSError:
        return False
    records = []
    for line in lines[-frames - 1:]:
        try:
            records.append(json.loads(line))
        except ValueError:
            continue  # a line being written
    recent = records[-frames:]
    fresh = any(r.get("sent") and not str(r.get("reason", "")).startswith("held") for r in recent)
    return (bool(recent) and bool(recent[-1].get("committed_ned_m")) and fresh
            and sum(bool(r.get("sent")) for r in recent) >= sent)
