"""The paper's metrics, pure numpy (+ OpenCV for the SSIM filter): depth errors, SSIM, Median Rel, HVO.

Depth follows the AdaBins evaluation (reference/models.md "Depth metrics"): valid pixels are finite ground
truth with ``min_depth < gt < max_depth``; predictions are clamped to ``[min_depth, max_depth]`` (NaN -> min,
+inf -> max, as AdaBins does); metrics are computed per image and averaged over images (the default), or
over all pixels of a scene at once (``Averaging.GLOBAL``). Example::

    m = depth_metrics(gt_m, pred_m, max_depth=80.0)          # {'a1': ..., 'abs_rel': ..., ...}
    s = median_scale(gt_m, pred_m, 1e-3, 80.0)               # Monodepth2 per-image median scaling
    acc = DepthAccumulator(); acc.add(gt_m, pred_m); acc.result()
    hvo = hvo_metrics(gt_labels, pred_labels)                # per class vs rest + 'average' + 'confusion'
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, List, Optional

import cv2
import numpy as np

from edge_landing.runtime.core.choices import ChoiceEnum
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.core.labels import HVO_CLASSES, HVO_IGNORE

DEPTH_KEYS = ("a1", "a2", "a3", "abs_rel", "sq_rel", "rms", "rms_log", "log10", "silog")
HVO_KEYS = ("accuracy", "precision", "recall", "iou")
# Per-pixel sums from which every depth metric follows; summing them over images gives the global metrics.
_SUM_KEYS = ("n", "a1", "a2", "a3", "abs_rel", "sq_rel", "sq_err", "sq_log_err", "log10", "e", "e2")


class Averaging(ChoiceEnum):
    """How a scene's figure is formed: mean of per-image metrics (AdaBins) or one pass over all pixels."""

    PER_IMAGE = "per-image"
    GLOBAL = "global"

    @classmethod
    def _label(cls) -> str:
        return "averaging"


# -- depth ------------------------------------------------------------------------------------------------
def valid_mask(gt_m: np.ndarray, min_depth: float = 1e-3, max_depth: float = 80.0) -> np.ndarray:
    """Pixels that count: finite ground truth strictly inside (min_depth, max_depth)."""
    gt = np.asarray(gt_m)
    with np.errstate(invalid="ignore"):
        return np.isfinite(gt) & (gt > min_depth) & (gt < max_depth)


def clamp_prediction(pred_m: np.ndarray, min_depth: float, max_depth: float) -> np.ndarray:
    """float64 copy clamped to [min, max]; NaN -> min and +inf -> max (AdaBins' convention)."""
    pred = np.array(pred_m, dtype=np.float64, copy=True)
    pred[np.isnan(pred)] = min_depth
    return np.clip(pred, min_depth, max_depth)


def _check_shapes(gt: np.ndarray, pred: np.ndarray, what: str) -> None:
    if np.shape(gt) != np.shape(pred):
        raise InputError(f"{what}: ground truth {np.shape(gt)} and prediction {np.shape(pred)} differ in shape; "
                         f"resize the prediction to the ground truth's size first")


def _depth_sums(gt_m, pred_m, min_depth: float, max_depth: float) -> Dict[str, float]:
    _check_shapes(gt_m, pred_m, "depth metrics")
    mask = valid_mask(gt_m, min_depth, max_depth)
    gt = np.asarray(gt_m, dtype=np.float64)[mask]
    pred = clamp_prediction(np.asarray(pred_m)[mask], min_depth, max_depth)
    thresh = np.maximum(gt / pred, pred / gt)
    e = np.log(pred) - np.log(gt)
    diff = gt - pred
    return {"n": float(gt.size), "a1": float((thresh < 1.25).sum()), "a2": float((thresh < 1.25 ** 2).sum()),
            "a3": float((thresh < 1.25 ** 3).sum()), "abs_rel": float((np.abs(diff) / gt).sum()),
            "sq_rel": float((diff ** 2 / gt).sum()), "sq_err": float((diff ** 2).sum()),
            "sq_log_err": float((e ** 2).sum()), "log10": float(np.abs(np.log10(gt) - np.log10(pred)).sum()),
            "e": float(e.sum()), "e2": float((e ** 2).sum())}


