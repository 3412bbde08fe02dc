"""fusion.splat: lattice sizes from footprints, and samples that fill each pixel's footprint."""
import numpy as np

from edge_landing.runtime.fusion.splat import footprint_keys, key_base, splat


def test_footprint_keys_count_samples_per_axis_and_leave_discontinuities_bare():
    # Two-pixel steps (north, east rows); one-pixel lengths 0.2, 0.5, 0.51, 1.9 and 2.4 m along u, 0.2 along v.
    step_u = np.array([[0.4, 1.0, 1.02, 3.8, 4.8], [0, 0, 0, 0, 0]], np.float32)
    step_v = np.array([[0, 0, 0, 0, 0], [0.4, 0.4, 0.4, 0.4, 20.0]], np.float32)
    keys = footprint_keys(step_u, step_v, spacing_m=0.5, max_footprint_m=4.0, max_per_axis=4)
    base = key_base(4)
    ku, kv = keys // base, keys % base
    assert ku.tolist() == [1, 1, 2, 4, 1]        # ceil(length / spacing), capped at 4; the last is a 10 m jump
    assert kv.tolist() == [1, 1, 1, 1, 1]
    assert keys.dtype == np.uint8


def test_splat_fills_each_footprint_on_a_lattice_and_carries_values():
    # Two-pixel steps (north, east rows): pixel 0 covers 0.1 m (1×1), pixel 1 covers 1 m × 1 m (2×2).
    step_u = np.array([[0.0, 2.0], [0.2, 0.0]], np.float32)
    step_v = np.array([[0.2, 0.0], [0.0, 2.0]], np.float32)
    points = np.array([[10.0, 20.0], [5.0, 7.0]], np.float32)
    keys = footprint_keys(step_u, step_v, 0.5, 4.0, 4)
    columns = np.zeros((3, 3, 2), np.float32)             # quantities north, east, vote; per pixel (u, v, value)
    columns[:2, 0], columns[:2, 1], columns[:2, 2] = step_u, step_v, points
    columns[2, 2] = (0.25, 1.0)
    order = np.argsort(keys, kind="stable")
    samples = splat(columns[:, :, order], keys[order], 4)
    assert samples.shape == (3, 1 + 4)
    # The 1×1 pixel is its own point; the 2×2 one gets the centres of its four quarters (±0.25 m).
    assert np.allclose(samples[:, 0], [10.0, 5.0, 0.25])
    quarter = samples[:, 1:]
    assert sorted(map(tuple, np.round(quarter[:2].T, 3))) == [(19.75, 6.75), (19.75, 7.25), (20.25, 6.75),
                                                               (20.25, 7.25)]
    assert np.all(quarter[2] == 1.0)              # a vote is the same over the whole footprint
