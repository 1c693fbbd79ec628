"""candidates.ground_floor_height: a ground effect's resolution floor read at the heights the flight holds."""

from types import SimpleNamespace

import numpy as np

from twin_nodes.discovery.candidates import GROUND_FLOOR_MAX_M, build_candidates, ground_floor_height
from twin_nodes.prove import rotorpy_flights as rf

DT = 0.02


def _heights(low_m: float, low_s: float) -> np.ndarray:
    """A flight at 1.5 m with ``low_s`` s hovered at ``low_m`` (c011: RotorPy RP4, 10 s near 0.26 m)."""
    return np.concatenate([np.full(int(30 / DT), 1.5), np.full(int(low_s / DT), low_m), np.full(int(10 / DT), 1.5)])


def test_the_floor_height_is_the_lowest_second_flown_and_at_most_0_3_m():
    assert ground_floor_height(_heights(0.26, 10.0), DT) == 0.26
    # under a second that low: the next heights up count, here the cruise, so the old 0.3 m holds
    assert ground_floor_height(_heights(0.10, 0.5), DT) == GROUND_FLOOR_MAX_M
    assert ground_floor_height(np.full(2000, 1.5), DT) == GROUND_FLOOR_MAX_M
    # a ramp 0 -> 0.6 m over 6 s: the first second of it lies under 0.1 m
    assert abs(ground_floor_height(np.linspace(0.0, 0.6, 300), DT) - 0.1003) < 1e-3
    assert ground_floor_height(np.zeros(10), DT) == GROUND_FLOOR_MAX_M


def _ge_floor(height: np.ndarray):
    vp = rf.nominal_params(rf.rotorpy_params("crazyflie"), "rotorpy_crazyflie")
    n = height.size
    data = SimpleNamespace(v=np.zeros((n, 3)), valid=np.ones(n, bool), motor_dt_s=0.02, dt=DT, height=height,
                           battery_v=np.full(n, np.nan))
    return next(c for c in build_candidates(vp, data) if c.name == "ground_effect").floor


def test_a_crazyflie_ground_effect_of_0_2_clears_the_floor_where_the_flight_hovers_low():
    """c011's truth (0.2 at a 0.1505 m height scale) adds 2.7 % at 0.3 m, 3.6 % at 0.26 m; its fit 0.183 / 0.156
    2.7 % and 3.4 %; read at 0.3 m wherever the flight holds no second lower."""
    low, high = _ge_floor(_heights(0.26, 10.0)), _ge_floor(np.full(3000, 0.29))
    for th in ([0.2, 0.1505], [0.183, 0.1555]):
        assert low(np.array(th)) and not _ge_floor(_heights(0.5, 10.0))(np.array(th))
    assert not high(np.array([0.2, 0.1505]))  # the whole flight at 0.29 m: 2.9 % there
    assert not low(np.array([0.1, 0.1505]))   # half the coefficient: 1.8 % at 0.26 m