def _metrics_from_sums(s: Dict[str, float]) -> Dict[str, float]:
    n = s["n"]
    if n <= 0:
        return {k: math.nan for k in DEPTH_KEYS}
    mean = {k: s[k] / n for k in _SUM_KEYS if k != "n"}
    # max(…, 0): mean(e²) − mean(e)² can dip below zero by rounding when every e is equal.
    silog = 100.0 * math.sqrt(max(mean["e2"] - mean["e"] ** 2, 0.0))
    return {"a1": mean["a1"], "a2": mean["a2"], "a3": mean["a3"], "abs_rel": mean["abs_rel"],
            "sq_rel": mean["sq_rel"], "rms": math.sqrt(mean["sq_err"]), "rms_log": math.sqrt(mean["sq_log_err"]),
            "log10": mean["log10"], "silog": silog}


def depth_metrics(gt_m: np.ndarray, pred_m: np.ndarray, min_depth: float = 1e-3,
                  max_depth: float = 80.0) -> Dict[str, float]:
    """AdaBins' errors for one image (keys ``DEPTH_KEYS``); all NaN when no pixel is valid."""
    return _metrics_from_sums(_depth_sums(gt_m, pred_m, min_depth, max_depth))


def median_scale(gt_m: np.ndarray, pred_m: np.ndarray, min_depth: float = 1e-3, max_depth: float = 80.0) -> float:
    """Monodepth2's per-image ratio median(gt) / median(pred) over valid pixels (NaN when none).

    The prediction is taken as given (not clamped) for the ratio, and is clamped after scaling.
    """
    _check_shapes(gt_m, pred_m, "median scale")
    pred = np.asarray(pred_m, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        mask = valid_mask(gt_m, min_depth, max_depth) & np.isfinite(pred) & (pred > 0)
    if not mask.any():
        return math.nan
    return float(np.median(np.asarray(gt_m, dtype=np.float64)[mask]) / np.median(pred[mask]))


def median_scaled_depth_metrics(gt_m, pred_m, min_depth: float = 1e-3, max_depth: float = 80.0) -> Dict[str, float]:
    """The paper's starred rows for one image: metrics of pred × median_scale (the per-image oracle)."""
    s = median_scale(gt_m, pred_m, min_depth, max_depth)
    return depth_metrics(gt_m, np.asarray(pred_m, dtype=np.float64) * s, min_depth, max_depth)


def median_rel(gt_m: np.ndarray, pred_m: np.ndarray, min_depth: float = 1e-3, max_depth: float = 80.0) -> float:
    """Median over valid pixels of (gt − pred) / gt; positive = predictions shorter than the truth."""
    _check_shapes(gt_m, pred_m, "median rel")
    mask = valid_mask(gt_m, min_depth, max_depth)
    if not mask.any():
        return math.nan
    gt = np.asarray(gt_m, dtype=np.float64)[mask]
    pred = clamp_prediction(np.asarray(pred_m)[mask], min_depth, max_depth)
    return float(np.median((gt - pred) / gt))


# -- SSIM -------------------------------------------------------------------------------------------------
SSIM_WINDOW = 11
SSIM_SIGMA = 1.5


def ssim_map(a: np.ndarray, b: np.ndarray, data_range: float, k1: float = 0.01, k2: float = 0.03) -> np.ndarray:
    """Wang et al. 2004 SSIM index per pixel: Gaussian window 11×11, σ 1.5, population covariances.

    Equal to scikit-image's ``structural_similarity(gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, full=True)`` away from the 5-pixel border (the border differs only in how
    the filter pads, and ``ssim_index`` leaves it out as scikit-image does).
    """
    if data_range <= 0:
        raise InputError(f"SSIM data range must be positive, got {data_range}")
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    kernel = cv2.getGaussianKernel(SSIM_WINDOW, SSIM_SIGMA, ktype=cv2.CV_64F)

    def blur(x):
        return cv2.sepFilter2D(x, cv2.CV_64F, kernel, kernel, borderType=cv2.BORDER_REFLECT)

    mu_a, mu_b = blur(a), blur(b)
    var_a = blur(a * a) - mu_a ** 2
    var_b = blur(b * b) - mu_b ** 2
    cov = blur(a * b) - mu_a * mu_b
    c1, c2 = (k1 * data_range) ** 2, (k2 * data_range) ** 2
    return ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a ** 2 + mu_b ** 2 + c1) * (var_a + var_b + c2))


