"""Training any network of the zoo on scene folders, then exporting it with the model contract.

    cfg = TrainConfig(arch="edgenet", train_scenes=("scenes/sub1",), val_scenes=("scenes/sub9",), out_dir="runs/a",
                      epochs=20, batch=8, height=120, width=160)
    result = train(cfg)            # checkpoints out_dir/last.pth + best.pth each epoch, record.json, model.onnx

Losses (export/losses.py): DenseDepth's depth loss in the loss space of the model's depth convention plus
``hvo_weight`` × cross-entropy (ignore 255). Targets are taken at the output's resolution (nearest, never
blended). Checkpoints hold the state_dict under "model" (and, for SafeUAV's loader, the ordered parameter
list under "weights"), the optimiser, the schedule, the epoch and the history, so ``resume`` continues exactly;
``init`` only takes the weights (a new schedule, e.g. fine-tuning at a larger size).
"""
from __future__ import annotations

import json
import logging
import math
import pickle
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import torch
from torch.nn import functional as F
from tqdm import tqdm

from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.core.labels import HVO_IGNORE
from edge_landing.runtime.perception.contract import (
    Layout,
    ModelContract,
    Task,
)

from .augment import AugmentConfig, Augmenter
from .datasets import SceneSet, check_not_held_out, load_scenes
from .losses import W_DEPTH, DepthLossSpace, depth_loss, hvo_loss
from .onnx_export import MAX_INPUT_SIDE, check_input_size
from .train_record import epoch_summary, export_trained, run_record
from .zoo import get_arch

log = logging.getLogger(__name__)
DELTA1 = 1.25
WARMUP_SHARE = 0.05     # linear warm-up over the first 5 % of the steps, then cosine to 2 % of the peak
FINAL_LR_SHARE = 0.02


@dataclass(frozen=True)
class TrainConfig:
    arch: str
    train_scenes: Tuple[str, ...]
    out_dir: str
    val_scenes: Tuple[str, ...] = ()         # held-out scenes, pooled: best.pth is chosen on their loss
    task: Optional[str] = None               # default: the architecture's default task
    epochs: int = 10
    batch: int = 8
    lr: float = 1e-3
    weight_decay: float = 1e-4
    height: Optional[int] = None             # training size; default the architecture's input size
    width: Optional[int] = None
    export_height: Optional[int] = None      # ONNX input size; default the training size
    export_width: Optional[int] = None
    options: Tuple[Tuple[str, float], ...] = ()   # architecture options, e.g. (("channels", 16),)
    resume: Optional[str] = None
    init: Optional[str] = None
    threads: int = 1
    device: str = "auto"                     # auto (CUDA when present), cpu, cuda
    seed: int = 0
    hvo_weight: float = 1.0
    depth_l1_weight: float = W_DEPTH         # DenseDepth's λ on the L1 term
    max_steps_per_epoch: Optional[int] = None
    export: bool = True
    augment: AugmentConfig = AugmentConfig()
    progress: bool = True
    overwrite: bool = False                  # allow a fresh run into a folder that holds an earlier one


@dataclass
class TrainResult:
    out_dir: Path
    best_checkpoint: Path
    last_checkpoint: Path
    history: List[dict]
    onnx_path: Optional[Path] = None
    record: dict = field(default_factory=dict)


@dataclass(frozen=True)
class _Setup:
    task: Task
    contract: ModelContract
    names: Tuple[str, ...]
    space: Optional[DepthLossSpace]
    hvo_weight: float
    depth_l1_weight: float = W_DEPTH


