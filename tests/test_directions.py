"""The one angle between two directions the fit, eval and benches report."""

import math

import numpy as np
import pytest

from mi_invrgbl.physics.directions import angle_deg


def test_angles_against_closed_forms():
    assert angle_deg([0, 0, 1], [0, 0, 5]) == 0.0                 # lengths do not matter
    assert angle_deg([1, 0, 0], [0, 2, 0]) == pytest.approx(90.0)
    assert angle_deg([1, 0, 0], [-3, 0, 0]) == pytest.approx(180.0)
    t = math.radians(23.7)
    assert angle_deg([0, 0, 1], [math.sin(t), 0, math.cos(t)]) == pytest.approx(23.7, abs=1e-9)


def test_parallel_directions_with_rounding_give_no_nan():
    # A cosine that rounds past 1 would give arccos NaN without the clip.
    d = np.array([0.1, 0.7, 0.3], np.float32)
    for a, b in ((d, d.astype(np.float64) * 3), (d, -d)):
        assert np.isfinite(angle_deg(a, b))
    assert angle_deg(d, d * 7) < 1e-3


def test_no_direction_gives_nan_and_wrong_shapes_are_refused():
    assert math.isnan(angle_deg([0, 0, 0], [0, 0, 1]))
    assert math.isnan(angle_deg([np.nan, 0, 1], [0, 0, 1]))
    with pytest.raises(ValueError, match="3-vectors"):
        angle_deg([1, 0], [0, 1])
