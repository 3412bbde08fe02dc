"""The autopilot's local frame moves (an EKF reset, a GPS glitch, a reboot): NED positions before and after the
jump name different places, so nothing kept in local NED may survive it (ARCHITECTURE.md §12).

A jump starts a new ``VehicleState.position_epoch`` (runtime/io/telemetry.py); fusion starts over, a committed
spot is dropped and announced, and a target fused before the jump is not re-expressed after it.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from edge_landing.runtime.core.camera import Intrinsics, Mount
from edge_landing.runtime.core.messages import EVIDENCE_GEOMETRY, Target, VehicleState
from edge_landing.runtime.fusion.fuser import FusionConfig, LandingFuser
from edge_landing.runtime.io.telemetry import TelemetryBuffer
from edge_landing.runtime.pipeline.trust import Continuity, ContinuityConfig
from tests.test_trust import SWITCH_S, assets, run_against  # noqa: F401  (assets: the module's fixture)

JUMP = "position jumped (the autopilot's frame moved): earlier positions dropped"


def test_a_position_faster_than_flight_starts_a_new_epoch_and_drops_the_old_positions():
    buf = TelemetryBuffer()
    rng = np.random.default_rng(0)
    t = 0.0
    for i in range(60):                       # 3 s at 20 Hz, 15 m/s with 0.3 m of noise: flight, not a jump
        t = 100.0 + 0.05 * i
        buf.add_attitude(0.0, 0.0, 0.0, arrival_s=t, sample_s=t)
        buf.add_position(15.0 * 0.05 * i + rng.normal(0, 0.3), 0.0, -30.0, arrival_s=t, sample_s=t)
    state = buf.state_at(t)
    assert state is not None and state.position_epoch == 0 and JUMP not in buf.rejected()
    t += 0.05
    buf.add_attitude(0.0, 0.0, 0.0, arrival_s=t, sample_s=t)
    buf.add_position(15.0 * 3.0 + 60.0, 0.0, -30.0, arrival_s=t, sample_s=t)   # 60 m in 50 ms
    after = buf.state_at(t)
    assert after is not None and after.position_epoch == 1 and buf.rejected()[JUMP] == 1
    assert after.position_ned_m[0] == pytest.approx(105.0)
    # The positions before the jump are gone: a frame captured just before gets the nearest position of the new
    # frame (within the matching window), one captured earlier gets none; never one from the old frame.
    assert buf.state_at(t - 0.2).position_ned_m[0] == pytest.approx(105.0)
    assert buf.state_at(t - 0.5).position_ned_m is None
    # Far after a long silence is flight again (100 m in 10 s), and a reboot (forget) is a new frame too.
    buf.add_position(15.0 * 3.0 + 160.0, 0.0, -30.0, arrival_s=t + 10.0, sample_s=t + 10.0)
    assert buf.rejected()[JUMP] == 1
    buf.forget()
    buf.add_attitude(0.0, 0.0, 0.0, arrival_s=t + 11.0, sample_s=t + 11.0)
    buf.add_position(0.0, 0.0, -30.0, arrival_s=t + 11.0, sample_s=t + 11.0)
    assert buf.state_at(t + 11.0).position_epoch == 2


def test_a_reset_of_a_few_metres_is_told_from_flight_by_the_autopilots_own_velocity():
    """An EKF lane switch or a GPS glitch's recovery moves the local frame by a metre or a few in one step, well
    within what 40 m/s allows: LOCAL_POSITION_NED's own velocity tells it from flight."""
    buf, rng = TelemetryBuffer(), np.random.default_rng(1)

    def fly(t0_s: float, seconds: float, north0_m: float, v0_mps: float, accel_mps2: float, step_s: float = 0.05,
            velocity: bool = True) -> tuple:
        t, north, v = t0_s, north0_m, v0_mps
        for _ in range(int(round(seconds / step_s))):
            t, north, v = t + step_s, north + v * step_s + 0.5 * accel_mps2 * step_s ** 2, v + accel_mps2 * step_s
            buf.add_attitude(0.0, 0.0, 0.0, arrival_s=t, sample_s=t)
            buf.add_position(north + rng.normal(0, 0.05), 0.0, -30.0, arrival_s=t, sample_s=t,
                             velocity_ned_mps=(v + rng.normal(0, 0.1), 0.0, 0.0) if velocity else None)
        return t, north, v

    # Flight: 3 s accelerating at 5 m/s² to 15 m/s, 2 s braking hard at 12 m/s², samples 0.6 s apart at 8 m/s².
    t, north, v = fly(100.0, 3.0, 0.0, 0.0, 5.0)
    t, north, v = fly(t, 1.0, north, v, -12.0)
    t, north, v = fly(t, 1.8, north, v, 8.0, step_s=0.6)
    assert JUMP not in buf.rejected() and buf.newest_state().position_epoch == 0
    # A 2 m reset sideways while flying at 17 m/s, the velocity smooth across it: a new epoch.
    t += 0.05
    north += v * 0.05
    buf.add_position(north, 2.0, -30.0, arrival_s=t, sample_s=t, velocity_ned_mps=(v, 0.0, 0.0))
    assert buf.rejected()[JUMP] == 1 and buf.state_at(t).position_epoch == 1
    # Without velocities (a source that sends none) such a step is not caught: the 5 m / 40 m/s rule alone.
    t, north, v = fly(t, 0.5, north, v, 0.0, velocity=False)
    buf.add_position(north + v * 0.05, 4.0, -30.0, arrival_s=t + 0.05, sample_s=t + 0.05)
    assert buf.rejected()[JUMP] == 1