# -- tensors in and out ------------------------------------------------------------------------------------
def to_input(rgb01: torch.Tensor, contract: ModelContract) -> torch.Tensor:
    """N×3×H×W RGB in [0, 1] -> the network input of the contract (mean/std, colour order, layout)."""
    spec = contract.input
    x = rgb01 if spec.color == "RGB" else rgb01.flip(1)
    mean = torch.tensor(spec.mean, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
    std = torch.tensor(spec.std, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
    x = (x - mean) / std
    return x.permute(0, 2, 3, 1).contiguous() if spec.layout is Layout.NHWC else x


def _nchw(t: torch.Tensor, layout: Layout) -> torch.Tensor:
    return t.permute(0, 3, 1, 2) if layout is Layout.NHWC else t


def split_outputs(outputs, setup: _Setup) -> Tuple[Optional[torch.Tensor], Optional[torch.Tensor]]:
    """The model's output tuple -> (depth N×1×h×w, HVO logits N×3×h×w), both NCHW."""
    named = dict(zip(setup.names, outputs if isinstance(outputs, (tuple, list)) else (outputs,)))
    c = setup.contract
    depth = _nchw(named[c.depth.output], c.depth.layout) if c.depth is not None else None
    hvo = _nchw(named[c.hvo.output], c.hvo.layout) if c.hvo is not None else None
    return depth, hvo


def _at(t: torch.Tensor, hw) -> torch.Tensor:
    """N×H×W target at another size by nearest neighbour (labels and NaN are never blended)."""
    if tuple(t.shape[-2:]) == tuple(hw):
        return t
    return F.interpolate(t[:, None].float(), size=tuple(hw), mode="nearest")[:, 0].to(t.dtype)


def compute_losses(model, rgb01, depth_m, hvo, setup: _Setup) -> Dict[str, torch.Tensor]:
    depth_out, hvo_out = split_outputs(model(to_input(rgb01, setup.contract)), setup)
    return losses_from_outputs(depth_out, hvo_out, depth_m, hvo, setup)


def losses_from_outputs(depth_out, hvo_out, depth_m, hvo, setup: _Setup) -> Dict[str, torch.Tensor]:
    """Loss terms of NCHW outputs against full-size targets (taken at the outputs' size)."""
    terms: Dict[str, torch.Tensor] = {}
    total = (depth_out if depth_out is not None else hvo_out).new_zeros(())
    if depth_out is not None:
        assert setup.space is not None     # a depth output comes with the depth head's loss space
        gt = _at(depth_m, depth_out.shape[-2:])[:, None]
        d = depth_loss(setup.space.output_to_loss(depth_out), setup.space.target_to_loss(gt), setup.space.valid(gt),
                       setup.depth_l1_weight)
        terms.update({"depth": d["total"], "l1": d["l1"], "grad": d["grad"], "ssim": d["ssim"]})
        total = total + d["total"]
    if hvo_out is not None:
        ce = hvo_loss(hvo_out, _at(hvo, hvo_out.shape[-2:]))
        terms["hvo"] = ce
        total = total + setup.hvo_weight * ce
    terms["total"] = total
    return terms


# -- validation ----------------------------------------------------------------------------------------------
@torch.no_grad()
def evaluate(model, data: SceneSet, setup: _Setup, batch: int, device) -> dict:
    """Mean loss terms, per-image median-scaled δ1 / AbsRel, and HVO precision/recall of 'horizontal'."""
    model.eval()
    sums: Dict[str, float] = {}
    n_batches, deltas, absrels = 0, [], []
    confusion = torch.zeros(3, 3, dtype=torch.long)
    for b in data.batches(batch, shuffle=False):
        rgb, depth = b.rgb.to(device), (b.depth_m.to(device) if b.depth_m is not None else None)
        hvo = b.hvo.to(device) if b.hvo is not None else None
        depth_out, hvo_out = split_outputs(model(to_input(rgb, setup.contract)), setup)
        for k, v in losses_from_outputs(depth_out, hvo_out, depth, hvo, setup).items():
            sums[k] = sums.get(k, 0.0) + float(v)
        n_batches += 1
        if depth_out is not None:
            assert setup.space is not None and depth is not None   # a depth head is trained on depth frames
            gt = _at(depth, depth_out.shape[-2:])
            pred = setup.space.loss_to_metres(setup.space.output_to_loss(depth_out[:, 0]))
            for g, p in zip(gt, pred):
                ok = setup.space.valid(g)
                if int(ok.sum()) == 0:
                    continue
                p_s = p[ok] * (g[ok].median() / p[ok].median())
                deltas.append(float((torch.maximum(g[ok] / p_s, p_s / g[ok]) < DELTA1).float().mean()))
                absrels.append(float(((g[ok] - p_s).abs() / g[ok]).mean()))
        if hvo_out is not None:
            assert hvo is not None                                  # an HVO head is trained on HVO frames
            lab = _at(hvo, hvo_out.shape[-2:]).flatten().cpu()
            pred_lab = hvo_out.argmax(1).flatten().cpu()
            keep = lab != HVO_IGNORE
            confusion += torch.bincount(lab[keep] * 3 + pred_lab[keep], minlength=9).view(3, 3)
    out = {k: v / max(n_batches, 1) for k, v in sums.items()}
    if deltas:
        out["delta1_median_scaled"] = sum(deltas) / len(deltas)
        out["abs_rel_median_scaled"] = sum(absrels) / len(absrels)
    if int(confusion.sum()):
        tp = confusion.diag().float()
        out["h_precision"] = float(tp[0] / confusion[:, 0].sum().clamp(min=1))
        out["h_recall"] = float(tp[0] / confusion[0].sum().clamp(min=1))
        out["hvo_pixel_acc"] = float(tp.sum() / confusion.sum())
    model.train()
    return out


# -- checkpoints -----------------------------------------------------------------------------------------------
def save_checkpoint(path: Path, model, optimizer, scheduler, epoch: int, best: float, history, cfg: TrainConfig) -> None:
    state = {"model": model.state_dict(), "weights": [p.detach().cpu() for p in model.parameters()],
             "optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(), "epoch": epoch,
             "best_val": best, "history": json.dumps(history), "config": json.dumps(_config_json(cfg))}
    tmp = path.with_suffix(".tmp")
    torch.save(state, tmp)
    tmp.replace(path)    # a crash mid-save never leaves a truncated checkpoint behind


def _config_json(cfg: TrainConfig) -> dict:
    d = asdict(cfg)
    d["options"] = dict(cfg.options)
    return d


def check_export_size(spec, task: Task, options: dict, height: Optional[int], width: Optional[int],
                      train_hw: Tuple[int, int]) -> None:
    """The ONNX export at the end runs after hours of training: its size must suit the network now (the same
    rules as edge-export), or the run would overwrite last.pth and then fail."""
    for flag, value in (("--export-height", height), ("--export-width", width)):
        if value is not None and not 1 <= value <= MAX_INPUT_SIDE:
            raise InputError(f"{flag} must be between 1 and {MAX_INPUT_SIDE} pixels, got {value}")
    h = height if height is not None else train_hw[0]
    w = width if width is not None else train_hw[1]
    try:
        check_input_size(spec, h, w)
        spec.contract(task, h, w, **options)      # architecture rules (e.g. AdaBins' patch count)
    except InputError as exc:
        raise InputError(f"cannot export at {h}x{w} after training (--export-height/--export-width, default the "
                         f"training size; or --no-export): {exc}") from None


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name not in ("cpu", "cuda"):
        raise InputError(f"--device '{name}' is not supported; expected auto, cpu or cuda")
    if name == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda was asked for but PyTorch sees no CUDA device")
    return torch.device(name)


def _schedule(optimizer, total_steps: int):
    warm = max(1, int(WARMUP_SHARE * total_steps))

    def factor(step: int) -> float:
        if step < warm:
            return (step + 1) / warm
        p = min(1.0, (step - warm) / max(1, total_steps - warm))
        return FINAL_LR_SHARE + (1 - FINAL_LR_SHARE) * 0.5 * (1 + math.cos(math.pi * p))
    return torch.optim.lr_scheduler.LambdaLR(optimizer, factor)


# -- the loop --------------------------------------------------------------------------------------------------
def train(cfg: TrainConfig) -> TrainResult:
    t_start = time.time()
    torch.set_num_threads(max(1, int(cfg.threads)))
    torch.manual_seed(cfg.seed)
    spec = get_arch(cfg.arch)
    task = Task.from_string(cfg.task) if cfg.task else spec.default_task
    if task not in spec.tasks:
        raise InputError(f"{spec.name} has no '{task}' head; expected one of: {', '.join(map(str, spec.tasks))}")
    if cfg.epochs < 1 or cfg.batch < 1 or not (cfg.lr > 0 and math.isfinite(cfg.lr)):
        raise InputError(f"need epochs >= 1, batch >= 1 and lr > 0, got {cfg.epochs}, {cfg.batch}, {cfg.lr}")
    if cfg.max_steps_per_epoch is not None and cfg.max_steps_per_epoch < 1:
        raise InputError(f"--max-steps must be at least 1, got {cfg.max_steps_per_epoch}")
    h = cfg.height if cfg.height is not None else spec.input_hw[0]
    w = cfg.width if cfg.width is not None else spec.input_hw[1]
    if min(h, w) < max(16, spec.size_multiple):
        raise InputError(f"training size {h}x{w} is too small for {spec.name}: at least "
                         f"{max(16, spec.size_multiple)} pixels each way expected")
    if h % spec.size_multiple or w % spec.size_multiple:
        raise InputError(f"training size {h}x{w} does not suit {spec.name}: multiples of {spec.size_multiple} expected")
    if max(h, w) > MAX_INPUT_SIDE:
        raise InputError(f"training size {h}x{w} is too large: at most {MAX_INPUT_SIDE} pixels each way")
    options = dict(cfg.options)
    contract = spec.contract(task, h, w, **options)
    if cfg.export:
        check_export_size(spec, task, options, cfg.export_height, cfg.export_width, (h, w))
    setup = _Setup(task, contract, tuple(spec.output_names(task)),
                   DepthLossSpace.from_spec(contract.depth) if contract.depth else None, cfg.hvo_weight,
                   cfg.depth_l1_weight)
    device = _device(cfg.device)
    out = Path(cfg.out_dir)
    if (out / "last.pth").exists() and not cfg.resume and not cfg.overwrite:
        raise InputError(f"--out {out} already holds a training run (last.pth); continue it with --resume "
                         f"{out / 'last.pth'}, choose a new --out, or pass --overwrite to replace it")
    check_not_held_out([*cfg.train_scenes, *cfg.val_scenes])     # before anything is written
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the output folder {out}: {exc.strerror}") from None

    train_set = load_scenes(cfg.train_scenes, h, w, task.has_depth, task.has_hvo, cfg.progress)
    val_set = (load_scenes(cfg.val_scenes, h, w, task.has_depth, task.has_hvo, cfg.progress)
               if cfg.val_scenes else None)
    model = spec.build(task, **options).to(device)
    optimizer = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    steps = train_set.steps(cfg.batch, drop_last=len(train_set) > cfg.batch)
    steps = min(steps, cfg.max_steps_per_epoch or steps)
    scheduler = _schedule(optimizer, steps * cfg.epochs)
    start_epoch, best, history = 0, math.inf, []
    if cfg.resume:
        try:
            state = torch.load(cfg.resume, map_location=device, weights_only=True)
            model.load_state_dict(state["model"])
            optimizer.load_state_dict(state["optimizer"])
            scheduler.load_state_dict(state["scheduler"])
            start_epoch, best, history = int(state["epoch"]), float(state["best_val"]), json.loads(state["history"])
        except (RuntimeError, KeyError, TypeError, ValueError, pickle.UnpicklingError, EOFError) as exc:
            raise InputError(f"--resume {cfg.resume} is not a last.pth/best.pth written by edge-train for this "
                             f"architecture and size ({_why_unloadable(exc)})") from None
        log.info("resumed %s at epoch %d", cfg.resume, start_epoch)
    elif cfg.init:
        (spec.init_checkpoint or spec.load_checkpoint)(model, Path(cfg.init))
    augmenter = Augmenter(cfg.augment, seed=cfg.seed + start_epoch)
    last, best_path = out / "last.pth", out / "best.pth"
    model.train()
    for epoch in range(start_epoch, cfg.epochs):
        t0 = time.time()
        sums: Dict[str, float] = {}
        bar = tqdm(total=steps, desc=f"epoch {epoch + 1}/{cfg.epochs}", disable=not cfg.progress, leave=False)
        batches = train_set.batches(cfg.batch, shuffle=True, seed=cfg.seed * 1000 + epoch,
                                    drop_last=len(train_set) > cfg.batch)
        for step, b in zip(range(steps), batches):
            rgb, depth, hvo = augmenter(b.rgb, b.depth_m, b.hvo)
            terms = compute_losses(model, rgb.to(device), depth.to(device) if depth is not None else None,
                                   hvo.to(device) if hvo is not None else None, setup)
            if not torch.isfinite(terms["total"]):
                raise InputError(f"training diverged at epoch {epoch + 1} step {step + 1} (loss is not finite); "
                                 f"lower --lr (now {cfg.lr})")
            optimizer.zero_grad(set_to_none=True)
            terms["total"].backward()
            optimizer.step()
            scheduler.step()
            for k, v in terms.items():
                sums[k] = sums.get(k, 0.0) + float(v.detach())
            bar.update(1)
            bar.set_postfix(loss=f"{sums['total'] / (step + 1):.4f}")
        bar.close()
        row = {"epoch": epoch + 1, "lr": optimizer.param_groups[0]["lr"],
               "train": {k: v / steps for k, v in sums.items()}, "epoch_s": round(time.time() - t0, 1)}
        if val_set is not None:
            row["val"] = evaluate(model, val_set, setup, cfg.batch, device)
        history.append(row)
        score = row["val"]["total"] if val_set is not None else row["train"]["total"]
        if score < best:
            best = score
            save_checkpoint(best_path, model, optimizer, scheduler, epoch + 1, best, history, cfg)
        save_checkpoint(last, model, optimizer, scheduler, epoch + 1, best, history, cfg)
        (out / "history.json").write_text(json.dumps(history, indent=1))
        tqdm.write(epoch_summary(row))
    if not best_path.exists():   # resumed after the last epoch: nothing new, keep last as best
        save_checkpoint(best_path, model, optimizer, scheduler, cfg.epochs, best, history, cfg)
    record = run_record(cfg, spec.name, task, (h, w), train_set, val_set, history, time.time() - t_start, device)
    (out / "record.json").write_text(json.dumps(record, indent=1, default=str))
    result = TrainResult(out, best_path, last, history, record=record)
    if cfg.export:
        result.onnx_path = export_trained(cfg.arch, cfg.options, (cfg.export_height, cfg.export_width),
                                          best_path, out / f"{spec.name}.onnx", record, cfg.progress)
    return result


def _why_unloadable(exc: Exception) -> str:
    """A short reason for a checkpoint that does not load (torch's unpickling messages run to a page)."""
    if isinstance(exc, (pickle.UnpicklingError, EOFError)):
        return "not a PyTorch checkpoint file, or a truncated one"
    if isinstance(exc, KeyError):
        return f"no '{exc.args[0]}' entry"
    return f"{type(exc).__name__}: {str(exc).splitlines()[0][:160]}"
