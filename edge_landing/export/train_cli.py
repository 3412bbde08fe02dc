"""edge-train: train a network of the zoo on scene folders, checkpoint every epoch, export ONNX at the end.

    edge-train --arch edgenet --train scenes/sub1 scenes/sub2 --val scenes/sub9 --epochs 30 --batch 8 \\
               --lr 2e-3 --height 120 --width 160 --out runs/edgenet
    edge-train --arch edgenet ... --resume runs/edgenet/last.pth          # continue where it stopped
    edge-train --arch edgenet ... --init runs/edgenet/best.pth --height 240 --width 320   # fine-tune larger
    edge-train --arch edgenet ... --init runs/edgenet/best.pth --net-width 24   # widen (same outputs at step 0)

Writes OUT/last.pth and OUT/best.pth each epoch, OUT/history.json, OUT/record.json and OUT/<arch>.onnx (the
best checkpoint, exported at the training size with the contract and the training record in
edge.source).
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Sequence

from edge_landing.cli.common import CliParser, check_number, check_threads, output_folder, run_cli
from edge_landing.runtime.core.errors import EdgeError, InputError

from .zoo import arch_names


def build_parser() -> argparse.ArgumentParser:
    p = CliParser(prog="edge-train", description=__doc__.split("\n\n")[0], extra="export")
    p.add_argument("--arch", required=True, help=f"architecture: {', '.join(arch_names())}")
    p.add_argument("--task", default=None, help="depth, hvo or depth+hvo (default: the architecture's)")
    p.add_argument("--train", nargs="+", required=True, metavar="SCENE", help="training scene folder(s)")
    p.add_argument("--val", nargs="+", default=(), metavar="SCENE",
                   help="held-out validation scene(s), pooled (best.pth by their loss)")
    p.add_argument("--epochs", type=int, default=10)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--weight-decay", type=float, default=1e-4)
    p.add_argument("--out", required=True, type=Path, help="output folder for checkpoints, records and the ONNX")
    p.add_argument("--resume", default=None, metavar="CKPT", help="continue a run (model, optimiser, schedule, epoch)")
    p.add_argument("--init", default=None, metavar="CKPT", help="start from these weights with a fresh schedule")
    p.add_argument("--height", type=int, default=None, help="training height (default: the architecture's)")
    p.add_argument("--width", type=int, default=None, help="training width")
    p.add_argument("--export-height", type=int, default=None,
                   help="ONNX input height (default: the training height); checked before training starts")
    p.add_argument("--export-width", type=int, default=None, help="ONNX input width (default: the training width)")
    p.add_argument("--net-width", type=int, default=None, help="edgenet only: base channel width (default 16, at most 256)")
    p.add_argument("--hvo-weight", type=float, default=1.0, help="weight of the HVO cross-entropy")
    p.add_argument("--depth-l1-weight", type=float, default=0.1,
                   help="DenseDepth's λ on the depth L1 term (0.1; larger teaches absolute scale harder)")
    p.add_argument("--threads", type=int, default=1, help="torch threads, 1..256 (default 1: the cores are shared)")
    p.add_argument("--device", default="auto", help="auto (CUDA when present), cpu or cuda")
    p.add_argument("--seed", type=int, default=0, help="seed of the initialisation, shuffling and augmentation")
    p.add_argument("--max-steps", type=int, default=None, help="cap on steps per epoch (smoke runs)")
    p.add_argument("--no-augment", action="store_true", help="train without augmentation")
    p.add_argument("--no-export", action="store_true", help="skip the ONNX export at the end")
    p.add_argument("--overwrite", action="store_true", help="start afresh in an --out folder that holds a run")
    p.add_no_progress()
    return p


MAX_SEED = 2 ** 32 - 1


def check_numbers(args: argparse.Namespace) -> None:
    """Every number on the command line, before anything is loaded or written (the export size's fit to the
    architecture is checked by train() before the first epoch)."""
    from .onnx_export import MAX_INPUT_SIDE
    from .zoo.edgenet import MAX_CHANNELS

    for flag, value in (("--epochs", args.epochs), ("--batch", args.batch)):
        if value < 1:
            raise InputError(f"{flag} must be at least 1, got {value}")
    check_number("--lr", args.lr, 0.0, lo_open=True)
    for flag, value in (("--weight-decay", args.weight_decay), ("--hvo-weight", args.hvo_weight),
                        ("--depth-l1-weight", args.depth_l1_weight)):
        check_number(flag, value, 0.0)
    check_threads("--threads", args.threads)
    if not 0 <= args.seed <= MAX_SEED:
        raise InputError(f"--seed must be an integer between 0 and {MAX_SEED}, got {args.seed}")
    for flag, value in (("--export-height", args.export_height), ("--export-width", args.export_width)):
        if value is not None:
            check_number(flag, value, 1, MAX_INPUT_SIDE, unit="pixels")
    if args.net_width is not None:
        if args.arch != "edgenet":
            raise InputError(f"--net-width applies to edgenet only, not {args.arch}")
        if not 1 <= args.net_width <= MAX_CHANNELS:
            raise InputError(f"--net-width must be between 1 and {MAX_CHANNELS}, got {args.net_width}")


def config_from_args(args: argparse.Namespace):
    """The TrainConfig of the parsed arguments (torch is imported here; the parser has checked the extra)."""
    from .augment import AugmentConfig
    from .train import TrainConfig

    if args.resume and args.init:
        raise InputError("--resume and --init exclude each other (resume continues a run, init starts a new one)")
    for flag, value in (("--resume", args.resume), ("--init", args.init)):
        if value and Path(value).is_dir():
            raise InputError(f"{flag} checkpoint {value} is a folder, expected a last.pth/best.pth file")
        if value and not Path(value).is_file():
            raise InputError(f"{flag} checkpoint {value} does not exist")
    check_numbers(args)
    options: tuple[tuple[str, float], ...] = ()
    if args.net_width is not None:
        options = (("channels", int(args.net_width)),)
    return TrainConfig(
        arch=args.arch, task=args.task, train_scenes=tuple(str(s) for s in args.train),
        val_scenes=tuple(str(s) for s in args.val),
        out_dir=str(args.out), epochs=args.epochs, batch=args.batch, lr=args.lr, weight_decay=args.weight_decay,
        height=args.height, width=args.width, export_height=args.export_height, export_width=args.export_width,
        options=options, resume=args.resume, init=args.init, threads=args.threads, device=args.device,
        seed=args.seed, hvo_weight=args.hvo_weight, depth_l1_weight=args.depth_l1_weight,
        max_steps_per_epoch=args.max_steps, export=not args.no_export,
        augment=AugmentConfig.none() if args.no_augment else AugmentConfig(), progress=not args.no_progress,
        overwrite=args.overwrite)


def _main(argv: Sequence[str] | None) -> int:
    args = build_parser().parse_args(argv)   # without the [export] extra: one line (CliParser checks it)
    config = config_from_args(args)
    made = _missing_folders(Path(args.out))
    output_folder(args.out, "the --out folder")
    from .train import train

    try:
        result = train(config)
    except EdgeError:
        _remove_if_empty(made)   # refused before anything was written (a scene that does not load)
        raise
    last = result.history[-1] if result.history else {}
    print(f"trained {args.arch}: {len(result.history)} epochs, final train loss "
          f"{last.get('train', {}).get('total', float('nan')):.4f}; best checkpoint {result.best_checkpoint}"
          + (f"; exported {result.onnx_path}" if result.onnx_path else ""))
    return 0


def _missing_folders(path: Path) -> list[Path]:
    """``path`` and those of its parents that do not exist yet, deepest first."""
    missing = []
    while not path.exists() and path != path.parent:
        missing.append(path)
        path = path.parent
    return missing


def _remove_if_empty(folders: list[Path]) -> None:
    """Remove the folders this run made, deepest first, as long as they are empty."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:
            return   # something was written after all: keep it


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
