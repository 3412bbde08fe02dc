"""Issue 13's goals on a set of flights: lying-model replays in parallel, every target judged by ray casting.

Runs ``lying_model``'s replay (ARCHITECTURE.md §11) on each flight of a set, ``--workers`` at a time, and writes
each flight's result to ``OUT/STYLE_SEED_APPROACH.json`` as soon as it finishes. A rerun with the same settings
reads the flights already there instead of flying them again, so an interrupted set loses nothing. At the end it
prints, and writes to ``OUT/summary.json``, per flight and model: the targets edge-run would send (geometry-
confirmed, with the continuity of §12) and how many were on ground-truth safe ground, beside the network alone's
(its spot sent unconfirmed: the base rate of trusting the network), raw and as edge-run ``--allow-unconfirmed``
sends it (through the same continuity: lying_model's ``network_sent``); and the goals, pooled:
- sent targets on safe ground: at least 95 % for the lying model, 99 % for the shipped one;
- targets on at least 20 % of the frames: on how many flights (refusing everything does not pass);
- the shipped model: at least as many frames with a target as its network alone, on how many flights, against
  both counts (a result written before ``network_sent`` existed has only the raw one).

``--set validation`` is the 42 hazard-rich flights the measurements use (no test uses their seeds); ``--flights``
names others (``STYLE:SEED`` or ``STYLE:SEED:APPROACH``). Each replay renders its flight on the fly (about 2 min
per 200 frames and model on one core of a 2-core machine at 640×480).

    python -m edge_landing.benchmarks.flight_set --set validation --approach arc --out out/arc42
    python -m edge_landing.benchmarks.flight_set --flights suburban:3141:arc urban:7202 --models lying shipped --out o
"""
from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import time
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional, Sequence

from edge_landing.benchmarks.lying_model import check_camera_size, weather_text
from edge_landing.cli.common import CliParser, check_choice, check_seed, check_threads, output_folder, run_cli
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.io.sources import SimReader

_VALIDATION_SEEDS = {
    "suburban": (1505, 3535, 4646, 5150, 6262, 7101, 7202, 7303, 7373, 7404, 7505, 7606, 7707, 7808, 8282, 9202,
                 9303, 9505, 9606, 9783, 9814),
    "urban": (1505, 3535, 4646, 5150, 6262, 7101, 7202, 7303, 7373, 7404, 7505, 7606, 7707, 7808, 8282, 9202,
              9303, 9505, 9606, 9749, 9767),
}
SAFE_GOAL = {"lying": 0.95, "shipped": 0.99}   # share of sent targets on safe ground
FRAMES_GOAL = 0.20                             # share of frames with a target, per flight


@dataclass(frozen=True)
class Flight:
    style: str
    seed: int
    approach: str = "straight"

    @property
    def name(self) -> str:
        return f"{self.style}_{self.seed}_{self.approach}"

    @staticmethod
    def parse(text: str, approach: str = "straight") -> Flight:
        """``STYLE:SEED`` or ``STYLE:SEED:APPROACH`` (the approach defaults to ``approach``): the style and
        approach as ``edge-sim`` takes them (sim.world.Style, sim.flight.Approach)."""
        from edge_landing.sim.flight import Approach
        from edge_landing.sim.world import Style

        parts = text.split(":")
        if len(parts) not in (2, 3) or not parts[1].isdigit():
            raise InputError(f"--flights: '{text}' is not STYLE:SEED[:APPROACH] (seed a whole number >= 0)")
        style = check_choice(f"--flights {text}", Style.from_string, parts[0]).value
        app = check_choice(f"--flights {text}", Approach.from_string, parts[2] if len(parts) == 3 else approach)
        return Flight(style, check_seed("--flights", int(parts[1])), app.value)


def validation_set(approach: str = "straight") -> list[Flight]:
    return [Flight(style, seed, approach) for style, seeds in _VALIDATION_SEEDS.items() for seed in seeds]


@dataclass(frozen=True)
class SetConfig:
    flights: tuple[Flight, ...]
    out: Path
    models: tuple[str, ...] = ("lying",)
    frames: int = 200
    width: int = SimReader.DEFAULT_SIZE[0]
    height: int = SimReader.DEFAULT_SIZE[1]
    workers: int = 2

    def settings(self) -> dict[str, Any]:
        """What a finished flight's file must have been made with to be reused."""
        return {"frames": self.frames, "width": self.width, "height": self.height, "models": list(self.models)}


