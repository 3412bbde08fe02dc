"""How many threads the libraries beside the network may start (ARCHITECTURE.md §9).

On a 2-core companion computer the network's runtime already uses both cores. OpenCV's parallel loops and
numpy's OpenBLAS each start a pool of their own as well, and their idle threads spin while they wait for work:
that is CPU the network does not get, for little gain on the small arrays fusion works on. Their decisions do
not depend on the number of threads.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
from threadpoolctl import threadpool_limits


@dataclass(frozen=True)
class SideThreads:
    """Threads for OpenCV and BLAS; 0 leaves a library's own default."""

    opencv: int = 1
    blas: int = 1


def limit_side_threads(config: SideThreads = SideThreads()) -> None:
    """Apply ``config`` to this process (both libraries read it at every call, so it takes effect at once)."""
    if config.opencv > 0:
        cv2.setNumThreads(config.opencv)
    if config.blas > 0:
        threadpool_limits(limits=config.blas, user_api="blas")