def test_a_step_of_the_clock_offset_is_not_taken_for_a_reset():
    """LOCAL_POSITION_NED at 20 Hz, 12 m/s, that first arrives 0.25 s late and then 0.13 s late: the clock offset
    follows the faster samples at once, so their local times step back by 0.12 s, and the local interval between the
    last slow sample and the first fast one kept is 30 ms, not the 150 ms they were apart. The reset check reads the
    autopilot's own stamps (1.4 m off at 12 m/s otherwise)."""
    buf = TelemetryBuffer()
    for k in range(120):
        remote_ms = 600_000 + 50 * k
        arrival_s = 100.0 + 0.05 * k + (0.25 if k < 60 else 0.13)
        north = 12.0 * 0.05 * k
        buf.add_attitude(0.0, 0.0, 0.0, remote_ms, arrival_s=arrival_s)
        buf.add_position(north, 0.0, -30.0, remote_ms, arrival_s=arrival_s, velocity_ned_mps=(12.0, 0.0, 0.0))
    assert JUMP not in buf.rejected() and buf.newest_state().position_epoch == 0
    assert buf.newest_state().position_ned_m[0] == pytest.approx(12.0 * 0.05 * 119)
    # Not vacuous: the same flight with one 2 m step sideways is a reset.
    buf.add_position(12.0 * 0.05 * 120, 2.0, -30.0, 600_000 + 50 * 120, arrival_s=100.0 + 0.05 * 120 + 0.13,
                     velocity_ned_mps=(12.0, 0.0, 0.0))
    assert buf.rejected()[JUMP] == 1


def test_velocities_that_do_not_describe_the_positions_are_not_believed_after_three_resets(caplog):
    """A source that sends zero velocities while flying (a partial MAVLink implementation) at 4 Hz and 5 m/s: each
    1.25 m step looks like a reset. After three within 10 s the velocities are not used, and said so; before the
    fallback, fusion would have started over on every sample."""
    buf = TelemetryBuffer()
    for k in range(20):
        t = 50.0 + 0.25 * k
        buf.add_attitude(0.0, 0.0, 0.0, arrival_s=t, sample_s=t)
        buf.add_position(1.25 * k, 0.0, -30.0, arrival_s=t, sample_s=t, velocity_ned_mps=(0.0, 0.0, 0.0))
    assert buf.rejected()[JUMP] == 3 and buf.newest_state().position_epoch == 3
    assert "does not describe its positions" in caplog.text


