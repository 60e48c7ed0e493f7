"""LiDAR intensity scales (omnire/data/intensity.py): each maps its documented range onto
[0, 1] as its definition says (checked value by value in float64), inverts exactly for the
writers, and refuses a value outside the range with the field and the range named."""
from __future__ import annotations

import math
import re

import numpy as np
import pytest

from omnire.api import BYTE_INTENSITY, UNBOUNDED_INTENSITY, UNIT_INTENSITY, SceneDataError


def test_each_scale_maps_its_range_onto_unit():
    rng = np.random.default_rng(0)
    cases = [(BYTE_INTENSITY, np.append(rng.integers(0, 256, 200), [0, 255]), lambda v: v / 255.0),
             (UNIT_INTENSITY, np.append(rng.random(200), [0.0, 1.0]), lambda v: v),
             (UNBOUNDED_INTENSITY, np.append(rng.exponential(0.4, 200), [0.0, 3e4]), math.tanh)]
    for scale, values, obvious in cases:
        unit = scale.to_unit(values, "file: column i")
        assert unit.dtype == np.float32 and unit.shape == values.shape
        assert 0 <= unit.min() and unit.max() <= 1
        np.testing.assert_allclose(unit, [obvious(float(v)) for v in values], rtol=1e-6, atol=1e-7, err_msg=scale.name)
        keep = unit < 0.999  # tanh's inverse is ill-conditioned near 1 (float32 rounds tanh(3e4) to 1)
        back = scale.from_unit(unit[keep])
        np.testing.assert_allclose(back, values[keep], rtol=1e-5, atol=1e-5, err_msg=scale.name)
    assert UNBOUNDED_INTENSITY.to_unit(np.array([0.05]), "f")[0] == pytest.approx(0.05, rel=1e-3)  # ~x for small x


@pytest.mark.parametrize("scale, bad, expected", [
    (BYTE_INTENSITY, 255.5, "numbers in 0..255"), (BYTE_INTENSITY, -1.0, "numbers in 0..255"),
    (BYTE_INTENSITY, np.nan, "numbers in 0..255"), (UNIT_INTENSITY, 1.5, "numbers in 0..1"),
    (UNBOUNDED_INTENSITY, -0.1, "finite numbers >= 0"), (UNBOUNDED_INTENSITY, np.inf, "finite numbers >= 0"),
])
def test_values_outside_the_scale_are_refused_with_the_field(scale, bad, expected):
    values = np.array([0.0, 0.5, bad, bad])
    with pytest.raises(SceneDataError, match=re.escape(f"x.bin: column 4 (intensity) must hold {expected} (found "
                                                       f"{bad:g}, 2 of 4 values; {scale.name} scale)")):
        scale.to_unit(values, "x.bin: column 4 (intensity)")


def test_a_readers_own_error_kind_is_raised():
    class ReaderError(SceneDataError):
        pass

    with pytest.raises(ReaderError):
        BYTE_INTENSITY.to_unit(np.array([300.0]), "f", ReaderError)
    assert len(BYTE_INTENSITY.to_unit(np.zeros(0), "f")) == 0


def test_writers_refuse_unit_values_outside_the_range():
    for scale, bad in ((BYTE_INTENSITY, 1.01), (UNIT_INTENSITY, -0.01), (UNBOUNDED_INTENSITY, 1.0)):
        with pytest.raises(ValueError, match="intensity in \\[0, 1"):
            scale.from_unit(np.array([0.2, bad]))
