"""Fusion speed, this checkout against another, frame by frame in one run (ARCHITECTURE.md §9).

    python -m edge_landing.benchmarks.fusion_ab --base /path/to/other/checkout --frames 1500

On a shared machine the same code measures 20-50 % apart from one run to the next, so two bench_fusion runs
one after the other cannot show a change of a few per cent. Here two worker processes, one importing this
checkout's ``edge_landing`` and one the ``--base`` checkout's, get the same pre-rendered frames (bench_fusion's
box field, rendered once by this checkout) and run ``LandingFuser.update`` in turn, one frame each, the order
swapped every frame: whatever slows the machine slows both alike. Each worker sets the thread pools as edge-run
does (OpenCV ``--opencv-threads``, BLAS 1, through the environment). Prints one JSON object: each side's wall
p50/p90/p99 and thread-CPU p50 in ms, and the ratios this / base (below 1: this checkout is faster).
The base needs only the long-standing fuser API (LandingFuser, FusionConfig(working_hw), Prediction,
VehicleState, Attitude, Intrinsics, Mount).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Sequence

import numpy as np

from edge_landing.benchmarks.bench_fusion import BenchConfig, scene
from edge_landing.cli.common import CliParser, check_threads, run_cli
from edge_landing.runtime.core.cpu_features import cpu_features
from edge_landing.runtime.core.errors import InputError

# Runs in each worker, against whichever edge_landing its PYTHONPATH names. Protocol: one line in, one frame
# fused, one line out ("wall_s cpu_s").
_WORKER = r"""
import sys, time
import cv2, numpy as np
cv2.setNumThreads(int(sys.argv[3]))
from edge_landing.runtime.core.camera import Attitude, Intrinsics, Mount
from edge_landing.runtime.core.messages import Prediction, VehicleState
from edge_landing.runtime.fusion.fuser import FusionConfig, LandingFuser
d = np.load(sys.argv[1])
mode, fps = sys.argv[2], float(d["fps"])
intr = Intrinsics(*(int(v) for v in d["size"]), *(float(v) for v in d["pinhole"]))
fuser = LandingFuser(FusionConfig(working_hw=tuple(int(v) for v in d["working_hw"])), intr, Mount())
depth, probs, att, pos = d["depth"], d["probs"], d["attitude"], d["position"]
import edge_landing
print("ready", edge_landing.__file__, flush=True)
for i, _ in enumerate(sys.stdin):
    k = i % len(depth)
    state = VehicleState(i / fps, Attitude(*(float(v) for v in att[k])), pos[k] if mode == "ned" else None)
    pred = Prediction(i, i / fps, depth[k], probs[k])
    c0, t0 = time.thread_time(), time.perf_counter()
    fuser.update(pred, state, now_s=i / fps)
    print(time.perf_counter() - t0, time.thread_time() - c0, flush=True)
