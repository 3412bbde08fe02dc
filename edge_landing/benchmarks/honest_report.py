"""The README's accuracy table: edge-sim scenes, one scene scale (edge-calibrate), then edge-eval, per model.

Each row is a real run of the command-line tools (subprocesses, as a user would type them), and its figures
come from edge-eval's ``--json``: horizontal precision beside its base rate and lift, mIoU, landable precision
beside its base rate, δ1 and AbsRel after one per-scene scale.

    python -m edge_landing.benchmarks.honest_report --out out/honest \\
        --scene rural:901 --scene rural:902:randomise --scene suburban:930:randomise

``STYLE:SEED[:randomise][:hazards]`` scenes are rendered with ``edge-sim --frames N [--randomise] [--hazards]``
into OUT (kept when present).
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Optional, Sequence

from edge_landing.cli.common import CliParser, check_number, output_folder, run_cli
from edge_landing.runtime.core.errors import ContractError, InputError

MODELS = Path(__file__).resolve().parents[1] / "runtime" / "models"


def _tool(module: str, *args: str) -> None:
    proc = subprocess.run([sys.executable, "-m", module, *args], capture_output=True, text=True)
    if proc.returncode != 0:
        raise InputError(f"{module} {' '.join(args)} failed: {(proc.stderr or proc.stdout).strip().splitlines()[-1:]}")


SCENE_FLAGS = ("randomise", "hazards")


def parse_scene(spec: str) -> list[str]:
    """``STYLE:SEED[:randomise][:hazards]`` split in its parts, or one InputError naming the spec."""
    from edge_landing.sim.world import Style

    parts = spec.split(":")
    flags = parts[2:]
    if len(parts) < 2 or not parts[0] or not parts[1].isdigit() or any(f not in SCENE_FLAGS for f in flags) \
            or len(set(flags)) != len(flags):
        raise InputError(f"--scene must be STYLE:SEED[:randomise][:hazards], got '{spec}'")
    try:
        Style.from_string(parts[0])
    except InputError as exc:
        raise InputError(f"--scene '{spec}': {exc}") from None
    return parts


def scene_folder(out: Path, spec: str, frames: int) -> Path:
    parts = parse_scene(spec)
    flags = parts[2:]
    folder = out / spec.replace(":", "_")
    if not (folder / "scene.json").exists():
        _tool("edge_landing.sim.cli", str(folder), "--frames", str(frames), "--style", parts[0], "--seed", parts[1],
              "--no-progress", "--overwrite", *[f"--{f}" for f in flags])
    return folder


def row(model: Path, scene: Path, out: Path, max_depth_m: float) -> dict:
    tag = f"{scene.name}_{model.stem}"
    cal, res = out / f"cal_{tag}.json", out / f"eval_{tag}.json"
    _tool("edge_landing.calibration.cli", str(scene), "--model", str(model), "--out", str(cal),
          "--max-depth", str(max_depth_m), "--threads", "1", "--no-progress")
    _tool("edge_landing.cli.eval_cli", str(model), str(scene), "--max-depth", str(max_depth_m), "--calibration",
          str(cal), "--json", str(res), "--threads", "1", "--no-progress")
    m = json.loads(res.read_text())["models"][0]
    b, land, d = m["hvo"]["baseline"], m["landable"] or {}, m["depth"]
    return {"scene": scene.name, "model": model.name, "frames": d["frames"], **b,
            "landable_precision": land.get("landable_precision"), "landable_base_rate": land.get("landable_base_rate"),
            "delta1": d["calibrated"]["a1"], "abs_rel": d["calibrated"]["abs_rel"],
            "scale": d["calibration"]["scale"]}


def markdown(rows: Sequence[dict]) -> str:
    def f(v) -> str:
        return "–" if v is None else f"{v:.3f}"

    out = ["| scene | model | H precision | H base rate | lift | max lift | mIoU | landable precision | "
           "landable base | δ1 (scene scale) | AbsRel |", "|" + "---|" * 11]
    for r in rows:
        out.append(f"| {r['scene']} | {r['model']} | {f(r['horizontal_precision'])} | {f(r['horizontal_base_rate'])} | "
                   f"{f(r['horizontal_lift'])} | {f(r['horizontal_max_lift'])} | {f(r['miou'])} | "
                   f"{f(r['landable_precision'])} | {f(r['landable_base_rate'])} | {f(r['delta1'])} | {f(r['abs_rel'])} |")
    return "\n".join(out)


def _main(argv: Optional[Sequence[str]] = None) -> int:
    p = CliParser(prog="honest_report", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, type=Path, help="folder for scenes, calibrations and edge-eval JSON")
    p.add_argument("--scene", action="append", required=True, help="STYLE:SEED[:randomise][:hazards]")
    p.add_argument("--model", action="append", default=None,
                   help="ONNX model (repeatable; default: the shipped FP32 and INT8)")
    p.add_argument("--frames", type=int, default=40)
    p.add_argument("--max-depth", type=float, default=1000.0)
    args = p.parse_args(argv)
    # Everything checked before the first scene is rendered into --out.
    for spec in args.scene:
        parse_scene(spec)
    if args.frames < 1:
        raise InputError(f"--frames must be at least 1, got {args.frames}")
    check_number("--max-depth", args.max_depth, 0.0, 1e6, lo_open=True, unit="metres")
    models = [Path(m) for m in (args.model or [MODELS / "edgenet.onnx", MODELS / "edgenet.int8.onnx"])]
    from edge_landing.runtime.perception.inference import read_contract

    for m in models:
        try:
            read_contract(m)
        except ContractError as exc:
            raise InputError(f"--model: {exc}") from None
    output_folder(args.out, "the --out folder")
    rows = [row(m, scene_folder(args.out, s, args.frames), args.out, args.max_depth)
            for s in args.scene for m in models]
    (args.out / "report.json").write_text(json.dumps(rows, indent=1))
    print(markdown(rows))
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    return run_cli(_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