def ssim_index(a: np.ndarray, b: np.ndarray, data_range: float, mask: Optional[np.ndarray] = None) -> float:
    """Mean SSIM over the image less its 5-pixel border (and over ``mask`` when given); NaN when empty."""
    _check_shapes(a, b, "SSIM")
    if min(np.shape(a)) < SSIM_WINDOW:
        raise InputError(f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels, got {np.shape(a)}")
    pad = (SSIM_WINDOW - 1) // 2
    keep = np.zeros(np.shape(a), dtype=bool)
    keep[pad:-pad, pad:-pad] = True
    if mask is not None:
        keep &= mask
    if not keep.any():
        return math.nan
    return float(ssim_map(a, b, data_range)[keep].mean())


def ssim(gt_m: np.ndarray, pred_m: np.ndarray, min_depth: float = 1e-3, max_depth: float = 80.0) -> float:
    """SSIM between two depth maps, data range 1 after normalising both by the ground truth's valid maximum.

    The prediction is clamped as for the depth metrics; pixels whose ground truth is invalid (sky) are
    set to 0 in both maps and left out of the mean, so the score is about the valid scene only.
    """
    _check_shapes(gt_m, pred_m, "SSIM")
    mask = valid_mask(gt_m, min_depth, max_depth)
    if not mask.any():
        return math.nan
    top = float(np.asarray(gt_m, dtype=np.float64)[mask].max())
    gt = np.where(mask, np.asarray(gt_m, dtype=np.float64), 0.0) / top
    pred = np.where(mask, clamp_prediction(pred_m, min_depth, max_depth), 0.0) / top
    return ssim_index(gt, pred, data_range=1.0, mask=mask)


# -- accumulators -----------------------------------------------------------------------------------------
class DepthAccumulator:
    """Depth metrics over many images: the mean of per-image metrics (AdaBins, default) or global sums.

    Images with no valid pixel are counted in ``skipped`` and left out of both averages.
    """

    def __init__(self, min_depth: float = 1e-3, max_depth: float = 80.0,
                 averaging: Averaging = Averaging.PER_IMAGE):
        self.min_depth, self.max_depth, self.averaging = min_depth, max_depth, averaging
        self._sums = {k: 0.0 for k in _SUM_KEYS}
        self._per_image: List[Dict[str, float]] = []
        self.skipped = 0

    def add(self, gt_m: np.ndarray, pred_m: np.ndarray) -> Dict[str, float]:
        """Add one image; returns its own metrics."""
        sums = _depth_sums(gt_m, pred_m, self.min_depth, self.max_depth)
        metrics = _metrics_from_sums(sums)
        if sums["n"] == 0:
            self.skipped += 1
            return metrics
        for k in _SUM_KEYS:
            self._sums[k] += sums[k]
        self._per_image.append(metrics)
        return metrics

    @property
    def count(self) -> int:
        return len(self._per_image)

    def result(self) -> Dict[str, float]:
        if self.averaging is Averaging.GLOBAL:
            return _metrics_from_sums(self._sums)
        if not self._per_image:
            return {k: math.nan for k in DEPTH_KEYS}
        return {k: float(np.mean([m[k] for m in self._per_image])) for k in DEPTH_KEYS}


# -- HVO --------------------------------------------------------------------------------------------------
def hvo_confusion(gt_labels: np.ndarray, pred_labels: np.ndarray, ignore: int = HVO_IGNORE) -> np.ndarray:
    """3×3 int64 counts, rows = ground truth class, columns = predicted class; ``ignore`` pixels skipped."""
    _check_shapes(gt_labels, pred_labels, "HVO metrics")
    gt = np.asarray(gt_labels).ravel().astype(np.int64)
    pred = np.asarray(pred_labels).ravel().astype(np.int64)
    n = len(HVO_CLASSES)
    keep = (gt != ignore) & (gt >= 0) & (gt < n) & (pred >= 0) & (pred < n)
    return np.bincount(gt[keep] * n + pred[keep], minlength=n * n).reshape(n, n)


def _ratio(num: float, den: float) -> float:
    return float(num / den) if den > 0 else math.nan


def hvo_metrics_from_confusion(cm: np.ndarray) -> dict:
    """Per class (that class against the rest): accuracy, precision, recall, IoU; 'average' = their mean
    over classes (NaN where a ratio is 0/0, e.g. a class absent from both maps; the average skips NaN)."""
    cm = np.asarray(cm, dtype=np.int64)
    total = cm.sum()
    out: dict = {}
    for i, name in enumerate(HVO_CLASSES):
        tp = cm[i, i]
        fp = cm[:, i].sum() - tp
        fn = cm[i, :].sum() - tp
        tn = total - tp - fp - fn
        out[name] = {"accuracy": _ratio(tp + tn, total), "precision": _ratio(tp, tp + fp),
                     "recall": _ratio(tp, tp + fn), "iou": _ratio(tp, tp + fp + fn)}
    out["average"] = {k: _nanmean([out[c][k] for c in HVO_CLASSES]) for k in HVO_KEYS}
    out["confusion"] = cm.tolist()
    out["pixels"] = int(total)
    out["baseline"] = horizontal_baseline(cm)
    return out


def horizontal_baseline(cm: np.ndarray) -> dict:
    """How easy the scene is: the precision of calling *every* labelled pixel horizontal (= the share of
    labelled pixels that are horizontal, the base rate), the model's horizontal precision, its lift over the
    base rate (precision − base rate), and mIoU (mean IoU over the classes present). On our town scenes
    73–80 % of labelled pixels are horizontal, so a precision of 0.80 can mean nothing: read it with the lift.
    """
    cm = np.asarray(cm, dtype=np.int64)
    total = int(cm.sum())
    h = HVO_CLASSES.index("horizontal")
    tp, called = cm[h, h], cm[:, h].sum()
    base = _ratio(cm[h, :].sum(), total)
    precision = _ratio(tp, called)
    ious = [_ratio(cm[i, i], cm[i, :].sum() + cm[:, i].sum() - cm[i, i]) for i in range(len(HVO_CLASSES))]
    return {"horizontal_precision": precision, "horizontal_base_rate": base,
            "horizontal_lift": precision - base if not (math.isnan(precision) or math.isnan(base)) else math.nan,
            "horizontal_max_lift": 1.0 - base if not math.isnan(base) else math.nan,   # a perfect net's lift
            "miou": _nanmean(ious)}


def _nanmean(values) -> float:
    finite = [v for v in values if not math.isnan(v)]
    return float(np.mean(finite)) if finite else math.nan


def hvo_metrics(gt_labels: np.ndarray, pred_labels: np.ndarray, ignore: int = HVO_IGNORE) -> dict:
    """HVO figures for one image (see ``hvo_metrics_from_confusion``)."""
    return hvo_metrics_from_confusion(hvo_confusion(gt_labels, pred_labels, ignore))


class HvoAccumulator:
    """HVO figures over many images: global counts (one confusion matrix for the scene, default) or the
    mean of per-image figures (``Averaging.PER_IMAGE``)."""

    def __init__(self, averaging: Averaging = Averaging.GLOBAL, ignore: int = HVO_IGNORE):
        self.averaging, self.ignore = averaging, ignore
        self.confusion = np.zeros((len(HVO_CLASSES),) * 2, dtype=np.int64)
        self._per_image: List[dict] = []

    def add(self, gt_labels: np.ndarray, pred_labels: np.ndarray) -> dict:
        cm = hvo_confusion(gt_labels, pred_labels, self.ignore)
        self.confusion += cm
        metrics = hvo_metrics_from_confusion(cm)
        if cm.sum() > 0:
            self._per_image.append(metrics)
        return metrics

    @property
    def count(self) -> int:
        return len(self._per_image)

    def result(self) -> dict:
        out = hvo_metrics_from_confusion(self.confusion)
        if self.averaging is Averaging.PER_IMAGE:
            for name in (*HVO_CLASSES, "average"):
                out[name] = {k: _nanmean([m[name][k] for m in self._per_image]) for k in HVO_KEYS}
            out["baseline"] = {k: _nanmean([m["baseline"][k] for m in self._per_image])
                               for k in out["baseline"]}
        return out


@dataclass
class MeanAccumulator:
    """Mean of per-image scalars (SSIM, Median Rel), skipping NaN (images with nothing valid)."""

    total: float = 0.0
    count: int = 0

    def add(self, value: float) -> float:
        if not math.isnan(value):
            self.total += value
            self.count += 1
        return value

    def result(self) -> float:
        return self.total / self.count if self.count else math.nan