def _fly(flight: Flight, cfg: SetConfig) -> dict[str, Any]:
    """One replay, written to its file through a temporary name (a killed run leaves no half file)."""
    from edge_landing.benchmarks.lying_model import ReplayConfig, replay

    result = replay(ReplayConfig(flight.style, flight.seed, cfg.frames, models=cfg.models, width=cfg.width,
                                 height=cfg.height, approach=flight.approach))
    result["set_settings"] = cfg.settings()
    path = cfg.out / f"{flight.name}.json"
    part = path.with_suffix(".json.part")
    part.write_text(json.dumps(result, indent=1))
    os.replace(part, path)
    return result


def _finished(flight: Flight, cfg: SetConfig) -> Optional[dict[str, Any]]:
    """The flight's earlier result in ``cfg.out`` (None: not flown yet); refused if made with other settings."""
    path = cfg.out / f"{flight.name}.json"
    if not path.exists():
        return None
    try:
        result: dict[str, Any] = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: not a finished flight's result ({exc}); remove it or use another --out") from None
    if result.get("set_settings") != cfg.settings():
        raise InputError(f"{path} was made with other settings ({result.get('set_settings')}, now "
                         f"{cfg.settings()}): use another --out")
    return result


def flight_row(flight: Flight, result: dict[str, Any]) -> dict[str, Any]:
    """Per model: frames, sent and safe, the network alone's targets and safe ones; the flight's weather when the
    result has it (sim.effects.Effects.to_json)."""
    row: dict[str, Any] = {"flight": flight.name, "frames": int(result["frames"])}
    if "weather" in result:
        row["weather"] = result["weather"]
    for model, kinds in result["stats"].items():
        row[model] = {"sent": kinds["sent"]["targets"], "sent_safe": kinds["sent"]["safe"],
                      "network": kinds["network"]["targets"], "network_safe": kinds["network"]["safe"]}
        if "network_sent" in kinds:
            row[model].update(network_sent=kinds["network_sent"]["targets"],
                              network_sent_safe=kinds["network_sent"]["safe"])
    return row


