"""What a training run leaves behind: the record (edge.source "training" and the shipped JSON), the one-line
epoch summary, and the exported ONNX of the best checkpoint with that record inside.
"""
from __future__ import annotations

import json
import subprocess
from dataclasses import asdict
from datetime import datetime, timezone
from pathlib import Path
from typing import Optional, Tuple

import torch

from edge_landing.runtime.perception.contract import ModelContract, Task

from .datasets import label_counts
from .zoo import get_arch


def git_commit(cwd: Path) -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=cwd, capture_output=True, text=True, timeout=10)
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def epoch_summary(row: dict) -> str:
    parts = [f"epoch {row['epoch']}: train loss {row['train']['total']:.4f}"]
    v = row.get("val")
    if v:
        parts.append(f"val loss {v['total']:.4f}")
        for key, label in (("delta1_median_scaled", "δ1*"), ("h_precision", "H-prec"), ("hvo_pixel_acc", "HVO acc")):
            if key in v:
                parts.append(f"{label} {v[key]:.3f}")
    parts.append(f"{row['epoch_s']:.0f} s")
    return ", ".join(parts)


def run_record(cfg, arch, task, hw, train_set, val_set, history, wall_s, device) -> dict:
    """What edge.source and the shipped JSON say about the training run."""
    last = history[-1] if history else {}
    best = min(history, key=lambda r: r.get("val", r["train"])["total"]) if history else {}
    return {
        "weights": "trained", "arch": arch, "task": task.value, "train_size_hw": list(hw),
        "train_scenes": [s.to_json() for s in train_set.scenes], "train_frames": len(train_set),
        "train_label_pixels": label_counts(train_set.hvo) if train_set.hvo is not None else None,
        "val_scenes": [s.to_json() for s in val_set.scenes] if val_set is not None else [],
        "epochs": len(history), "batch": cfg.batch, "lr": cfg.lr, "options": dict(cfg.options),
        "augment": asdict(cfg.augment), "init": cfg.init, "resumed_from": cfg.resume,
        "losses": f"depth: DenseDepth {cfg.depth_l1_weight:g}*L1 + grad L1 + (1-SSIM)/2 in the loss space of the "
                  f"depth convention (metric: normalised log depth); hvo: {cfg.hvo_weight:g} * cross-entropy, "
                  "ignore 255",
        "final_train": last.get("train"), "final_val": last.get("val"),
        "best_epoch": best.get("epoch"), "best_val": best.get("val"),
        "git_commit": git_commit(Path(__file__).resolve().parent),
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "device": str(device), "threads": cfg.threads, "wall_s": round(wall_s, 1), "torch": torch.__version__,
    }


def export_trained(arch: str, options, export_hw: Tuple[Optional[int], Optional[int]], checkpoint: Path,
                   out_path: Path, record: dict, progress: bool = True) -> Path:
    """Export ``checkpoint`` with the contract (export.onnx_export) and put the training record in edge.source."""
    from .onnx_export import ExportSettings, export_onnx

    spec = get_arch(arch)
    task = Task.from_string(record["task"])
    # Default: the size it was trained at. A net trained on 120×160 frames sees objects at half the scale
    # of 240×320 ones; exported at 240×320 our SafeUAV-Net-Small depth baseline fell from δ1* 0.99 to 0.27.
    train_h, train_w = record["train_size_hw"]
    h, w = export_hw[0] or train_h, export_hw[1] or train_w
    report = export_onnx(spec, task, out_path, h, w, checkpoint=checkpoint, options=dict(options),
                         settings=ExportSettings(progress=progress))
    set_source(out_path, {**report.source, "training": record})
    return out_path


def set_source(onnx_path: Path, source: dict) -> None:
    """Replace edge.source of an exported model (the rest of the contract is validated and kept)."""
    import onnx

    from edge_landing.runtime.perception.contract import KEY_SOURCE

    model = onnx.load(str(onnx_path))
    props = {p.key: p.value for p in model.metadata_props}
    ModelContract.from_metadata(props, where=str(onnx_path))
    props[KEY_SOURCE] = json.dumps(source, sort_keys=True, default=str)
    del model.metadata_props[:]
    for k, v in props.items():
        model.metadata_props.add(key=k, value=v)
    tmp = onnx_path.with_name(f".{onnx_path.name}.tmp")
    onnx.save(model, str(tmp))
    tmp.replace(onnx_path)
