"""The fleet throughput shortcuts give the answers of the paths they short-cut (docs/fleet.md, Throughput).

- the closed-loop runner compares setpoint samples with ``runner._same`` instead of ``np.array_equal``;
- the offline closed-loop run decides what each log row flies, whether its setpoint sample is new and its
  carried terms once for all rows (``runner._row_decisions``) instead of per control step (ninth session);
- ``VehicleParams.with_effect`` on a validated parent checks only the new effect (the rest was checked);
- ``fleet discover`` reads a log's GPS time and its actuator-test commands in one pass (``side_topics``).
- ``params._validate`` skips a pure check whose inputs passed it before (``params._PASSED``), and the held
  twin's rotor states are kept per runner by its command (``GroundHandling._rest_reference``; seventeenth session).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import missing_shared

from twin_nodes.base.errors import ParamsError
from twin_nodes.twin.flight_mode import fly_mode, fly_modes
from twin_nodes.twin.inputs import LogFeed
from twin_nodes.twin.runner import TwinRunner, _row_decisions, _same, _same_as_previous
from twin_nodes.vehicle.params import _known_valid, load_params, validate

ROOT = Path(__file__).resolve().parents[1]
FLEET = ROOT.parent / "shared" / "flightlogs" / "fleet_quadx_v6c"


def test_same_is_array_equal_with_nan():
    rng = np.random.default_rng(7)
    pool = np.array([0.0, -0.0, 1.0, -1.5, np.nan, np.inf, -np.inf, 2.5e-300])
    n_diff = 0
    for _ in range(3000):
        a = rng.choice(pool, size=9)
        b = a.copy()
        if rng.random() < 0.6:  # change a few entries (NaN for NaN too: equal again)
            idx = rng.integers(0, 9, size=rng.integers(1, 4))
            b[idx] = rng.choice(pool, size=idx.size)
        want = bool(np.array_equal(a, b, equal_nan=True))
        n_diff += not want
        assert _same(a.tolist(), b.tolist()) is want, (a, b)
    assert 300 < n_diff < 2700  # both answers were exercised


def test_same_as_previous_is_same_row_by_row():
    rng = np.random.default_rng(11)
    pool = np.array([0.0, -0.0, 1.0, np.nan, np.inf, -np.inf])
    rows = rng.choice(pool, size=(400, 9))
    rows[1::3] = rows[0:-1:3]  # repeats
    rows[2::5, :4] = np.nan  # NaN for NaN
    got = _same_as_previous(rows)
    prev = np.vstack([np.full((1, 9), np.nan), rows[:-1]])
    want = [_same(a.tolist(), b.tolist()) for a, b in zip(rows, prev)]
    assert got.tolist() == want
    assert 50 < sum(want) < 350
    assert _same_as_previous(np.zeros((0, 2))).shape == (0,)


def _random_feed(rng, n: int) -> LogFeed:
    """Log rows that exercise every branch of fly_mode: the manual, ACRO, ALTCTL, OFFBOARD and AUTO nav states,
    thrust, attitude, rate and trajectory setpoints and offboard flags each present, partly NaN or absent."""
    def maybe_nan(a, p=0.3):
        a = np.array(a, float)
        a[rng.random(a.shape) < p] = np.nan
        return a
    sp = maybe_nan(rng.choice([0.0, -0.0, 1.5, -2.0], size=(n, 11)), 0.4)
    sp[1::4] = sp[0:-1:4]  # repeated samples
    flags = rng.choice([0.0, 1.0], size=(n, 6))
    flags[rng.random(n) < 0.3] = np.nan
    return LogFeed(t=np.arange(n) * 0.004, x=np.zeros((n, 13)), finite=np.ones(n, bool), motors=np.zeros((n, 4)),
                   sp=sp, repeated=np.zeros(n, bool), armed=np.ones(n), battery_v=np.full(n, np.nan),
                   nav_state=rng.choice([np.nan, 0.0, 1.0, 2.0, 3.0, 10.0, 14.0, 15.0, 16.0], size=n),
                   throttle=maybe_nan(rng.random(n)), att_q=maybe_nan(rng.random((n, 4)), 0.1),
                   att_thrust=maybe_nan(rng.random(n)), att_yawrate=maybe_nan(rng.random(n)),
                   rates_sp=maybe_nan(rng.random((n, 3)), 0.1), offboard=flags)


def test_row_decisions_are_the_runners_per_step_ones():
    """What ``run_twin_on_log`` decides per row equals what the runner decides per control step: fly_mode,
    the attitude setpoint's finiteness, new trajectory / yaw samples (``_same`` on the previous row) and the
    carried terms the runner makes from its (ground-shifted) setpoint."""
    rng = np.random.default_rng(5)
    feed = _random_feed(rng, 3000)
    rows = list(_row_decisions(feed, chunk=1000))  # several chunks
    modes, _ = fly_modes(feed.nav_state, feed.throttle, feed.att_q, feed.att_thrust, feed.rates_sp,
                         feed.offboard, feed.sp)
    seen = set()
    runner = TwinRunner(load_params(ROOT / "params" / "px4_sih_quadx.yaml"))
    prev = np.full(11, np.nan)
    for k, (how, q_ok, same, rates) in enumerate(rows):
        want = fly_mode(feed.nav_state[k], feed.throttle[k], feed.att_q[k], feed.att_thrust[k], feed.rates_sp[k],
                        feed.offboard[k], feed.sp[k], True)
        assert how == modes[k] == want, k
        seen.add(how)
        assert q_ok == bool(np.isfinite(feed.att_q[k]).all())
        new, old = feed.sp[k].tolist(), prev.tolist()
        assert same == (_same(new[0:9], old[0:9]), _same(new[9:11], old[9:11])), k
        prev = feed.sp[k]
        # the runner's own terms from the row shifted by a ground height (as _take_setpoint shifts it)
        runner.sp = feed.sp[k].copy()
        runner.sp[2] -= 0.7
        runner.sp_t, runner.yaw_t, runner.t, runner._sp_rates, runner._row_rates = 0.0, 0.0, 0.0, None, None
        runner._carried_setpoint()
        mine = runner._sp_rates
        assert (mine[0], mine[3], mine[4]) == (rates[0], rates[3], rates[4]), k
        assert np.array_equal(mine[1], rates[1]) and np.array_equal(mine[2], rates[2]), k
    assert seen == {"attitude", "rates", "real_attitude", "cascade"}


def test_with_effect_on_a_validated_parent_checks_as_validate_does():
    vp = load_params(ROOT / "params" / "px4_sih_quadx.yaml")
    assert _known_valid(vp)
    new = vp.with_effect("body_drag", c_dx=0.1, c_dy=0.2, c_dz=0.05).with_effect("motor_efficiency", motor=2,
                                                                                  efficiency=0.8)
    assert _known_valid(new)
    assert new.effect_dict == {**vp.effect_dict, "body_drag": {"c_dx": 0.1, "c_dy": 0.2, "c_dz": 0.05},
                               "motor_efficiency": {"motor": 2.0, "efficiency": 0.8}}
    validate(new)  # the full check agrees
    # a bad value of the new effect: the same one-line error as the full check gives
    bad = [("linear_drag", {"k_n_s_m": -1.0}), ("linear_drag", {"k_n_s_m": float("nan")}),
           ("motor_efficiency", {"motor": 9, "efficiency": 0.8}), ("linear_drag", {"k": 1.0})]
    for name, params in bad:
        with pytest.raises(ParamsError) as fast:
            vp.with_effect(name, **params)
        with pytest.raises(ParamsError) as full:
            vp.replace(effects=tuple(e for e in vp.effects if e[0] != name)
                       + ((name, tuple((k, float(v)) for k, v in params.items())),))
        assert str(fast.value) == str(full.value)


def test_with_effect_after_a_controller_edit_validates_everything():
    vp = load_params(ROOT / "params" / "px4_sih_quadx.yaml")
    edited = vp.replace(controller={**dict(vp.controller or {}), "rate_hz": 250.0})
    assert _known_valid(edited)
    edited.controller["rate_hz"] = 0.0  # the one mutable field, changed after its check: no shortcut
    assert not _known_valid(edited)
    with pytest.raises(ParamsError, match="controller.rate_hz"):
        edited.with_effect("linear_drag", k_n_s_m=0.1)


def _shared_logs() -> list[Path]:
    if not FLEET.is_dir():
        missing_shared("flightlogs/fleet_quadx_v6c")  # skips locally, fails under CI=true
    logs = sorted(FLEET.rglob("*.ulg"))
    # a ground/bench test with actuator-test commands (23 Jun log_11), a free flight, a flight without GPS fix
    pick = [p for p in logs if p.name.startswith(("log_11_2023-6-23", "log_15_2023-6-23", "log_59_2023-6-21"))]
    assert len(pick) == 3, pick
    return pick


def test_one_side_pass_gives_what_the_two_reads_gave():
    """Identity (date from the first GPS fix) and the actuator-test count, hence the flight kind, from the one
    side pass equal those of the separate reads, on a bench test, a free flight and a flight without GPS."""
    from twin_nodes.fleet.facts import actuator_tests, flight_kind
    from twin_nodes.fleet.identity import identity, side_reader
    from twin_nodes.logs.ulog_io import read_ulog

    kinds = []
    for p in _shared_logs():
        side = side_reader(p)
        assert side() is not None and side() is side()  # read once
        assert identity(p, side) == identity(p)
        n = actuator_tests(p, side)
        assert n == actuator_tests(p)
        log = read_ulog(p)
        kinds.append(flight_kind(log, n)[0])
        assert kinds[-1] == flight_kind(log, actuator_tests(p))[0]
    assert kinds == ["ground/bench test", "free flight", "no GPS"]
    assert identity(_shared_logs()[1], side_reader(_shared_logs()[1]))["date_source"] == "gps"


def test_side_pass_of_an_unreadable_file_falls_back(tmp_path):
    bad = tmp_path / "bad.ulg"
    bad.write_bytes(b"ULog\x01\x12\x35\x01" + b"\x00" * 40)
    from twin_nodes.fleet.facts import actuator_tests
    from twin_nodes.fleet.identity import _gps_time, side_reader

    side = side_reader(bad)
    assert _gps_time(bad, side) == _gps_time(bad) and actuator_tests(bad, side) == actuator_tests(bad) == 0


def test_hooked_rotor_states_reused_only_where_the_kernel_reads_the_same():
    """A vehicle with a command-path hook (battery sag): the rotor states are kept per flight and given again
    for a candidate that leaves the command path alone (a mass), bit for bit what a fresh integration gives;
    another sag exponent, another motor lag or another exogenous series (a wind) integrate anew."""
    from twin_nodes.discovery import residuals as rs
    from twin_nodes.logs.ulog_io import read_ulog
    from twin_nodes.physics.model import Multirotor
    from twin_nodes.vehicle.params import shipped

    log = read_ulog(ROOT / "bags" / "sim_quadx_weak_motor3.ulg")
    vp = shipped("px4_sih_quadx").with_effect("battery_sag", v_ref=16.0, exponent=0.9)
    data = rs.prepare(log, vp)

    def fresh(v):
        data.cache.clear()
        return np.array(rs.model_rotor_states(Multirotor(v), data))

    variants = {"sag": vp, "mass": vp.with_effect("mass", mass=1.3 * vp.mass_kg),
                "exponent": vp.with_effect("battery_sag", v_ref=16.0, exponent=1.1),
                "lag": vp.with_effect("motor_time_constant", tau_up=0.08, tau_down=0.08),
                "wind": vp.with_effect("wind", vx=2.0, vy=0.0, gust_std=0.5)}
    want = {k: fresh(v) for k, v in variants.items()}
    data.cache.clear()
    first = rs.model_rotor_states(Multirotor(vp), data)
    again = rs.model_rotor_states(Multirotor(variants["mass"]), data)
    assert again is first and np.array_equal(again, want["mass"]) and np.array_equal(want["mass"], want["sag"])
    for k in ("exponent", "lag", "wind", "sag", "mass"):
        got = rs.model_rotor_states(Multirotor(variants[k]), data)
        assert np.array_equal(got, want[k], equal_nan=True), k
    assert not np.array_equal(want["exponent"], want["sag"]) and not np.array_equal(want["lag"], want["sag"])
    # what is kept is the rotor states alone, on the residual's grid: the exogenous series (10x finer) by its
    # digest (16 kept copies of it took a 60-min flight's discovery over its memory budget)
    kept = [v for k, v in data.cache.items() if isinstance(k, tuple) and k[0] == "rotor_hooked"]
    assert kept and all(isinstance(v, np.ndarray) and v.shape == first.shape for v in kept)


def test_hooked_wind_states_keyed_on_the_wind_not_its_series(monkeypatch):
    """A vehicle with a command-path hook (battery sag) and a wind candidate: the kept rotor states are found by
    the wind's class and parameters (the same ones make the same exogenous series), so a repeated wind is given
    its kept states without its series being made or hashed (~1 ms each on the command grid; fps16); another
    wind speed or gust level is another key and integrates anew, each bit for bit a fresh integration."""
    from twin_nodes.discovery import residuals as rs
    from twin_nodes.logs.ulog_io import read_ulog
    from twin_nodes.physics.model import Multirotor
    from twin_nodes.vehicle.params import shipped

    log = read_ulog(ROOT / "bags" / "sim_quadx_weak_motor3.ulg")
    vp = shipped("px4_sih_quadx").with_effect("battery_sag", v_ref=16.0, exponent=0.9)
    data = rs.prepare(log, vp)
    nf, up = len(data.u_fine), data.up
    winds = {"a": dict(vx=2.0, vy=0.0, gust_std=0.5), "b": dict(vx=2.5, vy=0.0, gust_std=0.5),
             "c": dict(vx=2.0, vy=0.0, gust_std=0.0), "d": dict(vx=2.0, vy=-0.0, gust_std=0.5)}
    models = {k: Multirotor(vp.with_effect("wind", **w)) for k, w in winds.items()}
    series = {k: rs.exogenous(m, data, nf, up) for k, m in models.items()}
    keys = {k: rs._exogenous_key(m, nf, up) for k, m in models.items()}
    for k in winds:   # the same key for a wind built again; equal keys only where the series are equal
        assert rs._exogenous_key(Multirotor(vp.with_effect("wind", **winds[k])), nf, up) == keys[k]
        for j in winds:
            if keys[k] == keys[j]:
                assert np.array_equal(series[k], series[j]), (k, j)
    assert len(set(keys.values())) == 4 and not rs._plain_exogenous(models["a"])

    def fresh(m):
        data.cache.clear()
        return np.array(rs.model_rotor_states(m, data))

    want = {k: fresh(m) for k, m in models.items()}
    assert not np.array_equal(series["a"], series["b"]) and not np.array_equal(series["a"], series["c"])
    data.cache.clear()
    first = rs.model_rotor_states(models["a"], data)
    made = []
    monkeypatch.setattr(rs, "exogenous", lambda *a, **k: made.append(1))
    monkeypatch.setattr(rs, "_digest", lambda *a, **k: made.append(1))
    again = rs.model_rotor_states(Multirotor(vp.with_effect("wind", **winds["a"])), data)
    assert again is first and np.array_equal(again, want["a"]) and not made
    monkeypatch.undo()
    for k in ("b", "c", "d", "a"):
        assert np.array_equal(rs.model_rotor_states(models[k], data), want[k], equal_nan=True), k


def test_row_scalars_chunked_are_the_rows_and_the_next_time():
    """The offline run's per-row scalars, made a chunk at a time (bounded memory on long logs): every row's
    values as Python scalars and the next row's time (None after the last), whatever the chunk."""
    from twin_nodes.twin.runner import _row_scalars
    t = np.linspace(0.0, 1.0, 11)
    flags = t > 0.45
    for chunk in (1, 3, 10, 11, 50):
        rows = list(_row_scalars([t, flags], chunk=chunk))
        assert [r[0] for r in rows] == t.tolist() and [r[1] for r in rows] == flags.tolist()
        assert [r[2] for r in rows] == t.tolist()[1:] + [None]
        assert all(type(r[0]) is float and type(r[1]) is bool for r in rows)


