"""The runtime interpolates gains exactly as `ptw-rt design --check` assumed when it proved stability."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from ptw_rt.core.schedule import grid_position, lerp
from ptw_rt.design.discretize import interpolate

GRID = np.linspace(10, 130, 49) / 3.6
TABLE = np.random.default_rng(0).normal(size=(49, 3, 2))


@given(st.floats(-10.0, 60.0))
def test_runtime_interpolation_equals_the_checked_rule(u):
    i, w = grid_position(GRID, u)
    runtime = np.array([[lerp(TABLE, i, w, r, c) for c in range(2)] for r in range(3)])
    assert np.allclose(runtime, interpolate(GRID, TABLE, u), rtol=1e-12, atol=1e-12)


def test_nan_speed_falls_back_to_the_lowest_grid_point():
    assert grid_position(GRID, float("nan")) == (0, 0.0)
