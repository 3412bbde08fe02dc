"""The motion stage beside the frame path (fusion.deferred, FusionConfig.geometry_timing).

Overlapped, a frame hands its stage run to a thread and the next fused frame adds the result: the same pair
results as inline, one fused frame later, on every run whatever the machine's speed; nothing unsafe from it.
"""
from __future__ import annotations

import subprocess
import sys
import threading

import numpy as np
import pytest

from edge_landing.runtime.fusion.deferred import DeferredRun, StageTiming
from edge_landing.runtime.fusion.fuser import FusionConfig, LandingFuser

sim = pytest.importorskip("edge_landing.sim")

from edge_landing.benchmarks.landing_truth import TruthConfig, check_target  # noqa: E402
from edge_landing.benchmarks.lying_model import lying_prediction  # noqa: E402
from tests.test_motion import INTR, MOUNT, _car_park, _frames  # noqa: E402


def test_inline_runs_at_submit_and_overlapped_on_another_thread():
    names = []

    def job() -> int:
        names.append(threading.current_thread().name)
        return 7

    inline = DeferredRun[int](StageTiming.INLINE, "geo")
    inline.submit(job)
    assert names == [threading.current_thread().name] and inline.pending
    done = inline.collect()
    assert done is not None and done.value == 7 and done.run_s >= 0 and not inline.pending
    assert inline.collect() is None                      # collected once

    over = DeferredRun[int](StageTiming.OVERLAPPED, "geo")
    gate = threading.Event()
    over.submit(lambda: (gate.wait(5.0), job())[1])
    assert over.pending and len(names) == 1              # still waiting on the gate: not run at submit
    gate.set()
    done = over.collect()                                # waits for the thread
    assert done is not None and done.value == 7 and names[-1] == "geo"


def test_a_failed_job_raises_once_at_collect_and_cancel_drops_a_result():
    run = DeferredRun[int](StageTiming.OVERLAPPED)

    def fail() -> int:
        raise ValueError("no flow")

    run.submit(fail)
    with pytest.raises(ValueError, match="no flow"):
        run.collect()
    assert run.collect() is None and not run.pending
    run.submit(lambda: 1)
    run.cancel()
    assert run.collect() is None


def _fly(timing: StageTiming, world, path):
    fuser = LandingFuser(FusionConfig(geometry_timing=timing), INTR, MOUNT)
    rows = []
    for k, t, r, state in _frames(world, path):
        target = fuser.update(lying_prediction(INTR, MOUNT, state, k), state, t, r.rgb)
        res = fuser.stage_result
        rows.append((target, fuser.geometry_ran, None if res is None else (res.time_s, res.height_m.copy())))
    return rows


def test_overlapped_geometry_adds_the_same_pairs_one_frame_later_and_stays_safe():
    """The car park pass: the overlapped stage's results are the inline ones, each on the next fused frame;
    two overlapped runs agree target for target; every target is on ground-truth safe ground."""
    world, path = _car_park()
    path = path[:60]
    inline = _fly(StageTiming.INLINE, world, path)
    over = _fly(StageTiming.OVERLAPPED, world, path)
    ran = [k for k, (_, did, _) in enumerate(inline) if did]
    assert len(ran) > 10 and ran == [k for k, (_, did, _) in enumerate(over) if did]
    for k in ran[:-1]:
        a, b = inline[k][2], over[k + 1][2]
        assert (a is None) == (b is None), k               # a run that measured nothing, on both sides
        if a is not None and b is not None:
            assert a[0] == b[0]
            np.testing.assert_array_equal(a[1], b[1])
    assert over[ran[0]][2] is None                         # not on the frame that ran it: on the next

    truth = TruthConfig(log="", clearance_m=FusionConfig().required_clearance_m)
    sent = [(k, t) for k, (t, _, _) in enumerate(over) if t.valid]
    first_inline = next(k for k, (t, _, _) in enumerate(inline) if t.valid)
    assert sent and sent[0][0] >= first_inline             # evidence never arrives sooner than inline
    for k, t in sent:
        assert t.evidence.startswith("geometry+network")
        ok, why = check_target(world, *t.position_ned_m[:2], truth)
        assert ok, (k, why)

    again = _fly(StageTiming.OVERLAPPED, world, path)
    assert [(t.valid, t.reason, None if t.position_ned_m is None else tuple(t.position_ned_m))
            for t, _, _ in again] == [(t.valid, t.reason, None if t.position_ned_m is None
                                       else tuple(t.position_ned_m)) for t, _, _ in over]


def test_reset_while_a_stage_run_is_in_flight_drops_it():
    world, path = _car_park()
    fuser = LandingFuser(FusionConfig(geometry_timing=StageTiming.OVERLAPPED), INTR, MOUNT)
    for k, t, r, state in _frames(world, path[:4]):
        fuser.update(lying_prediction(INTR, MOUNT, state, k), state, t, r.rgb)
    fuser.reset()
    assert fuser.stage_result is None and fuser.geometry is None and not fuser.motion.keyframes


def test_edge_run_overlaps_the_stage_unless_told_inline():
    from edge_landing.cli.run import config_from_args, fusion_config

    assert config_from_args([]).geometry_timing is StageTiming.OVERLAPPED
    assert config_from_args(["--geometry-timing", "inline"]).geometry_timing is StageTiming.INLINE
    assert fusion_config(config_from_args([])).motion.max_width_px == 1280
    assert fusion_config(config_from_args(["--geometry-width", "640"])).motion.max_width_px == 640


def test_a_run_in_flight_when_the_program_ends_is_finished_not_torn_down(tmp_path):
    """The last frame's run is never collected: the program waits for it at exit instead of tearing it down
    inside OpenCV (a daemon thread there while the interpreter shut down aborted replays, exit 134, on 2 of 3
    runs of a 30-frame one). The job here writes a file after the main program has ended."""
    done_file = tmp_path / "done"
    code = ("import time\n"
            "from edge_landing.runtime.fusion.deferred import DeferredRun, StageTiming\n"
            "run = DeferredRun(StageTiming.OVERLAPPED)\n"
            f"run.submit(lambda: (time.sleep(0.3), open({str(done_file)!r}, 'w').write('ok')))\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr[-500:]
    assert done_file.read_text() == "ok"