def _outcome(vp, **changes):
    """What ``vp.replace(**changes)`` gives: None (valid) or the error's text."""
    try:
        vp.replace(**changes)
    except ParamsError as e:
        return str(e)
    return None


def test_validate_with_kept_passes_raises_as_the_full_check():
    """``_validate`` skips a pure check (inertia, rotor geometry, each effect, the controller gains) whose inputs
    passed it before (``params._PASSED``): every variant below, checked right after valid sets that share all but
    the one changed input, gives what it gives with nothing kept (the same error text, or valid)."""
    import dataclasses

    from twin_nodes.vehicle import params as pm

    vp = load_params(ROOT / "params" / "px4_sih_quadx.yaml").with_effect("battery_sag", v_ref=16.0, exponent=0.9)
    key = "rate_hz"
    ctrl = {**dict(vp.controller or {}), key: 250.0}
    vp = vp.replace(controller=ctrl)
    r = vp.rotors
    variants = [
        {"mass_kg": 1.2 * vp.mass_kg}, {"mass_kg": -1.0}, {"mass_kg": 1e3 * vp.mass_kg},
        {"inertia_kg_m2": ((1.0, 0.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, 1.0))},
        {"inertia_kg_m2": tuple(tuple(2.0 * e for e in row) for row in vp.inertia_kg_m2)},
        {"rotors": dataclasses.replace(r, x_flu_m=tuple(0.0 for _ in r.x_flu_m))},
        {"rotors": dataclasses.replace(r, x_flu_m=tuple(1e6 * x for x in r.x_flu_m))},
        {"rotors": dataclasses.replace(r, tau_up_s=0.05)},
        {"effects": vp.effects[:-1] + (("battery_sag", (("v_ref", -16.0), ("exponent", 0.9))),)},
        {"effects": vp.effects[:-1] + (("battery_sag", (("v_ref", 16.0), ("exponent", 1.1))),)},
        {"controller": {**ctrl, key: -1.0}}, {"controller": {**ctrl, key: True}},
        {"controller": {**ctrl, key: float("nan")}}, {"controller": {**ctrl, "law": "pid"}},
    ]
    pm._PASSED.clear()
    fresh = []
    for ch in variants:
        pm._PASSED.clear()
        fresh.append(_outcome(vp, **ch))
    assert sum(f is not None for f in fresh) >= 9 and None in fresh  # valid and invalid variants of each input
    for _ in range(2):  # with every valid set's passes kept, in both orders
        for ch, want in zip(variants, fresh):
            validate(vp)
            assert _outcome(vp, **ch) == want, ch
        variants, fresh = variants[::-1], fresh[::-1]
    assert any(k[0] == "controller" for k in pm._PASSED) and any(k[0] == "geometry" for k in pm._PASSED)
    # a controller edited in place after its pass is checked again (the key is its contents, made at each check)
    edited = vp.replace(controller=dict(ctrl))
    edited.controller[key] = -1.0
    with pytest.raises(ParamsError, match=f"controller.{key}"):
        validate(edited)