"""


@dataclass(frozen=True)
class AbConfig:
    base: Path
    frames: int = 1500
    warmup: int = 20
    mode: str = "ned"
    opencv_threads: int = 1


def _checkout_root() -> Path:
    return Path(__file__).resolve().parents[2]


def _save_scene(cfg: AbConfig, path: Path) -> None:
    bench = BenchConfig(mode=cfg.mode)
    intr, _, preds, states = scene(bench)
    np.savez(path, fps=bench.fps, size=[intr.width, intr.height], pinhole=[intr.fx, intr.fy, intr.cx, intr.cy],
             working_hw=list(bench.working_hw), depth=np.stack([p[0] for p in preds]),
             probs=np.stack([p[1] for p in preds]),
             attitude=np.array([[a.roll_rad, a.pitch_rad, a.yaw_rad] for a, _ in states]),
             position=np.stack([p for _, p in states]))


def _start(root: Path, scene_path: Path, cfg: AbConfig, name: str) -> subprocess.Popen:
    """One worker on ``root``'s edge_landing (first on the path); its stderr goes to a file beside the scene."""
    path = os.pathsep.join(p for p in (str(root), os.environ.get("PYTHONPATH", "")) if p)
    env = dict(os.environ, PYTHONPATH=path, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    with open(scene_path.parent / f"{name}.stderr", "w") as err:
        proc = subprocess.Popen([sys.executable, "-c", _WORKER, str(scene_path), cfg.mode, str(cfg.opencv_threads)],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=err, text=True, env=env,
                                cwd=str(scene_path.parent))
    ready = _pipe(proc.stdout).readline().split()
    if len(ready) != 2 or ready[0] != "ready":
        _stop(proc)
        who = f"--base {root}" if name == "base" else f"this checkout ({root})"
        raise InputError(f"{who}: its fusion did not start ({_last_line(scene_path.parent / f'{name}.stderr')})")
    if not Path(ready[1]).resolve().is_relative_to(root):
        _stop(proc)
        raise InputError(f"{name} side ({root}): the worker imported edge_landing from {ready[1]} instead")
    return proc


def _stop(proc: subprocess.Popen) -> None:
    """End a worker: close its input (it then exits), else kill it; never raises."""
    try:
        _pipe(proc.stdin).close()
    except OSError:                            # (a worker that died leaves a broken pipe)
        pass
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    if proc.stdout is not None:
        proc.stdout.close()


def _last_line(path: Path) -> str:
    lines = [ln.strip() for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
    return lines[-1] if lines else "no error output"


def _pipe(stream: IO[str] | None) -> IO[str]:
    assert stream is not None                  # (Popen with PIPE)
    return stream


def _frame(proc: subprocess.Popen, name: str, stderr: Path) -> tuple[float, float]:
    """One frame fused by one worker: (wall s, thread CPU s). A worker that hangs blocks here (a benchmark)."""
    try:
        _pipe(proc.stdin).write("\n")
        _pipe(proc.stdin).flush()
        line = _pipe(proc.stdout).readline().split()
    except OSError:
        line = []
    if len(line) != 2:
        raise InputError(f"the {name} side's fusion stopped mid-run ({_last_line(stderr)})")
    return float(line[0]), float(line[1])


def _figures(times: np.ndarray) -> dict:
    ms = times * 1e3
    return {"p50_ms": round(float(np.percentile(ms[:, 0], 50)), 3), "p90_ms": round(float(np.percentile(ms[:, 0], 90)), 3),
            "p99_ms": round(float(np.percentile(ms[:, 0], 99)), 3),
            "cpu_p50_ms": round(float(np.percentile(ms[:, 1], 50)), 3)}


def run(cfg: AbConfig, progress: bool = True) -> dict:
    if cfg.mode not in ("ned", "vehicle"):
        raise InputError(f"--mode must be 'ned' or 'vehicle', got '{cfg.mode}'")
    if cfg.frames < 10 or cfg.warmup < 0:
        raise InputError(f"--frames must be >= 10 and --warmup >= 0, got {cfg.frames} and {cfg.warmup}")
    if not (cfg.base / "edge_landing" / "runtime" / "fusion" / "fuser.py").is_file():
        raise InputError(f"--base {cfg.base}: not a checkout of this project (no edge_landing/runtime/fusion/fuser.py)")
    with tempfile.TemporaryDirectory(prefix="fusion_ab_") as tmp:
        scene_path = Path(tmp) / "scene.npz"
        _save_scene(cfg, scene_path)
        names = ("this", "base")
        procs: list[subprocess.Popen] = []
        try:
            for name, root in zip(names, (_checkout_root(), cfg.base.resolve())):
                procs.append(_start(root, scene_path, cfg, name))
            times: list[list[tuple[float, float]]] = [[], []]
            total = cfg.warmup + cfg.frames
            for i in range(total):
                for k in ((0, 1) if i % 2 == 0 else (1, 0)):
                    times[k].append(_frame(procs[k], names[k], Path(tmp) / f"{names[k]}.stderr"))
                if progress and (i + 1) % 500 == 0:
                    print(f"fusion_ab: {i + 1}/{total} frame pairs", file=sys.stderr)
        finally:
            for proc in procs:
                _stop(proc)
    this, base = (_figures(np.array(t[cfg.warmup:])) for t in times)
    return {"benchmark": "fusion_ab", "mode": cfg.mode, "frames": cfg.frames, "this": this, "base": base,
            "base_checkout": str(cfg.base), "p50_ratio": round(this["p50_ms"] / base["p50_ms"], 3),
            "p99_ratio": round(this["p99_ms"] / base["p99_ms"], 3), "opencv_threads": cfg.opencv_threads,
            "loadavg_1m": round(os.getloadavg()[0], 2), "cpu": cpu_features().summary()}


def _main(argv: Sequence[str] | None = None) -> int:
    d = AbConfig(base=Path("."))
    ap = CliParser(prog="fusion_ab", description=__doc__.splitlines()[0])
    ap.add_argument("--base", type=Path, required=True, help="root of the other checkout (holds edge_landing/)")
    ap.add_argument("--frames", type=int, default=d.frames)
    ap.add_argument("--warmup", type=int, default=d.warmup)
    ap.add_argument("--mode", default=d.mode, choices=("ned", "vehicle"))
    ap.add_argument("--opencv-threads", type=int, default=d.opencv_threads, help="OpenCV threads (edge-run uses 1)")
    a = ap.parse_args(argv)
    check_threads("--opencv-threads", a.opencv_threads)
    print(json.dumps(run(AbConfig(a.base, a.frames, a.warmup, a.mode, a.opencv_threads))))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