def goals(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The pooled goals per model over flight rows (``flight_row``)."""
    out: dict[str, Any] = {}
    for model in SAFE_GOAL:
        mine = [r for r in rows if model in r]
        if not mine:
            continue
        sent = sum(r[model]["sent"] for r in mine)
        safe = sum(r[model]["sent_safe"] for r in mine)
        net, net_safe = sum(r[model]["network"] for r in mine), sum(r[model]["network_safe"] for r in mine)
        enough = sum(r[model]["sent"] >= FRAMES_GOAL * r["frames"] for r in mine)
        g: dict[str, Any] = {
            "flights": len(mine), "sent": sent, "sent_safe": safe, "safe_share": safe / sent if sent else None,
            "safe_goal": SAFE_GOAL[model], "safe_met": bool(sent) and safe >= SAFE_GOAL[model] * sent,
            "flights_with_enough_targets": enough, "frames_goal": FRAMES_GOAL, "frames_met": enough == len(mine),
            "network_alone": net, "network_alone_safe": net_safe,
            "unsafe_flights": [r["flight"] for r in mine if r[model]["sent_safe"] < r[model]["sent"]]}
        if model == "shipped":
            g["flights_at_least_network"] = sum(r[model]["sent"] >= r[model]["network"] for r in mine)
        as_sent = [r[model] for r in mine if "network_sent" in r[model]]
        if as_sent:
            g["network_sent"] = {"flights": len(as_sent), "targets": sum(m["network_sent"] for m in as_sent),
                                 "safe": sum(m["network_sent_safe"] for m in as_sent),
                                 "flights_at_least": sum(m["sent"] >= m["network_sent"] for m in as_sent)}
        out[model] = g
    return out


def _share(a: int, b: int) -> str:
    return f"{100 * a / b:.1f} %" if b else "-"


def report(rows: Sequence[dict[str, Any]], summary: dict[str, Any]) -> str:
    lines = []
    for r in rows:
        parts = [f"{m} sent {r[m]['sent']}/{r['frames']}, safe {r[m]['sent_safe']} | network alone "
                 f"{r[m]['network']}, safe {r[m]['network_safe']}" + _as_sent(r[m]) for m in SAFE_GOAL if m in r]
        weather = f" ({weather_text(r['weather'])})" if "weather" in r else ""
        lines.append(f"{r['flight']:26s} " + "; ".join(parts) + weather)
    for model, g in summary.items():
        lines.append(f"{model}: {g['sent']} sent on {g['flights']} flights, {g['sent_safe']} safe "
                     f"({_share(g['sent_safe'], g['sent'])}; goal {100 * g['safe_goal']:.0f} %: "
                     f"{'met' if g['safe_met'] else 'NOT met'}); the network alone {g['network_alone']}, "
                     f"{g['network_alone_safe']} safe ({_share(g['network_alone_safe'], g['network_alone'])})")
        lines.append(f"{model}: targets on >= {100 * FRAMES_GOAL:.0f} % of frames on {g['flights_with_enough_targets']}"
                     f" of {g['flights']} flights ({'met' if g['frames_met'] else 'NOT met'})"
                     + (f"; at least its network alone's count on {g['flights_at_least_network']}"
                        if "flights_at_least_network" in g else "")
                     + (f"; unsafe targets on {', '.join(g['unsafe_flights'])}" if g["unsafe_flights"] else ""))
        ns = g.get("network_sent")
        if ns:
            lines.append(f"{model}: the network alone as edge-run --allow-unconfirmed sends it, on {ns['flights']} "
                         f"flights: {ns['targets']}, {ns['safe']} safe ({_share(ns['safe'], ns['targets'])}); "
                         f"at least its count on {ns['flights_at_least']}")
    return "\n".join(lines)


def _as_sent(row: dict[str, Any]) -> str:
    """', as sent N, safe M' for a row with the network alone as edge-run sends it (else '')."""
    return f", as sent {row['network_sent']}, safe {row['network_sent_safe']}" if "network_sent" in row else ""


def _said(flight: Flight, result: dict[str, Any]) -> str:
    row = flight_row(flight, result)
    return f"{flight.name}: " + ", ".join(f"{m} {row[m]['sent']} sent, {row[m]['sent_safe']} safe"
                                          for m in SAFE_GOAL if m in row)


def fly_set(cfg: SetConfig, progress: bool = True) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Every flight of ``cfg`` (earlier results reused), then the rows and the pooled goals."""
    results: dict[Flight, dict[str, Any]] = {}
    for f in cfg.flights:                 # every earlier file checked before any flight starts
        done = _finished(f, cfg)
        if done is not None:
            results[f] = done
    todo = [f for f in cfg.flights if f not in results]
    t0 = time.monotonic()
    if todo:
        # spawn: each replay starts clean (the renderer and the motion stage's thread are per process)
        with ProcessPoolExecutor(min(cfg.workers, len(todo)), mp_context=multiprocessing.get_context("spawn")) as pool:
            pending: dict[Future[dict[str, Any]], Flight] = {pool.submit(_fly, f, cfg): f for f in todo}
            try:
                while pending:
                    finished, _ = wait(pending, return_when=FIRST_COMPLETED)
                    for fut in finished:
                        flight = pending.pop(fut)
                        results[flight] = fut.result()
                        if progress:
                            print(f"[{len(results)}/{len(cfg.flights)}] {_said(flight, results[flight])} "
                                  f"({time.monotonic() - t0:.0f} s)", flush=True)
            except BaseException:
                for fut in pending:   # flights not started are not flown; finished files stay
                    fut.cancel()
                raise
    rows = [flight_row(f, results[f]) for f in cfg.flights]
    return rows, goals(rows)


def _main(argv: Optional[Sequence[str]] = None) -> int:
    p = CliParser(prog="flight_set", description=__doc__.split("\n\n")[0], extra="sim",
                  formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, help="folder for each flight's result and summary.json")
    p.add_argument("--set", choices=["validation"], help="the 42 validation flights")
    p.add_argument("--flights", nargs="+", default=[], help="STYLE:SEED[:APPROACH] flights (with or instead of --set)")
    p.add_argument("--approach", default="straight", help="approach of --set and of flights that name none: "
                   "straight or arc")
    p.add_argument("--models", nargs="+", default=["lying"], choices=list(SAFE_GOAL))
    p.add_argument("--frames", type=int, default=200)
    p.add_argument("--size", type=int, nargs=2, default=SimReader.DEFAULT_SIZE, metavar=("W", "H"))
    p.add_argument("--workers", type=int, default=2, help="flights replayed at once (one core each)")
    p.add_no_progress()
    a = p.parse_args(argv)
    from edge_landing.sim.flight import Approach

    approach = check_choice("--approach", Approach.from_string, a.approach).value
    flights = (validation_set(approach) if a.set else []) + [Flight.parse(t, approach) for t in a.flights]
    if not flights:
        raise InputError("no flights: give --set validation or --flights STYLE:SEED[:APPROACH] ...")
    if a.frames < 10:
        raise InputError(f"--frames must be at least 10, got {a.frames}")
    check_camera_size(a.size)
    check_threads("--workers", a.workers)
    cfg = SetConfig(tuple(dict.fromkeys(flights)), output_folder(a.out, "the --out folder"), tuple(a.models),
                    a.frames, a.size[0], a.size[1], a.workers)
    rows, summary = fly_set(cfg, progress=not a.no_progress)
    print(report(rows, summary))
    (cfg.out / "summary.json").write_text(json.dumps({"flights": rows, "goals": summary}, indent=1))
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    return run_cli(_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