def test_rest_reference_kept_is_the_fresh_one():
    """The held twin's rotor states (``GroundHandling._rest_reference``, kept per runner by the command's bytes)
    equal ``reference_from_command(nan_to_num(u))`` for every command, repeated or not."""
    from twin_nodes.vehicle.params import shipped

    runner = TwinRunner(shipped("px4_sih_quadx"))
    rng = np.random.default_rng(3)
    cmds = [np.zeros(4), np.full(4, np.nan), np.array([0.2, np.nan, 1.5, -0.1])]
    cmds += [rng.uniform(-0.2, 1.2, 4) for _ in range(100)]
    for u in cmds + cmds[::-1] + cmds[:3] * 5:
        want = runner.params.rotors.reference_from_command(np.nan_to_num(u))
        got = runner._rest_reference(u)
        assert got.dtype == want.dtype and got.tobytes() == want.tobytes()
    assert len(runner._rest_refs) <= 64


def test_sum_terms_is_sum_bit_for_bit():
    """``residuals._sum_terms`` adds into one array what ``sum`` adds into new ones: the same bytes, signed zeros,
    NaN and infinities included, for strided term views as ``Multirotor.wrench_terms`` gives them."""
    from twin_nodes.discovery.residuals import _sum_terms

    rng = np.random.default_rng(11)
    pool = np.array([0.0, -0.0, 1.0, -1.0, 1e-300, -3.5, np.nan, np.inf, -np.inf, 1e300])
    for n_terms in (1, 2, 3, 5):
        for _ in range(50):
            F = rng.choice(pool, size=(40, n_terms, 3)) * rng.choice([1.0, rng.normal()], size=(40, n_terms, 3))
            terms = [F[:, j] for j in range(n_terms)]
            want, got = sum(terms), _sum_terms(iter(terms))
            assert got.shape == want.shape and got.tobytes() == want.tobytes()
            assert all(t.base is F for t in terms)


