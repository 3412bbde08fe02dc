import math

import numpy as np
import pytest

from edge_landing.evaluation.metrics import (
    DEPTH_KEYS,
    Averaging,
    DepthAccumulator,
    HvoAccumulator,
    MeanAccumulator,
    depth_metrics,
    hvo_confusion,
    hvo_metrics,
    median_rel,
    median_scale,
    median_scaled_depth_metrics,
    ssim,
    ssim_index,
    ssim_map,
)
from edge_landing.runtime.core.errors import InputError


def test_depth_metrics_match_a_hand_computed_case():
    # Valid: gt 1, 2, 4 (NaN and 100 m > max are left out); pred 2, 2, 1.
    gt = np.array([[1.0, 2.0], [4.0, np.nan], [100.0, 0.0]])
    pred = np.array([[2.0, 2.0], [1.0, 5.0], [3.0, 3.0]])
    m = depth_metrics(gt, pred, min_depth=1e-3, max_depth=80.0)
    e = np.log([2.0, 2.0, 1.0]) - np.log([1.0, 2.0, 4.0])
    expected = {
        "a1": 1 / 3, "a2": 1 / 3, "a3": 1 / 3,          # ratios 2, 1, 4: only 1 is under 1.25**3 = 1.95
        "abs_rel": (1 / 1 + 0 + 3 / 4) / 3,
        "sq_rel": (1 / 1 + 0 + 9 / 4) / 3,
        "rms": math.sqrt((1 + 0 + 9) / 3),
        "rms_log": math.sqrt(np.mean(e ** 2)),
        "log10": (math.log10(2) + 0 + math.log10(4)) / 3,
        "silog": 100 * math.sqrt(np.mean(e ** 2) - np.mean(e) ** 2),
    }
    assert set(m) == set(DEPTH_KEYS)
    for k, v in expected.items():
        assert m[k] == pytest.approx(v, rel=1e-12), k


def test_prediction_is_clamped_and_nan_becomes_min():
    gt = np.array([5.0, 5.0, 5.0])
    pred = np.array([np.nan, np.inf, 1000.0])
    m = depth_metrics(gt, pred, min_depth=1.0, max_depth=10.0)
    # pred -> 1, 10, 10: abs errors 4, 5, 5
    assert m["abs_rel"] == pytest.approx((4 + 5 + 5) / 3 / 5)
    assert m["a1"] == 0.0


def test_perfect_prediction_and_empty_image():
    gt = np.linspace(1, 50, 60).reshape(6, 10)
    m = depth_metrics(gt, gt.copy())
    assert m["a1"] == 1.0 and m["abs_rel"] == 0.0 and m["rms"] == 0.0 and m["silog"] == 0.0
    empty = depth_metrics(np.full((4, 4), np.nan), np.ones((4, 4)))
    assert all(math.isnan(v) for v in empty.values())
    with pytest.raises(InputError, match="differ in shape"):
        depth_metrics(gt, gt[:3])


def test_median_scaled_rows_equal_metrics_of_prescaled_predictions():
    rng = np.random.default_rng(1)
    gt = rng.uniform(5, 70, (30, 40))
    gt[:5] = np.nan
    pred = gt * rng.uniform(0.8, 1.2, gt.shape) / 3.0
    s = median_scale(gt, pred, 1e-3, 80.0)
    valid = np.isfinite(gt)
    assert s == pytest.approx(np.median(gt[valid]) / np.median(pred[valid]))
    assert median_scaled_depth_metrics(gt, pred) == depth_metrics(gt, pred * s)
    # a prediction off by a pure factor is perfect after median scaling
    assert median_scaled_depth_metrics(gt, gt / 7.0)["abs_rel"] == pytest.approx(0.0, abs=1e-12)


def test_median_rel_sign_convention():
    gt = np.array([10.0, 20.0, 40.0, np.nan])
    assert median_rel(gt, gt * 0.9) == pytest.approx(0.1)       # shorter than the truth -> positive
    assert median_rel(gt, gt * 1.5) == pytest.approx(-0.5)


def test_ssim_matches_scikit_image():
    from skimage.metrics import structural_similarity

    rng = np.random.default_rng(2)
    a = rng.random((40, 52))
    b = np.clip(a + 0.2 * rng.standard_normal(a.shape), 0, 1)
    kw = dict(data_range=1.0, gaussian_weights=True, sigma=1.5, use_sample_covariance=False)
    assert ssim_index(a, b, 1.0) == pytest.approx(structural_similarity(a, b, **kw), abs=1e-12)
    _, full = structural_similarity(a, b, full=True, **kw)
    np.testing.assert_allclose(ssim_map(a, b, 1.0)[5:-5, 5:-5], full[5:-5, 5:-5], atol=1e-12)