def test_a_reboot_starts_a_new_epoch_even_without_a_jump():
    """A rebooted autopilot (its time_boot_ms restarts) sets its origin again: even a position close to the last
    one may name another place, so the epoch moves on."""
    buf = TelemetryBuffer()
    for i in range(20):
        buf.add_attitude(0.0, 0.0, 0.0, 600_000 + 50 * i, arrival_s=50.0 + 0.05 * i)
        buf.add_position(1.0, 2.0, -30.0, 600_000 + 50 * i, arrival_s=50.0 + 0.05 * i)
    assert buf.newest_state().position_epoch == 0
    for i in range(45):      # booted 2 s ago; a clock that stays behind for a window (2 s) has restarted
        buf.add_attitude(0.0, 0.0, 0.0, 2_000 + 50 * i, arrival_s=51.05 + 0.05 * i)
        buf.add_position(1.5, 2.0, -30.0, 2_000 + 50 * i, arrival_s=51.05 + 0.05 * i)
    state = buf.newest_state()
    assert state.position_epoch == 1 and state.position_ned_m[0] == pytest.approx(1.5)
    assert buf.rejected()["autopilot rebooted (its clock restarted): every earlier sample dropped"] == 1


def test_a_committed_spot_is_dropped_when_the_frame_moves():
    state = VehicleState(0.0, position_ned_m=np.array([0.0, 0.0, -30.0]), agl_m=30.0)
    spot = np.array([8.0, 0.0, 0.0])
    cont = Continuity(ContinuityConfig())
    for i in range(3):
        cont.step(Target(i, float(i), True, position_body_frd_m=spot - state.position_ned_m, position_ned_m=spot,
                         clearance_m=3.0, confidence=0.9, evidence=EVIDENCE_GEOMETRY), state, None, True)
    held, said = cont.step(Target.none(3, 3.0, "no safe spot"), state, None, True)
    assert cont.spot is not None and held.valid and said == ""          # not vacuous: it is re-sent
    moved = VehicleState(4.0, position_ned_m=np.array([60.0, 0.0, -30.0]), agl_m=30.0, position_epoch=1)
    out, said = cont.step(Target.none(4, 4.0, "no safe spot"), moved, None, True)
    assert not out.valid and cont.spot is None
    assert said == "spot dropped: position or heading jumped" and len(said) <= 50   # one STATUSTEXT message
    out, said = cont.step(Target.none(5, 5.0, "no safe spot"), moved, None, True)
    assert not out.valid and said == ""


def test_fusion_starts_over_in_the_new_frame():
    """After a jump the grid holds this frame's evidence only: the same as a fuser that never saw the old frame."""
    from tests.test_link_safety import AGL_M, _ground_prediction, ground_plane_depth

    intr, mount = Intrinsics.from_hfov(64, 48, math.radians(90.0)), Mount(pitch_rad=math.radians(-45.0))
    depth = ground_plane_depth(48, 64, AGL_M, mount)
    old, fresh = LandingFuser(FusionConfig(), intr, mount), LandingFuser(FusionConfig(), intr, mount)
    for i in range(5):      # flying north at 5 m/s in the old frame
        state = VehicleState(0.1 * i, position_ned_m=np.array([0.5 * i, 0.0, -AGL_M]), agl_m=AGL_M)
        old.fuse(_ground_prediction(i, 0.1 * i, depth), state, 0.1 * i)
    jumped = VehicleState(0.5, position_ned_m=np.array([62.5, 0.0, -AGL_M]), agl_m=AGL_M, position_epoch=1)
    kept = old.fuse(_ground_prediction(5, 0.5, depth), jumped, 0.5).grid
    alone = fresh.fuse(_ground_prediction(5, 0.5, depth), jumped, 0.5).grid
    assert kept is not None and alone is not None and alone.observed.any()
    np.testing.assert_array_equal(kept.observed, alone.observed)
    np.testing.assert_array_equal(kept.votes, alone.votes)
    # Not vacuous: without the epoch change the old frame's evidence is still in the grid.
    same = LandingFuser(FusionConfig(), intr, mount)
    for i in range(5):
        state = VehicleState(0.1 * i, position_ned_m=np.array([0.5 * i, 0.0, -AGL_M]), agl_m=AGL_M)
        same.fuse(_ground_prediction(i, 0.1 * i, depth), state, 0.1 * i)
    near = VehicleState(0.5, position_ned_m=np.array([2.5, 0.0, -AGL_M]), agl_m=AGL_M)
    assert same.fuse(_ground_prediction(5, 0.5, depth), near, 0.5).grid.observed.sum() > alone.observed.sum()


