"""edge-export: a trained (or random) network of the zoo -> one self-describing ONNX file.

    edge-export --arch safeuav-small --task hvo --checkpoint safeuav_small_hvo.pkl --out safeuav_small.onnx
    edge-export --arch densedepth --checkpoint nyu.pth --out densedepth_nyu.onnx          # 480x640
    edge-export --arch densedepth --min-depth 1 --max-depth 80 --checkpoint kitti.pth --out dd_kitti.onnx
    edge-export --arch adabins --bins 256 --height 480 --width 640 --out adabins.onnx  # random weights: warns
    edge-export --arch edgenet --option channels=24 --checkpoint runs/edgenet.pth --out edgenet.onnx

Sizes default to the paper's input size of each architecture; the exported model is verified against
PyTorch with ONNX Runtime before it is written.
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

from edge_landing.cli.common import CliParser, check_number, check_outputs_spare_inputs, output_file, run_cli
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.perception.contract import Task

# (flag attribute, ArchSpec option name)
_OPTION_FLAGS = (("bins", "bins"), ("min_depth", "min_depth"), ("max_depth", "max_depth"))
MAX_SIDE = 4096   # onnx_export.MAX_INPUT_SIDE (not imported here: that module loads torch, and --help stays fast)


@dataclass(frozen=True)
class ExportCliConfig:
    arch: str
    task: Optional[Task]
    out: Path
    height: Optional[int]
    width: Optional[int]
    checkpoint: Optional[Path]
    options: tuple          # ((name, value), ...) given on the command line
    opset: int
    no_progress: bool
    trust_checkpoint: bool = False


def build_parser() -> argparse.ArgumentParser:
    from edge_landing.export.zoo import arch_names

    p = CliParser(prog="edge-export", description=__doc__.split("\n\n")[0], extra="export",
                  formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--arch", required=True, choices=arch_names(), help="architecture of the zoo")
    p.add_argument("--task", choices=[t.value for t in Task], help="head to export (default: the arch's own)")
    p.add_argument("--checkpoint", type=Path, help="the authors' checkpoint (.pth / .pkl); "
                   "without it the weights are RANDOM (speed tests only)")
    p.add_argument("--trust-checkpoint", action="store_true",
                   help="unpickle objects besides tensors in the checkpoint (old files); runs code from the file")
    p.add_argument("--height", type=int, help="fixed input height in pixels (default: the paper's)")
    p.add_argument("--width", type=int, help="fixed input width in pixels (default: the paper's)")
    p.add_argument("--bins", type=int, help="AdaBins: number of depth bins (e.g. 80 or 256)")
    p.add_argument("--min-depth", type=float, help="depth clamp in metres written to the contract")
    p.add_argument("--max-depth", type=float, help="max depth in metres (DenseDepth: 10 NYU, 80 KITTI)")
    p.add_argument("--option", action="append", default=[], metavar="NAME=VALUE",
                   help="any other build option of the arch (e.g. edgenet's channels=16); repeatable")
    p.add_argument("--opset", type=int, default=17, help="ONNX opset, at most 20 (default 17)")
    p.add_no_progress()
    p.add_argument("--out", type=Path, required=True, help="output .onnx file")
    return p


def parse_config(argv: Optional[Sequence[str]]) -> ExportCliConfig:
    args = build_parser().parse_args(argv)
    options = tuple((name, getattr(args, attr)) for attr, name in _OPTION_FLAGS if getattr(args, attr) is not None)
    options += tuple(_parse_option(text) for text in args.option)
    return ExportCliConfig(arch=args.arch, task=Task.from_string(args.task) if args.task else None, out=args.out,
                           height=args.height, width=args.width, checkpoint=args.checkpoint, options=options,
                           opset=args.opset, no_progress=args.no_progress, trust_checkpoint=args.trust_checkpoint)


def _parse_option(text: str) -> tuple:
    name, sep, value = text.partition("=")
    if not sep or not name:
        raise InputError(f"--option '{text}' should be NAME=VALUE (e.g. channels=16)")
    for kind in (int, float):
        try:
            return name.replace("-", "_"), kind(value)
        except ValueError:
            pass
    raise InputError(f"--option {name}: value '{value}' is not a number")


def _option_flag(name: str) -> str:
    """The flag that set a build option, for the error: --bins, --min-depth, --max-depth or --option NAME."""
    return next((f"--{attr.replace('_', '-')}" for attr, opt in _OPTION_FLAGS if opt == name), f"--option {name}")


def check_config(config: ExportCliConfig) -> None:
    """The flags that need no network: sizes, the checkpoint path and the option values (before the export)."""
    for flag, value in (("--height", config.height), ("--width", config.width)):
        if value is not None:
            check_number(flag, value, 1, MAX_SIDE, unit="pixels")
    if config.checkpoint is not None:
        if config.checkpoint.is_dir():
            raise InputError(f"--checkpoint {config.checkpoint} is a folder, expected a checkpoint file (.pth / .pkl)")
        if not config.checkpoint.is_file():
            raise InputError(f"--checkpoint {config.checkpoint} does not exist")
    check_outputs_spare_inputs({"--out": config.out}, {"--checkpoint": config.checkpoint})


def _main(argv: Optional[Sequence[str]] = None) -> int:
    config = parse_config(argv)   # without the [export] extra: one line (CliParser checks it after parsing)
    check_config(config)
    output_file(config.out, "the --out file")
    # torch is imported only here so that --help stays fast
    from edge_landing.export.onnx_export import ExportSettings, export_onnx, option_problem
    from edge_landing.export.zoo import get_arch

    spec = get_arch(config.arch)
    for name, value in config.options:   # before the network is built (and before the random-weights banner)
        problem = option_problem(spec, name, value) if name in spec.options else None   # unknown: check_options
        if problem:
            raise InputError(f"{_option_flag(name)} {problem}")
    height = config.height if config.height is not None else spec.input_hw[0]
    width = config.width if config.width is not None else spec.input_hw[1]
    report = export_onnx(spec, config.task, config.out, height, width, checkpoint=config.checkpoint,
                         options=dict(config.options),
                         settings=ExportSettings(opset=config.opset, progress=not config.no_progress,
                                                 trust_checkpoint=config.trust_checkpoint))
    print(report.summary())
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    return run_cli(_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
