"""Issue 24.1: every PX4 multirotor log starts.  A log without ``CA_*`` geometry takes its airframe's PX4
mixer geometry (SYS_AUTOSTART -> MIXER -> R: key -> geometry toml, PX4 1.8-1.13, the table in
twin_nodes.vehicle.px4_geometry); an unknown airframe takes an ASSUMED generic layout of its MAV_TYPE
class when the moving motor outputs confirm the rotor count; a rotor count that differs from the
outputs that move is refused in one line."""

from __future__ import annotations

import math

import numpy as np
import pytest

from twin_nodes.base.errors import ParamsError
from twin_nodes.logs.ulog_io import read_ulog
from twin_nodes.logs.ulog_write import write_px4_ulog
from twin_nodes.vehicle.px4_geometry import AUTOSTART, GEOMETRIES
from twin_nodes.vehicle.px4_params import rotor_layout

S = 1 / math.sqrt(2.0)
CCW, CW = 1, -1


def _rotors(key):
    return [(r[1][0], r[1][1], r[1][2], r[2]) for r in GEOMETRIES[key]["rotors"]]


def test_quad_x_is_px4s_motor_numbering():
    """quad_x.toml: Motor1 front right CCW, 2 rear left CCW, 3 front left CW, 4 rear right CW (FRD, y right)."""
    want = [(S, S, CCW), (-S, -S, CCW), (S, -S, CW), (-S, S, CW)]
    got = _rotors("4x")
    assert len(got) == 4
    for (x, y, z, d), (wx, wy, wd) in zip(got, want):
        assert (x, y, z, d) == (pytest.approx(wx, abs=1e-6), pytest.approx(wy, abs=1e-6), 0.0, wd)
    assert GEOMETRIES["4x"]["file"] == "quad_x"


def test_hexa_x_positions_and_spins():
    want = [(0, 1, CW), (0, -1, CCW), (0.866, -0.5, CW), (-0.866, 0.5, CCW), (0.866, 0.5, CCW), (-0.866, -0.5, CW)]
    got = _rotors("6x")
    assert [d for *_, d in got] == [w[2] for w in want]
    np.testing.assert_allclose([(x, y) for x, y, _, _ in got], [(w[0], w[1]) for w in want], atol=1e-3)


def test_octo_cox_pairs_share_a_place_and_spin_opposite():
    got = _rotors("8c")
    assert len(got) == 8
    pairs = []
    for i in range(8):
        for j in range(i + 1, 8):
            if got[i][:2] == got[j][:2]:
                pairs.append((i, j))
                assert got[i][3] == -got[j][3]          # opposite spin
                assert got[i][2] == -got[j][2] != 0.0   # one above (z < 0, FRD), one below
    assert sorted(pairs) == [(0, 5), (1, 4), (2, 7), (3, 6)]


def test_table_chain_for_the_held_aside_airframes():
    """4500 Clover 4 (present from PX4 1.11) -> quad_x (rc.mc_defaults' default at M113); 12001 -> octo_cox."""
    assert {r[3] for r in AUTOSTART[4500]} == {"4x"} and AUTOSTART[4500][-1][2] == "quad_x"
    assert {r[3] for r in AUTOSTART[12001]} == {"8c"} and AUTOSTART[12001][0][5][0] == "c73944c7a2"
    assert AUTOSTART[4040][-1][3] == "4h" and AUTOSTART[10016][-1][3] == "4w"
    assert AUTOSTART[6001][-1][3] == "6x" and AUTOSTART[11001][-1][3] == "6c"
    assert 13000 not in AUTOSTART and 1002 not in AUTOSTART    # VTOLs are left out


def _log(path, params, moving: int, channels: int = 8):
    """A 20 s armed log: ``moving`` MAIN outputs vary (1100-1700 us), the rest sit at 900 us (PX4 1.8-1.13:
    actuator_outputs, no actuator_motors, no CA_*)."""
    t = np.arange(0, 20e6, 2e4, dtype=np.uint64) + 1_000_000
    n = t.size
    z = np.zeros(n)
    out = np.full((n, 16), 0.0)
    out[:, :channels] = 900.0
    ph = np.linspace(0, 20, n)
    for k in range(moving):
        out[:, k] = 1400 + 300 * np.sin(ph + k)
    topics = {"vehicle_attitude": {"timestamp": t, "q[0]": np.ones(n), "q[1]": z, "q[2]": z, "q[3]": z},
              "vehicle_local_position": {"timestamp": t, "x": z, "y": z, "z": -np.linspace(0, 5, n),
                                         "vx": z, "vy": z, "vz": z},
              "actuator_outputs": {"timestamp": t, "noutputs": np.full(n, channels), "output": out},
              "vehicle_status": {"timestamp": t, "arming_state": np.full(n, 2), "nav_state": np.full(n, 2)}}
    write_px4_ulog(str(path), topics, params, {"sys_name": "test"})
    return read_ulog(str(path))


def test_clover4_4500_on_px4_113_starts_as_quad_x(tmp_path):
    log = _log(tmp_path / "clover.ulg", {"SYS_AUTOSTART": 4500, "SYS_CTRL_ALLOC": 0, "MAV_TYPE": 2}, 4)
    assert log.moving_outputs == (4, "actuator_outputs[0].output") and log.n_motors == 4
    lay = rotor_layout(log.params, log.path, None, log.moving_outputs)
    # PX4 Motor1 is front right (FRD y > 0), so FLU y < 0
    a = 0.25 * S                                     # ASSUMED quad class arm 0.25 m
    np.testing.assert_allclose(lay.x_flu_m, [a, -a, a, -a], atol=1e-9)
    np.testing.assert_allclose(lay.y_flu_m, [-a, a, a, -a], atol=1e-9)
    assert lay.direction == (CCW, CCW, CW, CW) and lay.coaxial == ()
    assert "4500" in lay.source and "quad_x" in lay.source and "ASSUMED" in lay.source
    lay2 = rotor_layout(log.params, log.path, 0.125, log.moving_outputs)
    assert math.hypot(lay2.x_flu_m[0], lay2.y_flu_m[0]) == pytest.approx(0.125) and "--arm-m" in lay2.source


