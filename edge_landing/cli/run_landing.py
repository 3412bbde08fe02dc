"""edge-run's landing flags: the clearance a spot needs and how motion geometry confirms it (ARCHITECTURE.md §11)."""
from __future__ import annotations

import argparse


def add_landing_arguments(parser: argparse.ArgumentParser) -> None:
    """edge-run's "landing" group: the vehicle's size, the grid, and the motion-geometry stage's settings."""
    f = parser.add_argument_group("landing")
    f.add_argument("--vehicle-radius", type=float, default=1.0, help="metres")
    f.add_argument("--margin", type=float, default=1.0, help="extra clearance, metres")
    f.add_argument("--grid", default="ned", help="ned: keep the landing grid in local NED across frames when the "
                   "vehicle position is known (default); frame: a fresh grid around the vehicle every frame")
    f.add_argument("--obstacle-height", type=float, default=0.5, help="metres: a spot is confirmed only when the "
                   "drone's own motion could have seen an obstacle this tall there and saw none")
    f.add_argument("--allow-unconfirmed", action="store_true", help="also send spots only the network vouches "
                   "for (no motion geometry, e.g. still images); marked 'network only' in the log")
    f.add_argument("--geometry-timing", default="overlapped", help="overlapped (default): a frame's motion "
                   "geometry is measured on its own thread while the next frame is inferred, and that frame uses "
                   "it, so the stage does not lengthen any frame's capture-to-send latency; inline: before the "
                   "frame's own target (one frame sooner, the stage's time added to that frame's latency)")
    f.add_argument("--geometry-width", type=int, default=1280, help="pixels: motion geometry measures camera frames "
                   "up to this wide at their own resolution (wider ones are scaled down first). 1280 (default) "
                   "resolves obstacles half as wide as 640 does from the same range, but its window (120x160 px) then "
                   "covers a quarter of the ground, so fewer spots get confirmed")