def test_depth_ssim_normalises_by_the_ground_truth_maximum():
    from skimage.metrics import structural_similarity

    rng = np.random.default_rng(3)
    gt = rng.uniform(10, 60, (32, 32))
    pred = gt * rng.uniform(0.7, 1.3, gt.shape)
    top = gt.max()
    expected = structural_similarity(gt / top, pred / top, data_range=1.0, gaussian_weights=True, sigma=1.5,
                                     use_sample_covariance=False)
    assert ssim(gt, pred) == pytest.approx(expected, abs=1e-12)
    assert ssim(gt, gt) == pytest.approx(1.0)
    assert math.isnan(ssim(np.full((16, 16), np.nan), gt[:16, :16]))


def test_hvo_metrics_hand_computed():
    gt = np.array([[0, 0, 1, 1], [2, 2, 255, 0]], np.uint8)
    pred = np.array([[0, 1, 1, 1], [2, 0, 2, 0]], np.uint8)
    cm = hvo_confusion(gt, pred)
    np.testing.assert_array_equal(cm, [[2, 1, 0], [0, 2, 0], [1, 0, 1]])
    m = hvo_metrics(gt, pred)
    # horizontal: tp 2, fp 1, fn 1, tn 3 over 7 pixels
    assert m["horizontal"] == pytest.approx({"accuracy": 5 / 7, "precision": 2 / 3, "recall": 2 / 3, "iou": 2 / 4})
    # vertical: tp 2, fp 1, fn 0
    assert m["vertical"] == pytest.approx({"accuracy": 6 / 7, "precision": 2 / 3, "recall": 1.0, "iou": 2 / 3})
    # other: tp 1, fp 0, fn 1
    assert m["other"] == pytest.approx({"accuracy": 6 / 7, "precision": 1.0, "recall": 0.5, "iou": 0.5})
    assert m["average"]["precision"] == pytest.approx((2 / 3 + 2 / 3 + 1) / 3)
    assert m["pixels"] == 7 and m["confusion"] == cm.tolist()


def test_absent_class_is_nan_and_skipped_in_the_average():
    gt = np.zeros((3, 3), np.uint8)
    m = hvo_metrics(gt, gt)
    assert math.isnan(m["vertical"]["precision"]) and m["horizontal"]["iou"] == 1.0
    assert m["average"]["iou"] == 1.0


def test_hvo_accumulator_global_and_per_image():
    a_gt, a_pred = np.zeros((2, 2), np.uint8), np.zeros((2, 2), np.uint8)
    b_gt = np.array([[0, 0], [0, 1]], np.uint8)
    b_pred = np.ones((2, 2), np.uint8)
    glob = HvoAccumulator()
    per = HvoAccumulator(Averaging.PER_IMAGE)
    for acc in (glob, per):
        acc.add(a_gt, a_pred)
        acc.add(b_gt, b_pred)
    g = glob.result()
    assert g["horizontal"]["recall"] == pytest.approx(4 / 7)
    np.testing.assert_array_equal(g["confusion"], [[4, 3, 0], [0, 1, 0], [0, 0, 0]])
    assert per.result()["horizontal"]["recall"] == pytest.approx((1.0 + 0.0) / 2)


def test_depth_accumulator_per_image_and_global():
    gt1, p1 = np.full((2, 2), 10.0), np.full((2, 2), 12.0)
    gt2, p2 = np.full((4, 4), 20.0), np.full((4, 4), 20.0)
    per = DepthAccumulator()
    glob = DepthAccumulator(averaging=Averaging.from_string("global"))
    for acc in (per, glob):
        acc.add(gt1, p1)
        acc.add(gt2, p2)
        acc.add(np.full((2, 2), np.nan), p1)       # nothing valid: skipped
    assert per.count == 2 and per.skipped == 1
    assert per.result()["abs_rel"] == pytest.approx((0.2 + 0.0) / 2)
    assert glob.result()["abs_rel"] == pytest.approx(4 * 0.2 / 20)
    assert glob.result()["rms"] == pytest.approx(math.sqrt(4 * 4 / 20))
    with pytest.raises(InputError, match="per-image, global"):
        Averaging.from_string("mean")


def test_mean_accumulator_skips_nan():
    acc = MeanAccumulator()
    for v in (0.5, math.nan, 1.0):
        acc.add(v)
    assert acc.result() == 0.75 and acc.count == 2