def test_edge_run_sends_no_committed_spot_across_a_position_jump(assets, tmp_path):  # noqa: F811
    """The autopilot's position jumps 60 m north (an EKF reset) while the vehicle hovers: the spot committed in
    the old frame, re-expressed from the new position, would go out 60 m behind the vehicle. It is dropped and
    announced; what goes out after the jump is fused in the new frame, where the spot still is (ahead)."""
    def script(fake, t: float) -> None:
        fake.healthy(ned=(5.0, -3.0, -10.0) if t < SWITCH_S else (65.0, -3.0, -10.0))

    fake, decisions, _ = run_against(assets, tmp_path, script, 5.0)
    before = fake.targets_between(0.0, SWITCH_S)
    assert len(before) >= 5 and any(d.get("committed_ned_m") is not None for d in decisions)
    ahead = float(np.median([t.x for t in before]))
    assert ahead > 2.0
    after = fake.targets_between(SWITCH_S + 0.5, 1e9)
    assert len(after) >= 5                                               # not vacuous: targets still go out
    assert all(abs(t.x - ahead) < 1.0 for t in after), sorted({round(t.x) for t in after})
    assert any("spot dropped: position or heading jumped" in text for text in fake.texts())


def test_edge_run_drops_the_committed_spot_on_a_reset_of_a_few_metres(assets, tmp_path):  # noqa: F811
    """The same as a 60 m jump, for a 2.5 m reset (inside the 5 m / 40 m/s rule) that LOCAL_POSITION_NED's own
    velocity (zero: hovering) gives away. Before, the spot stayed committed in the moved frame and went out
    re-expressed 2.5 m short of where it is."""
    def script(fake, t: float) -> None:
        fake.healthy(ned=(5.0, -3.0, -10.0) if t < SWITCH_S else (7.5, -3.0, -10.0), vel=(0.0, 0.0, 0.0))

    fake, decisions, _ = run_against(assets, tmp_path, script, 5.0)
    before = fake.targets_between(0.0, SWITCH_S)
    assert len(before) >= 5 and any(d.get("committed_ned_m") is not None for d in decisions)
    ahead = float(np.median([t.x for t in before]))
    after = fake.targets_between(SWITCH_S + 0.5, 1e9)
    assert len(after) >= 5
    assert all(abs(t.x - ahead) < 1.0 for t in after), sorted({round(t.x, 1) for t in after})
    assert any("spot dropped: position or heading jumped" in text for text in fake.texts())