def test_measured_force_and_moment_kept_apart_equal_a_fresh_make():
    """``residuals._measured`` keeps m f on the mass and J alpha + w x J w on the inertia: after other masses and
    inertias each pair is bit for bit what an empty cache makes."""
    from twin_nodes.discovery import residuals as rs
    from twin_nodes.logs.ulog_io import read_ulog
    from twin_nodes.physics.model import Multirotor
    from twin_nodes.vehicle.params import shipped

    log = read_ulog(ROOT / "bags" / "sim_quadx_weak_motor3.ulg")
    vp = shipped("px4_sih_quadx")
    data = rs.prepare(log, vp)
    variants = [vp, vp.with_effect("mass", mass=1.2 * vp.mass_kg),
                vp.with_effect("inertia", ixx=1.1 * vp.inertia[0, 0], iyy=vp.inertia[1, 1], izz=vp.inertia[2, 2])]
    variants += [vp.replace(mass_kg=m * vp.mass_kg) for m in np.linspace(0.8, 1.3, 25)]
    fresh = []
    for v in variants:
        data.cache.clear()
        fresh.append([a.copy() for a in rs._measured(data, Multirotor(v).params)])
    for v, want in list(zip(variants, fresh)) * 2:
        got = rs._measured(data, Multirotor(v).params)
        assert all(g.tobytes() == w.tobytes() for g, w in zip(got, want))
