"""Base rate, lift, mIoU and the landable precision, on inputs small enough to check by hand."""
import math

import numpy as np
import pytest

from edge_landing.evaluation.landable import LandableAccumulator
from edge_landing.evaluation.metrics import Averaging, HvoAccumulator, horizontal_baseline, hvo_metrics
from edge_landing.runtime.core.camera import Attitude, Intrinsics, Mount, ned_from_camera
from edge_landing.runtime.core.messages import Prediction


def test_base_rate_lift_and_miou_by_hand():
    # 8 labelled pixels: 6 horizontal (H), 1 vertical (V), 1 other (O); one ignored (255).
    gt = np.array([0, 0, 0, 0, 0, 0, 1, 2, 255])
    pred = np.array([0, 0, 0, 0, 1, 2, 0, 2, 0])
    b = hvo_metrics(gt, pred)["baseline"]
    # called H: pixels 0-3 (true H) and 6 (true V) -> precision 4/5; base rate = 6/8 H among labelled pixels
    assert b["horizontal_precision"] == pytest.approx(0.8)
    assert b["horizontal_base_rate"] == pytest.approx(0.75)
    assert b["horizontal_lift"] == pytest.approx(0.05)
    # IoU: H 4/(6+5-4)=4/7; V 0/(1+1-0)=0; O 1/(1+2-1)=1/2
    assert b["miou"] == pytest.approx((4 / 7 + 0 + 0.5) / 3)


def test_everything_horizontal_has_zero_lift():
    gt = np.array([[0, 0, 1], [2, 0, 1]])
    b = horizontal_baseline(hvo_metrics(gt, np.zeros_like(gt))["confusion"])
    assert b["horizontal_precision"] == pytest.approx(0.5) and b["horizontal_base_rate"] == pytest.approx(0.5)
    assert b["horizontal_lift"] == 0.0
    assert b["miou"] == pytest.approx(0.5 / 3)        # H IoU 3/6, V and O 0


def test_per_image_averaging_averages_the_baseline_too():
    acc = HvoAccumulator(Averaging.PER_IMAGE)
    acc.add(np.array([0, 0, 1, 1]), np.array([0, 0, 0, 0]))     # precision 0.5, base 0.5
    acc.add(np.array([0, 1, 1, 1]), np.array([0, 1, 1, 1]))     # precision 1.0, base 0.25
    b = acc.result()["baseline"]
    assert b["horizontal_precision"] == pytest.approx(0.75) and b["horizontal_base_rate"] == pytest.approx(0.375)
    assert b["horizontal_lift"] == pytest.approx(0.375)


def _flat_ground(intr: Intrinsics, mount: Mount, att: Attitude, height_m: float) -> np.ndarray:
    """Planar z-depth of level ground ``height_m`` below the camera (NaN above the horizon)."""
    down = (intr.pixel_rays().astype(np.float64) @ ned_from_camera(mount, att).T)[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(down > 1e-3, height_m / down, np.nan).astype(np.float32)


def _one_hot(labels: np.ndarray) -> np.ndarray:
    return np.stack([(labels == k) for k in range(3)], axis=-1).astype(np.float32)


def test_landable_precision_uses_the_runtime_fuser():
    intr = Intrinsics.from_hfov(160, 120, math.radians(90.0))
    mount, att = Mount(math.radians(-90.0)), Attitude()          # nadir over flat ground at 20 m
    depth = _flat_ground(intr, mount, att, 20.0)
    labels = np.zeros((120, 160), np.uint8)
    labels[:, 80:] = 2                                             # the right half is "other" (e.g. water)
    perfect = LandableAccumulator()
    perfect.add(Prediction(0, 0.0, depth, _one_hot(labels)), depth, labels, intr, mount, att)
    r = perfect.result()
    assert r["frames"] == 1 and 0.4 < r["landable_base_rate"] <= 0.5   # the left half (its edge cells are mixed)
    assert r["landable_precision"] == pytest.approx(1.0)
    assert r["called_share"] == pytest.approx(r["landable_base_rate"], abs=0.02)
    # A net that calls everything horizontal: the fuser now lands on the "other" half too.
    naive = LandableAccumulator()
    naive.add(Prediction(0, 0.0, depth, _one_hot(np.zeros_like(labels))), depth, labels, intr, mount, att)
    n = naive.result()
    assert n["called_share"] > 1.8 * r["called_share"]
    assert n["landable_precision"] < 0.55
    assert n["landable_lift"] == pytest.approx(n["landable_precision"] - n["landable_base_rate"])
    # Nothing called: precision undefined (NaN), not 0 or 1.
    none = LandableAccumulator()
    none.add(Prediction(0, 0.0, depth, _one_hot(np.full_like(labels, 1))), depth, labels, intr, mount, att)
    assert none.result()["called_share"] == 0.0 and math.isnan(none.result()["landable_precision"])