def test_a_target_captured_before_a_jump_is_not_re_expressed_after_it():
    """Between capture and send the frame moved: the target's NED point would be re-expressed from a position in
    the other frame, so it is held back (the next frame is fused in the new one)."""
    from types import SimpleNamespace

    from edge_landing.runtime.pipeline.loop import Pipeline, PipelineOptions

    buf = TelemetryBuffer()
    for k, north in enumerate((0.0, 0.5, 1.0, 61.5)):            # the last sample jumped 60 m
        t = 10.0 + 0.1 * k
        buf.add_attitude(0.0, 0.0, 0.0, arrival_s=t)
        buf.add_position(north, 0.0, -30.0, arrival_s=t)
    capture = VehicleState(10.0, position_ned_m=np.array([0.0, 0.0, -30.0]), agl_m=30.0)     # epoch 0
    assert buf.newest_state().position_epoch == 1
    spot = np.array([10.0, 0.0, 0.0])
    target = Target(1, 10.0, True, position_body_frd_m=np.array([10.0, 0.0, 30.0]), position_ned_m=spot,
                    clearance_m=3.0, confidence=0.9, evidence=EVIDENCE_GEOMETRY)
    holder = SimpleNamespace(telemetry=buf, options=PipelineOptions(mount=Mount()))
    out, _ = Pipeline._at_newest_pose(holder, target, capture)    # type: ignore[arg-type]
    assert not out.valid and "frame moved" in out.reason
    same = VehicleState(10.3, position_ned_m=np.array([61.5, 0.0, -30.0]), agl_m=30.0, position_epoch=1)
    out, _ = Pipeline._at_newest_pose(holder, target, same)       # type: ignore[arg-type]
    assert out.valid                                              # not vacuous: same frame, re-expressed


def test_a_heading_reset_starts_a_new_epoch_but_a_fast_turn_does_not():
    """An EKF yaw reset turns the heading 30° between two samples: evidence placed in NED with the old heading is
    rotated about the vehicle, so the epoch moves on. A 180°/s turn across ±180° is flight."""
    buf = TelemetryBuffer()
    t, yaw = 0.0, 0.0
    for i in range(40):                                    # 2 s at 20 Hz turning at 180°/s, wrapping at ±180°
        t, yaw = 20.0 + 0.05 * i, math.remainder(math.pi * 0.05 * i + 2.5, 2 * math.pi)
        buf.add_attitude(0.0, 0.0, yaw, arrival_s=t, sample_s=t)
        buf.add_position(0.0, 0.0, -30.0, arrival_s=t, sample_s=t)
    assert buf.newest_state().position_epoch == 0
    buf.add_attitude(0.0, 0.0, yaw + math.radians(30.0), arrival_s=t + 0.05, sample_s=t + 0.05)
    assert buf.newest_state().position_epoch == 1
    assert buf.rejected()["heading jumped (a yaw reset): earlier attitudes dropped"] == 1


def test_the_autopilots_own_estimator_status_is_believed():
    """EKF_STATUS_REPORT / ESTIMATOR_STATUS: without a usable horizontal position (dead reckoning, a GPS glitch)
    frames get no position, so nothing is placed in local NED; without a usable attitude there is no telemetry.
    A status older than estimator_status_s no longer counts; an autopilot that sends none is believed."""
    from edge_landing.runtime.io.telemetry import ESTIMATOR_ATTITUDE, ESTIMATOR_CONST_POS_MODE, ESTIMATOR_POS_HORIZ_REL

    good = ESTIMATOR_ATTITUDE | ESTIMATOR_POS_HORIZ_REL
    buf = TelemetryBuffer()
    for i in range(10):
        t = 30.0 + 0.05 * i
        buf.add_attitude(0.0, 0.0, 0.0, arrival_s=t, sample_s=t)
        buf.add_position(0.1 * i, 0.0, -30.0, arrival_s=t, sample_s=t)
    now = 30.45
    assert buf.lookup(now, now).state.position_ned_m is not None          # no status at all: believed
    buf.add_estimator_status(good, arrival_s=now)
    assert buf.lookup(now, now).state.position_ned_m is not None
    buf.add_estimator_status(good | ESTIMATOR_CONST_POS_MODE, arrival_s=now)
    match = buf.lookup(now, now)
    assert match.fresh and match.state.position_ned_m is None            # attitude still used, position not
    buf.add_estimator_status(ESTIMATOR_ATTITUDE, arrival_s=now)          # no relative horizontal position
    assert buf.lookup(now, now).state.position_ned_m is None
    buf.add_estimator_status(good | 32768, arrival_s=now, glitch_flag=32768)   # ArduPilot's EKF_GPS_GLITCHING
    assert buf.lookup(now, now).state.position_ned_m is None
    buf.add_estimator_status(ESTIMATOR_POS_HORIZ_REL, arrival_s=now)     # attitude not usable: no telemetry
    match = buf.lookup(now, now)
    assert not match.fresh and "attitude not usable" in match.reason
    assert buf.rejected()["the autopilot's estimator: horizontal position not usable"] == 3
    buf.add_attitude(0.0, 0.0, 0.0, arrival_s=now + 3.5, sample_s=now + 3.5)
    buf.add_position(1.0, 0.0, -30.0, arrival_s=now + 3.5, sample_s=now + 3.5)
    assert buf.lookup(now + 3.5, now + 3.5).state.position_ned_m is not None   # the status is 3.5 s old


