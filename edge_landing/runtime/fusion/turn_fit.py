"""The camera's turn fitted to frame pairs' directions (fusion.mount_check): Kabsch for one pair or a consensus,
then linearised least squares with the ground's slope. Frames: camera = OpenCV (x right, y down, z forward),
world = local NED. Pure numpy/OpenCV, no I/O, no state."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import cv2
import numpy as np

__all__ = ["PairDirections", "agreement_deg", "angles_deg", "pair_turns", "refine_with_slope", "solve_turn"]


@dataclass(frozen=True)
class PairDirections:
    """One frame pair: the ground's homography as seen (``a``: normalised, current -> reference, scaled so that its
    middle singular value is 1), the relative rotation ``rot`` and the directions of travel and of the ground's
    normal as the poses predict them (unit vectors, camera frames), and the vehicle's heading (NED, radians)."""

    a: np.ndarray
    rot: np.ndarray
    t_pred: np.ndarray
    n_pred: np.ndarray
    heading_rad: float
    r_nc: np.ndarray          # the current frame's NED <- camera rotation, as the poses give it

    def seen(self, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The directions of travel and of the normal as the camera saw them, with the camera turned by ``delta``
        (the relative rotation the poses give is then δᵀ R δ)."""
        u, _, vt = np.linalg.svd(self.a - delta.T @ self.rot @ delta)
        t, n = u[:, 0], vt[0]
        return (-t, -n) if n @ self.n_pred < 0 else (t, n)


def solve_turn(pairs: Sequence[PairDirections], delta: Optional[np.ndarray] = None) -> np.ndarray:
    """δ (3×3) that best turns the seen directions (read with the camera turned by ``delta``, default none) onto
    the predicted ones: predicted ≈ δ @ seen (Kabsch)."""
    start = np.eye(3) if delta is None else delta
    seen = np.concatenate([np.stack(p.seen(start)) for p in pairs])
    pred = np.concatenate([np.stack([p.t_pred, p.n_pred]) for p in pairs])
    u, _, vt = np.linalg.svd(pred.T @ seen)
    fix = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(u @ vt)))])
    out: np.ndarray = u @ fix @ vt
    return out


def seen_all(pairs: Sequence[PairDirections], delta: np.ndarray) -> np.ndarray:
    """``PairDirections.seen`` of every pair at once: N×2×3 (travel, normal)."""
    a = np.stack([p.a for p in pairs])
    rot = np.stack([p.rot for p in pairs])
    u, _, vt = np.linalg.svd(a - delta.T @ rot @ delta)
    t, n = u[:, :, 0], vt[:, 0, :]
    flip = np.where(np.sum(n * np.stack([p.n_pred for p in pairs]), axis=1) < 0, -1.0, 1.0)[:, None]
    out: np.ndarray = np.stack([t * flip, n * flip], axis=1)
    return out


def predicted_all(pairs: Sequence[PairDirections]) -> np.ndarray:
    """The predicted directions of every pair: N×2×3 (travel, normal)."""
    out: np.ndarray = np.stack([np.stack([p.t_pred for p in pairs]), np.stack([p.n_pred for p in pairs])], axis=1)
    return out


def pair_turns(pairs: Sequence[PairDirections], delta: Optional[np.ndarray] = None) -> np.ndarray:
    """Each pair's own turn (N×3×3): ``solve_turn([p], delta)`` for every pair at once (the per-frame path keeps
    up to ``MountCheckConfig.max_pairs``; one call per pair cost 70 ms at 240)."""
    seen = seen_all(pairs, np.eye(3) if delta is None else delta)
    pred = predicted_all(pairs)
    u, _, vt = np.linalg.svd(np.einsum("nki,nkj->nij", pred, seen))
    det = np.sign(np.linalg.det(u @ vt))
    fix = np.ones((len(pairs), 3))
    fix[:, 2] = det
    out: np.ndarray = (u * fix[:, None, :]) @ vt
    return out


def _skew_all(v: np.ndarray) -> np.ndarray:
    """[v]× of every vector in ``v`` (...×3) -> ...×3×3."""
    out = np.zeros(v.shape + (3,))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


PRIOR_RAD = math.radians(10.0)     # what the least squares assumes of the turn and the slope before the pairs
# A direction read from tracked features is not better than this (the ground is not a plane to the pixel, tracks
# are not exact): without the floor, pairs that agree by chance would make a confounded turn look certain.
SPREAD_FLOOR_RAD = math.radians(0.3)


def refine_with_slope(pairs: Sequence[PairDirections], delta: np.ndarray, steps: int = 3
                      ) -> tuple[np.ndarray, np.ndarray, float]:
    """δ refined together with the ground's slope, by linearised least squares: (δ, covariance of the turn's
    rotation vector in rad², slope in degrees).

    The seen normal is the sloped ground's, R_ncᵀ (down + σ) with σ = (σ_n, σ_e, 0) in NED, turned by δᵀ; the
    direction of travel has no slope in it. Flown one way, the direction of travel separates the camera's pitch
    from the slope along the track; across the track, roll and slope stay confounded until another heading
    is flown: a weak prior (``PRIOR_RAD`` on each) splits what the pairs cannot, and the covariance then says
    so (the turn's σ stays near the prior's). Each kind of direction is weighted by its own residual spread."""
    cov = np.full((3, 3), np.inf)
    sigma_ne = np.zeros(2)
    w_t = w_n = 1.0
    pred = predicted_all(pairs)
    slope_cols = -np.stack([p.r_nc.T[:, :2] for p in pairs])             # N×3×2: the slope's columns (normal)
    for _ in range(steps):
        # Per pair, 3 rows for the travel direction and 3 for the normal: [-[v]× | slope columns or 0].
        seen = seen_all(pairs, delta) @ delta.T                          # N×2×3, in the predicted frame
        blocks = np.zeros((len(pairs), 2, 3, 5))
        blocks[:, :, :, :3] = -_skew_all(seen)
        blocks[:, 1, :, 3:] = slope_cols
        a_mat, b = blocks.reshape(-1, 5), (pred - seen).reshape(-1)
        w = np.tile(np.concatenate([np.full(3, w_t), np.full(3, w_n)]), len(pairs))
        # The prior: the total turn (this step's increment added to the turn so far) and the slope near zero.
        turn_so_far = cv2.Rodrigues(delta)[0].reshape(3)
        prior_a = np.eye(5) / PRIOR_RAD
        prior_b = np.concatenate([-turn_so_far, np.zeros(2)]) / PRIOR_RAD
        sw = np.sqrt(w)
        x, *_ = np.linalg.lstsq(np.vstack([a_mat * sw[:, None], prior_a]), np.concatenate([b * sw, prior_b]),
                                rcond=None)
        res = (a_mat @ x - b).reshape(-1, 2, 3)
        # Each kind's robust residual spread: the next step's weights and the covariance's scale.
        s_t = max(1.4826 * float(np.median(np.linalg.norm(res[:, 0], axis=1))), SPREAD_FLOOR_RAD)
        s_n = max(1.4826 * float(np.median(np.linalg.norm(res[:, 1], axis=1))), SPREAD_FLOOR_RAD)
        w_t, w_n = 1.0 / s_t ** 2, 1.0 / s_n ** 2
        delta = cv2.Rodrigues(x[:3].reshape(3, 1))[0] @ delta
        sigma_ne = x[3:]
        w = np.tile(np.concatenate([np.full(3, w_t), np.full(3, w_n)]), len(pairs))
        # Two of a direction's three residual components carry information (it is a unit vector).
        cov = np.linalg.inv((a_mat * w[:, None]).T @ a_mat / 1.5 + prior_a.T @ prior_a)[:3, :3]
    return delta, cov, math.degrees(math.atan(float(np.linalg.norm(sigma_ne))))


def agreement_deg(turns: np.ndarray) -> np.ndarray:
    """Angle (degrees) between every two of ``turns`` (N×3×3): N×N, ``angles_deg`` row by row at once."""
    cos = np.clip((np.einsum("aij,bij->ab", turns, turns) - 1.0) / 2.0, -1.0, 1.0)
    out: np.ndarray = np.degrees(np.arccos(cos))
    return out


def angles_deg(delta: np.ndarray, turns: np.ndarray) -> np.ndarray:
    """Angle (degrees) between ``delta`` and each of ``turns`` (N×3×3)."""
    rel = np.einsum("ji,njk->nik", delta, turns)          # δᵀ δ_i
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    out: np.ndarray = np.degrees(np.arccos(cos))
    return out