def test_octo_coax_12001_on_px4_18_starts_with_four_coaxial_pairs(tmp_path):
    log = _log(tmp_path / "x8.ulg", {"SYS_AUTOSTART": 12001, "MAV_TYPE": 14}, 8)
    assert log.moving_outputs[0] == 8 and log.n_motors == 8
    lay = rotor_layout(log.params, log.path, 0.4, log.moving_outputs)
    assert len(lay.x_flu_m) == 8
    assert lay.coaxial == ((0, 5), (1, 4), (2, 7), (3, 6))
    for i, j in lay.coaxial:
        assert (lay.x_flu_m[i], lay.y_flu_m[i]) == pytest.approx((lay.x_flu_m[j], lay.y_flu_m[j]))
        assert lay.direction[i] == -lay.direction[j]
        assert lay.z_flu_m[i] > lay.z_flu_m[j]        # the first of each pair is the top rotor (FLU z up)
    np.testing.assert_allclose(np.hypot(lay.x_flu_m, lay.y_flu_m), 0.4, rtol=1e-9)
    assert "octo_cox" in lay.source and "8c" in lay.source


def test_a_rotor_count_the_moving_outputs_contradict_is_refused_in_one_line(tmp_path):
    log = _log(tmp_path / "x8.ulg", {"SYS_AUTOSTART": 12001, "MAV_TYPE": 14}, 6)
    with pytest.raises(ParamsError) as e:
        rotor_layout(log.params, log.path, None, log.moving_outputs)
    msg = str(e.value)
    assert len(msg.splitlines()) == 1
    assert "8 rotors" in msg and "6 motor outputs move" in msg
    # the nominal builder refuses the same log the same way (one line)
    from twin_nodes.identify.nominal import nominal_from_log
    with pytest.raises(ParamsError, match="8 rotors .* 6 motor outputs move"):
        nominal_from_log(log)


def test_unknown_airframe_takes_its_mav_type_class_marked_assumed(tmp_path):
    log = _log(tmp_path / "hexa.ulg", {"SYS_AUTOSTART": 6789, "MAV_TYPE": 13}, 6)
    lay = rotor_layout(log.params, log.path, None, log.moving_outputs)
    assert len(lay.x_flu_m) == 6 and lay.source.startswith("ASSUMED generic PX4 hex_x")
    assert "MAV_TYPE 13" in lay.source and "6 moving" in lay.source
    assert lay.direction == tuple(d for *_, d in _rotors("6x"))
    # the moving outputs must confirm the class's rotor count
    log4 = _log(tmp_path / "four.ulg", {"SYS_AUTOSTART": 6789, "MAV_TYPE": 13}, 4)
    with pytest.raises(ParamsError, match="6 rotors .* 4 motor outputs move"):
        rotor_layout(log4.params, log4.path, None, log4.moving_outputs)


def test_params_is_asked_for_only_when_the_rotor_count_is_unknown(tmp_path):
    log = _log(tmp_path / "odd.ulg", {"SYS_AUTOSTART": 6789, "MAV_TYPE": 3}, 2)
    with pytest.raises(ParamsError, match="coaxial helicopter.*--params"):
        rotor_layout(log.params, log.path, None, log.moving_outputs)
    with pytest.raises(ParamsError, match="CA_ROTOR_COUNT.*--params"):
        rotor_layout({"SYS_AUTOSTART": 6789, "MAV_TYPE": 2}, "x.ulg", None, None)


def test_an_airframe_whose_mixer_changed_between_versions_is_refused_not_guessed():
    """4900 Crazyflie: quad_x until 2019-10, quad_x_cw (another motor order) from 2020-06."""
    with pytest.raises(ParamsError, match="quad_x -> 4x.*quad_x_cw -> 4xcw"):
        rotor_layout({"SYS_AUTOSTART": 4900}, "cf.ulg")


def test_bebop_yaw_reversed_by_its_r_line():
    lay = rotor_layout({"SYS_AUTOSTART": 4013}, "b.ulg", 0.1)
    assert lay.direction == (CW, CW, CCW, CCW) and "yaw reversed" in lay.source


def test_ca_logs_and_known_airframes_unchanged():
    """CA_* parameters still win over the table; a known airframe (AIRFRAMES) keeps its layout and arm."""
    ca = {"SYS_AUTOSTART": 12001, "CA_ROTOR_COUNT": 4}
    for i, (x, y, km) in enumerate([(0.2, 0.2, 0.05), (-0.2, -0.2, 0.05), (0.2, -0.2, -0.05), (-0.2, 0.2, -0.05)]):
        ca.update({f"CA_ROTOR{i}_PX": x, f"CA_ROTOR{i}_PY": y, f"CA_ROTOR{i}_KM": km})
    assert len(rotor_layout(ca, "f.ulg").x_flu_m) == 4
    lay = rotor_layout({"SYS_AUTOSTART": 4014}, "s500.ulg", None, (4, "actuator_outputs[0].output"))
    assert math.hypot(lay.x_flu_m[0], lay.y_flu_m[0]) == pytest.approx(0.24)
    with pytest.raises(ParamsError, match="4 rotors .* 3 motor outputs move"):
        rotor_layout({"SYS_AUTOSTART": 4014}, "s500.ulg", None, (3, "actuator_outputs[0].output"))