def test_edge_run_holds_no_spot_while_the_autopilot_dead_reckons(assets, tmp_path):  # noqa: F811
    """The autopilot loses GPS and dead-reckons (EKF_STATUS_REPORT without a relative horizontal position) while
    its local position drifts: the spot committed before is not re-sent from that position; it is dropped."""
    def script(fake, t: float) -> None:
        m = fake.mavutil.mavlink
        if t < SWITCH_S:
            fake.healthy()
            fake.conn.mav.ekf_status_report_send(m.EKF_ATTITUDE | m.EKF_POS_HORIZ_REL | m.EKF_POS_HORIZ_ABS,
                                                 0.1, 0.1, 0.1, 0.1, 0.0)
        else:
            fake.healthy(ned=(5.0 + 3.0 * (t - SWITCH_S), -3.0, -10.0))   # drifting at 3 m/s
            fake.conn.mav.ekf_status_report_send(m.EKF_ATTITUDE | m.EKF_CONST_POS_MODE, 0.1, 5.0, 0.1, 0.1, 0.0)

    fake, decisions, _ = run_against(assets, tmp_path, script, 5.0)
    assert len(fake.targets_between(0.0, SWITCH_S)) >= 5
    assert any(d.get("committed_ned_m") is not None for d in decisions)  # not vacuous: a spot was committed
    assert any("spot dropped" in text for text in fake.texts())
    # From the first frame the estimator's word reached, nothing sent uses the local position or the spot.
    first = next(i for i, d in enumerate(decisions) if d["telemetry"] and d["valid"] and d["ned_m"] is None)
    after = [d for d in decisions[first:] if d["sent"]]
    assert len(after) >= 5 and all(d["ned_m"] is None and d["committed_ned_m"] is None for d in after)


def test_px4_estimator_status_without_a_position_sends_no_local_ned_target(assets, tmp_path):  # noqa: F811
    """PX4's ESTIMATOR_STATUS says the horizontal position is not usable (a GPS glitch): PX4 takes targets in
    LOCAL_NED only, so with no trusted position nothing goes out, rather than a point in a frame it doubts."""
    def script(fake, t: float) -> None:
        m = fake.mavutil.mavlink
        fake.healthy()
        good = m.ESTIMATOR_ATTITUDE | m.ESTIMATOR_POS_HORIZ_REL | m.ESTIMATOR_POS_HORIZ_ABS
        flags = good if t < SWITCH_S else good | m.ESTIMATOR_GPS_GLITCH
        fake.conn.mav.estimator_status_send(0, flags, 0.1, 0.1, 0.1, 0.1, 0.1, 0.0, 0.5, 0.5)

    fake, decisions, _ = run_against(assets, tmp_path, script, 5.0, "--autopilot", "px4")
    assert len(fake.targets_between(0.0, SWITCH_S)) >= 5                 # not vacuous: PX4 targets went out
    assert fake.targets_between(SWITCH_S + 0.5, 1e9) == []
    assert any(d["telemetry"] and not d["sent"] for d in decisions[-10:])
