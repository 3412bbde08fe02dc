"""Image-only pose fallback of motion geometry (ARCHITECTURE.md §11) on ray-cast renders of a known world.

When telemetry has attitude and height above ground but no position, fusion.image_motion estimates the
translation between frames from tracked ground features (RANSAC homography, attitude-constrained least
squares, metric from the height). The worlds are real sim worlds (tests/test_motion.py builds them).
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from edge_landing.runtime.core.camera import Attitude
from edge_landing.runtime.core.messages import EVIDENCE_GEOMETRY, EVIDENCE_IMAGE_POSE
from edge_landing.runtime.fusion.fuser import FusionConfig, LandingFuser
from edge_landing.runtime.fusion.image_motion import ImagePoseConfig, estimate_translation
from edge_landing.runtime.fusion.motion import POSE_IMAGE, POSE_TELEMETRY, CameraPose, MotionConfig, MotionStage
from edge_landing.runtime.pipeline.trust import HELD, Continuity

sim = pytest.importorskip("edge_landing.sim", reason="the sim extra (embreex) renders the test worlds")
from edge_landing.benchmarks.landing_truth import TruthConfig, check_target  # noqa: E402
from edge_landing.benchmarks.lying_model import lying_prediction  # noqa: E402
from tests.test_motion import EFFECTS, FPS, INTR, MOUNT, _flat_world, _frames  # noqa: E402

CFG = ImagePoseConfig()


def _views(world, poses):
    """(grey at the motion stage's size, CameraPose) per (position, attitude)."""
    stage = MotionStage(MotionConfig(), INTR, MOUNT)
    renderer = sim.Renderer(world, INTR, MOUNT)
    rng = np.random.default_rng(1)
    out = []
    for p, att in poses:
        p = np.asarray(p, np.float64)
        r = renderer.render(p, att, EFFECTS, rng)
        out.append((stage.grey(r.rgb), CameraPose.of(MOUNT, att, p, float(-p[2]))))
    return stage, out


def _estimate(stage, a, b, **kw):
    (g0, p0), (g1, p1) = a, b
    return estimate_translation(g0, g1, stage.k_cv, p0.r_nc, p1.r_nc, p1.agl_m, kw.pop("cfg", CFG), **kw)


def test_translation_from_images_matches_the_truth():
    """Pairs over a grass field with a few boxes, attitude changing between frames: the recovered translation is
    within 0.1 m + 1 % of the baseline of the rendered one (stated tolerance), quality figures say so."""
    world = _flat_world([[30.0, 10.0, 2.0, 1.0, 1.5], [45.0, -8.0, 2.2, 0.9, 1.5]])
    poses = [((0.0, 0.0, -40.0), Attitude(0.0, 0.0, 0.3)),
             ((1.0, 0.3, -40.5), Attitude(0.02, -0.03, 0.32)),
             ((6.0, 2.0, -39.0), Attitude(-0.03, 0.02, 0.25)),
             ((12.0, -3.0, -40.0), Attitude(0.01, 0.04, 0.35))]
    stage, views = _views(world, poses)
    for i in (1, 2, 3):
        truth = views[i][1].position_ned_m - views[0][1].position_ned_m
        est = _estimate(stage, views[0], views[i], prior_delta_ned_m=None if i < 3 else truth + 0.5)
        assert est.ok, est.reason
        err = float(np.linalg.norm(est.delta_ned_m - truth))
        assert err <= 0.1 + 0.01 * float(np.linalg.norm(truth)), (i, est.delta_ned_m, truth)
        assert est.inliers >= CFG.min_inliers and est.inlier_share >= 0.5 and est.residual_px < 0.5
        assert 0 < est.sigma_m < 0.1 and est.scale_sigma_rel == CFG.agl_sigma_rel


def test_degenerate_inputs_give_a_reason_not_an_exception():
    world = _flat_world([[30.0, 10.0, 2.0, 1.0, 1.5]])
    poses = [((0.0, 0.0, -40.0), Attitude(0.0, 0.0, 0.3)), ((6.0, 2.0, -40.0), Attitude(0.0, 0.0, 0.3))]
    stage, views = _views(world, poses)
    (g0, p0), (g1, p1) = views
    blank = np.full_like(g0, 128)
    est = _estimate(stage, (blank, p0), (blank, p1))
    assert not est.ok and est.reason.startswith("too few features") and np.all(np.isnan(est.delta_ned_m))
    assert "too few features" in est.describe()
    assert not _estimate(stage, (g0[:100], p0), views[1]).ok                 # sizes differ
    bad = estimate_translation(g0, g1, stage.k_cv, p0.r_nc, p1.r_nc, float("nan"), CFG)
    assert not bad.ok and "height above ground" in bad.reason
    # An attitude the images contradict (yaw off by 4°) is refused, not turned into a translation.
    wrong = CameraPose.of(MOUNT, Attitude(0.0, 0.0, 0.3 + math.radians(4.0)), p1.position_ned_m, p1.agl_m)
    est = _estimate(stage, views[0], (g1, wrong))
    assert not est.ok and "inconsistent with the attitude" in est.reason, est.describe()


def test_image_pose_never_makes_detection_easier_than_telemetry():
    """The same pair measured with telemetry positions and with the image pose: the image pose's detectable
    heights are never smaller (its baseline error and height scale error are added)."""
    world = _flat_world([[30.0, 0.0, 2.0, 2.0, 1.5]])
    att = Attitude(0.0, 0.0, 0.0)
    stage, views = _views(world, [((0.0, -3.0, -30.0), att), ((0.0, 3.0, -30.0), att)])
    results = {}
    for source in (POSE_TELEMETRY, POSE_IMAGE):
        motion = MotionStage(MotionConfig(), INTR, MOUNT)
        for k, (grey, pose) in enumerate(views):
            if source == POSE_IMAGE:
                pose = replace(pose, position_ned_m=np.full(3, np.nan))
            results[source] = motion.update(grey, pose, 0.5 * k, focus_ned_m=np.array([30.0, 0.0, 0.0]))
    tel, img = results[POSE_TELEMETRY], results[POSE_IMAGE]
    assert tel is not None and img is not None, motion.last_reason
    assert tel.pose_source == POSE_TELEMETRY and img.pose_source == POSE_IMAGE and img.pose_sigma_m > 0
    assert img.baseline_m == pytest.approx(6.0, abs=0.1)
    both = np.isfinite(tel.detectable_m) & np.isfinite(img.detectable_m)
    assert both.sum() > 1000
    ratio = img.detectable_m[both] / tel.detectable_m[both]
    assert float(np.median(ratio)) >= 1.0 + 2.0 * CFG.agl_sigma_rel, float(np.median(ratio))


def test_hover_without_position_gives_no_baseline_and_no_confirmation():
    world = _flat_world([[30.0, 10.0, 2.0, 1.0, 1.5]])
    hover = [(0.05 * math.sin(k), 0.05 * math.cos(k), -30.0) for k in range(12)]
    fuser = LandingFuser(FusionConfig(), INTR, MOUNT)
    targets = []
    for k, t, r, state in _frames(world, hover):
        pred = lying_prediction(INTR, MOUNT, state, k)
        targets.append(fuser.update(pred, replace(state, position_ned_m=None), t, r.rgb))
        est = fuser.motion.image_pose
        if k > 0:        # the frames are placed by the images, within centimetres of where they are
            assert fuser.motion.position_ned_m is not None
            drift = fuser.motion.position_ned_m - (np.asarray(hover[k]) - np.asarray(hover[0]))
            assert float(np.linalg.norm(drift[:2])) < 0.1, (k, drift, est.describe() if est else None)
    assert not any(t.valid for t in targets)
    assert all(t.reason.startswith("unconfirmed: geometry") for t in targets[1:]), targets[-1].reason


def test_flight_without_position_confirms_only_safe_spots():
    """The low pass of tests/test_motion.py (lying model, field of parked cars and a block) with telemetry that
    has attitude and height but no position: geometry from the image pose still confirms spots, every one on
    ground-truth safe ground (ray casting), and the evidence says the baseline came from the images. Continuity
    (ARCHITECTURE.md §12) commits a spot in the odometry's frame; what it sends, held targets included, points
    at safe ground and carries no local NED (the odometry's frame is not the autopilot's)."""
    cars = [[n, e, 2.2, 0.9, 1.5] for n in np.arange(15.0, 45.0, 5.0) for e in (-12.0, -6.0, 0.0, 6.0)]
    world = _flat_world(cars + [[30.0, 18.0, 6.0, 5.0, 6.0]])
    path = [(-14.0 + 0.3 * k, -3.0 + 2.0 * math.sin(0.2 * k), -25.0) for k in range(60)]
    truth = TruthConfig(log="", clearance_m=FusionConfig().required_clearance_m)
    fuser = LandingFuser(FusionConfig(), INTR, MOUNT)
    continuity = Continuity()
    confirmed, sent, held = 0, 0, 0
    for k, t, r, state in _frames(world, path):
        pred = lying_prediction(INTR, MOUNT, state, k)
        seen = replace(state, position_ned_m=None)
        result = fuser.fuse(pred, seen, t, r.rgb)
        target = result.target
        if k > 0:
            assert result.placement is not None and result.placement.odometry_epoch == 1, (k, result.placement)
        if target.valid:
            confirmed += 1
            assert target.evidence.startswith(f"{EVIDENCE_GEOMETRY}; {EVIDENCE_IMAGE_POSE}"), target.evidence
            assert target.position_ned_m is None and target.geometry_baseline_m > 0
            assert target.geometry_detectable_m <= FusionConfig().obstacle_height_m
            _assert_safe(world, state, target, truth, k)
        out, said = continuity.step(target, seen, result.grid, True, result.placement)
        assert said == "", (k, said)
        if out.valid:
            sent += 1
            held += out.reason.startswith(HELD)
            assert out.position_ned_m is None
            _assert_safe(world, state, out, truth, k)
    assert confirmed >= 10, confirmed
    assert continuity.spot is not None and not continuity.in_telemetry_frame()
    assert sent >= confirmed and held > 0, (sent, confirmed, held)


def _assert_safe(world, state, target, truth, k):
    """The target is judged where it points from the true pose (the autopilot flies the body vector)."""
    ned = state.position_ned_m + state.attitude.ned_from_body() @ target.position_body_frd_m
    ok, why = check_target(world, float(ned[0]), float(ned[1]), truth)
    assert ok, (k, target.reason, why)


def test_short_position_dropout_is_chained_from_the_last_telemetry_position():
    """Telemetry position for 1 s, then 1 s without: the frames are placed in the telemetry's frame (anchored),
    within 0.2 m of the truth, and geometry keeps measuring (pose source "image")."""
    world = _flat_world([[30.0, 10.0, 2.0, 1.0, 1.5]])
    path = [(-10.0 + 0.4 * k, 1.0 * math.sin(0.2 * k), -30.0) for k in range(20)]
    motion = MotionStage(MotionConfig(), INTR, MOUNT)
    sources = []
    for k, t, r, state in _frames(world, path):
        pose = CameraPose.of(MOUNT, state.attitude, state.position_ned_m, state.agl_m)
        if k >= 10:
            pose = replace(pose, position_ned_m=np.full(3, np.nan))
        result = motion.update(r.rgb, pose, t, focus_ned_m=np.array([30.0, 0.0, 0.0]))
        if k >= 10:
            assert motion.anchored and motion.odometry_epoch == 0
            assert motion.position_ned_m is not None
            assert float(np.linalg.norm(motion.position_ned_m - state.position_ned_m)) < 0.2, (k, motion.position_ned_m)
            sources.append(None if result is None else result.pose_source)
    assert sources.count(POSE_IMAGE) >= 5, sources


def _fly_without_position(world, path, short_m):
    """MotionStage over ``path`` with attitude and a height above ground ``short_m(k)`` metres short, no position:
    per frame (odometry epoch, horizontal error of the image position against the truth from the first frame)."""
    motion = MotionStage(MotionConfig(), INTR, MOUNT)
    out = []
    for k, t, r, state in _frames(world, path):
        pose = CameraPose.of(MOUNT, state.attitude, np.full(3, np.nan), state.agl_m - short_m(k))
        motion.update(r.rgb, pose, t, focus_ned_m=np.array([30.0, 0.0, 0.0]))
        assert motion.position_ned_m is not None, (k, motion.last_reason)
        truth = state.position_ned_m - np.asarray(path[0])
        out.append((motion.odometry_epoch, float(np.linalg.norm(motion.position_ned_m[:2] - truth[:2])),
                    motion.last_reason))
    return out


def test_a_rangefinder_reading_a_tree_does_not_rescale_the_image_pose():
    """Without a telemetry position the image pose's metric scale is the height above ground. A rangefinder over a
    7 m tree reads short for 0.6 s: the images carry the ground's height over instead, and every frame stays within
    0.3 m of the truth (before the carried height, the pairs at the tree's height put frames metres off)."""
    world = _flat_world([[30.0, 10.0, 2.0, 1.0, 1.5], [45.0, -8.0, 2.2, 0.9, 1.5]])
    path = [(-10.0 + 0.5 * k, 1.5 * math.sin(0.15 * k), -30.0) for k in range(36)]
    flown = _fly_without_position(world, path, lambda k: 7.0 if 12 <= k < 18 else 0.0)
    assert {epoch for epoch, _, _ in flown} == {1}, flown
    assert max(err for _, err, _ in flown) < 0.3, [round(err, 2) for _, err, _ in flown]


def test_a_height_that_stays_changed_starts_a_new_odometry_frame():
    """The same flight with the height 7 m short from frame 10 on and never back: carried for
    ``agl_refused_max_s`` (2 s), then the odometry starts over at the new height, and says why."""
    world = _flat_world([[30.0, 10.0, 2.0, 1.0, 1.5], [45.0, -8.0, 2.2, 0.9, 1.5]])
    path = [(-10.0 + 0.5 * k, 1.5 * math.sin(0.15 * k), -30.0) for k in range(36)]
    flown = _fly_without_position(world, path, lambda k: 7.0 if k >= 10 else 0.0)
    refused_frames = round(ImagePoseConfig().agl_refused_max_s * FPS)
    epochs = [epoch for epoch, _, _ in flown]
    first_new = epochs.index(2)
    assert 10 + refused_frames <= first_new <= 10 + refused_frames + 1, epochs
    assert flown[first_new][2].startswith("odometry started over: height above ground"), flown[first_new][2]
    assert max(err for _, err, _ in flown[:first_new]) < 0.3, [round(err, 2) for _, err, _ in flown]


def test_a_height_first_read_off_a_tree_starts_the_odometry_over_when_the_ground_shows():
    """The rangefinder reads a 7 m tree under the first 10 frames, then the ground: nothing on the ground reads
    long, so the carried height was the tree's, and every step at its scale was short (suburban 6930 without a
    position: 0.87 of the truth). The odometry starts over at the longer height after ``agl_longer_max_s``, says
    why, and from there the frames follow the truth within 0.3 m."""
    world = _flat_world([[30.0, 10.0, 2.0, 1.0, 1.5], [45.0, -8.0, 2.2, 0.9, 1.5]])
    path = [(-10.0 + 0.5 * k, 1.5 * math.sin(0.15 * k), -30.0) for k in range(30)]
    flown = _fly_without_position(world, path, lambda k: 7.0 if k < 10 else 0.0)
    epochs = [epoch for epoch, _, _ in flown]
    first_new = epochs.index(2)
    longest = 10 + math.ceil(ImagePoseConfig().agl_longer_max_s * FPS)
    assert 10 <= first_new <= longest, epochs
    assert set(epochs[first_new:]) == {2}, epochs
    assert "longer than the" in flown[first_new][2] and "read off something" in flown[first_new][2], flown[first_new]
    since = [err for (_, err, _) in _fly_without_position(world, path[first_new:], lambda k: 0.0)]
    assert max(since) < 0.3, [round(e, 2) for e in since]


def test_a_vehicle_hovering_over_a_tree_keeps_the_carried_height():
    """A vehicle that stops over a 7 m tree reads it for 3 s: past ``agl_refused_max_s`` but with no flight across
    the ground, whose level cannot have changed, so the carried height stays and the odometry goes on."""
    world = _flat_world([[30.0, 10.0, 2.0, 1.0, 1.5], [45.0, -8.0, 2.2, 0.9, 1.5]])
    path = [(-10.0 + 0.5 * min(k, 12), 0.0, -30.0) for k in range(12 + int(3 * FPS))]
    flown = _fly_without_position(world, path, lambda k: 7.0 if k >= 12 else 0.0)
    assert {epoch for epoch, _, _ in flown} == {1}, [(e, why) for e, _, why in flown if why]
    assert max(err for _, err, _ in flown) < 0.3, [round(err, 2) for _, err, _ in flown]


@pytest.mark.parametrize("field", ["agl_refused_max_s", "agl_refused_travel_m", "agl_longer_max_s"])
def test_height_refusal_settings_name_a_bad_value(field):
    from edge_landing.runtime.core.errors import InputError

    with pytest.raises(InputError, match=field):
        ImagePoseConfig(**{field: -1.0})


def test_a_step_no_multirotor_flies_starts_the_odometry_over():
    """A flat roof taken for the ground scales the chained translation by the ratio of the heights (urban 1041
    without a position: 2.07 -> 5.45 m per frame, and the frames drifted 10 m in 0.3 s before the chain broke on
    its own). Such a step is refused and the odometry starts over; noise and the sim flights' phase changes (a
    one-frame velocity step of 4 m/s) are not."""
    from edge_landing.runtime.fusion.image_motion import ImagePose
    from edge_landing.runtime.fusion.odometry import ImageOdometry

    def chain_of(*steps):
        odo = ImageOdometry(MotionConfig(), np.eye(3))
        return [odo._implausible_step(ImagePose(True, delta_ned_m=np.array([n, 0.0, 0.4]), sigma_m=s), 0.1)
                for n, s in steps]

    assert chain_of((2.07, 0.06), (2.09, 0.06), (2.05, 0.02), (2.11, 0.07)) == [""] * 4
    assert chain_of((0.05, 0.02), (0.37, 0.02), (0.09, 0.02)) == [""] * 3          # the sim's phase change
    refused = chain_of((2.07, 0.06), (5.45, 0.06))[1]
    assert "changes the velocity by 33.8 m/s in 0.10 s, more than 50 m/s²" in refused, refused
