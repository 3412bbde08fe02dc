"""One job at a time, run where it was submitted or on its own thread and collected at the next frame.

The motion stage costs about three times fusion's own work per run (DIS dominates) and runs on every other
frame at 10 frames/s; inline it adds that to the capture-to-send latency of those frames, which ArduPilot
cannot compensate (PLND_LAG is one fixed value). Overlapped, a frame hands the job to a thread and the next
fused frame collects its result first, before anything reads the evidence: the result always lands on the
same frame whatever the machine's speed, so replays repeat, and evidence is one fused frame later (memory is
seconds). The CPU time is the same; a 2-core computer paced by its camera has it spare between frames.

At most one job is in flight (the next submit waits for nothing: collect comes first); memory bounded.
No I/O.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Callable, Generic, Optional, TypeVar, Union

from edge_landing.runtime.core.choices import ChoiceEnum

T = TypeVar("T")


class StageTiming(ChoiceEnum):
    INLINE = "inline"            # the job runs inside the frame that submitted it
    OVERLAPPED = "overlapped"    # on its own thread; its result is collected by the next frame

    @classmethod
    def _label(cls) -> str:
        return "--geometry-timing value"


@dataclass(frozen=True)
class Done(Generic[T]):
    """A collected job: its value, and how long it ran (seconds, wall clock on its thread)."""

    value: T
    run_s: float


class DeferredRun(Generic[T]):
    """Runs submitted jobs inline or on a thread; ``collect`` hands back the one job submitted before it.

    A job's exception is raised again by ``collect`` (as it would have been inline), once."""

    def __init__(self, timing: StageTiming, name: str = "deferred"):
        self.timing = timing
        self._name = name
        self._thread: Optional[threading.Thread] = None
        self._box: list[Union[Done[T], Exception]] = []   # filled by the job's thread

    @property
    def pending(self) -> bool:
        return self._thread is not None or bool(self._box)

    def submit(self, job: Callable[[], T]) -> None:
        """Start ``job`` (inline: run it now). A job still uncollected is waited for and dropped first."""
        self.cancel()
        box: list[Union[Done[T], Exception]] = []

        def work() -> None:
            t0 = time.perf_counter()
            try:
                value = job()
            except Exception as exc:  # handed to collect: the frame that collects it decides
                box.append(exc)
            else:
                box.append(Done(value, time.perf_counter() - t0))

        self._box = box
        if self.timing is StageTiming.INLINE:
            work()
            return
        # Not a daemon: a run still in flight when the program ends is waited for (tens of milliseconds). A daemon
        # thread inside OpenCV or numpy while the interpreter shuts down aborted the process (exit 134).
        self._thread = threading.Thread(target=work, name=self._name, daemon=False)
        self._thread.start()

    def collect(self) -> Optional[Done[T]]:
        """The result of the job submitted last (waiting for it), or None when none is pending."""
        self._join()
        box, self._box = self._box, []
        if not box:
            return None
        item = box[0]
        if isinstance(item, Exception):
            raise item
        return item

    def cancel(self) -> None:
        """Wait for a job in flight and drop its result (and its exception)."""
        self._join()
        self._box = []

    def _join(self) -> None:
        if self._thread is not None:
            self._thread.join()
            self._thread = None
