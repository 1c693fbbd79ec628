"""Shipped files under params/, bad params files, and the ``rotortwin params`` CLI.

``params/derive_*.yaml`` are derivation specs (inputs of ``rotortwin params
derive``), every other ``params/*.yaml`` is a vehicle params file.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from twin_nodes.cli import main
from twin_nodes.vehicle.derive import RPM_TO_RAD_S, derive_file
from twin_nodes.base.errors import ParamsError
from twin_nodes.vehicle.params import VehicleParams, load_params

PARAMS = Path(__file__).resolve().parent.parent / "params"
SPECS = sorted(PARAMS.glob("derive_*.yaml"))
PARAM_FILES = sorted(p for p in PARAMS.glob("*.yaml") if not p.name.startswith("derive_"))


def test_there_are_files():
    names = {p.name for p in PARAM_FILES}
    assert {"buho_negro.yaml", "px4_sih_quadx.yaml", "quad_c_3dr.yaml"} <= names
    assert {"derive_buho_negro.yaml", "derive_quad_c_3dr.yaml"} <= {p.name for p in SPECS}


@pytest.mark.parametrize("path", PARAM_FILES, ids=lambda p: p.name)
def test_every_params_file_loads(path):
    vp = load_params(path)
    assert vp.mass_kg > 0
    assert 0.0 < vp.hover_command < 1.0


@pytest.mark.parametrize("path", SPECS, ids=lambda p: p.name)
def test_every_spec_derives(path):
    d = derive_file(path)
    assert isinstance(d.params, VehicleParams)


def _assert_same(a: VehicleParams, b: VehicleParams, rel: float, abs_pos: float) -> None:
    assert a.name == b.name
    assert a.mass_kg == pytest.approx(b.mass_kg, rel=rel)
    np.testing.assert_allclose(a.inertia, b.inertia, rtol=rel, atol=1e-15)
    ra, rb = a.rotors, b.rotors
    np.testing.assert_allclose(ra.positions_flu_m, rb.positions_flu_m, atol=abs_pos)
    assert ra.direction == rb.direction
    assert ra.thrust_model == rb.thrust_model
    for f in ("kt_n_s2_rad2", "km_m", "omega_min_rad_s", "omega_cmd_max_rad_s", "omega_max_rad_s",
              "tau_up_s", "tau_down_s"):
        assert getattr(ra, f) == pytest.approx(getattr(rb, f), rel=rel), f


def test_buho_spec_reproduces_buho_params():
    # buho_negro.yaml was written by hand from the paper (positions to 6 decimals).
    _assert_same(derive_file(PARAMS / "derive_buho_negro.yaml").params,
                 load_params(PARAMS / "buho_negro.yaml"), rel=1e-9, abs_pos=1e-6)


def test_buho_paper_numbers_from_spec():
    d = derive_file(PARAMS / "derive_buho_negro.yaml")
    r = d.params.rotors
    assert r.kt_n_s2_rad2 == pytest.approx(2.4066e-4, rel=1e-3)
    assert r.omega_max_rad_s == pytest.approx(487.0, abs=1.0)
    assert r.tau_up_s == pytest.approx(0.0227, abs=5e-4)
    assert r.tau_down_s == pytest.approx(0.028, abs=1e-9)
    assert r.omega_min_rad_s == pytest.approx(97.4)
    assert r.omega_cmd_max_rad_s == pytest.approx(462.65)
    assert d.value("omega_hover_rad_s") == pytest.approx(244.4, abs=0.1)
    assert d.value("thrust_to_weight_at_cmd_max") == pytest.approx(3.58, abs=0.01)


def test_quad_c_spec_regenerates_quad_c_params_exactly():
    _assert_same(derive_file(PARAMS / "derive_quad_c_3dr.yaml").params,
                 load_params(PARAMS / "quad_c_3dr.yaml"), rel=1e-12, abs_pos=1e-15)


def test_quad_c_numbers():
    d = derive_file(PARAMS / "derive_quad_c_3dr.yaml")
    vp = d.params
    r = vp.rotors
    assert r.tau_up_s == 0.15 and r.tau_down_s == 0.15
    # kt from the datasheet point: 1.380 kg-force at 7350 rpm.
    assert r.kt_n_s2_rad2 == pytest.approx(1.380 * 9.80665 / (7350 * RPM_TO_RAD_S) ** 2, rel=1e-4)
    # Mass that kt carries at 3745 rpm (ref 2: kt = m g / (4 w_h^2)).
    assert vp.mass_kg == pytest.approx(1.433, abs=1e-3)
    assert vp.hover_omega_rad_s / RPM_TO_RAD_S == pytest.approx(3745, abs=2)
    # PWM map: 3745 + 6.5 (pwm - 1425) rpm over 1000..2000 us; hover command = (1425-1000)/1000.
    assert r.omega_min_rad_s / RPM_TO_RAD_S == pytest.approx(982.5, abs=0.5)
    assert r.omega_cmd_max_rad_s / RPM_TO_RAD_S == pytest.approx(7482.5, abs=0.5)
    assert vp.hover_command == pytest.approx(0.425, abs=1e-3)
    slope = (r.omega_cmd_max_rad_s - r.omega_min_rad_s) / 1000.0 / RPM_TO_RAD_S
    assert slope == pytest.approx(6.5, abs=1e-3)
    # Inertia from shapes: symmetric, Izz about the sum of Ixx and Iyy for a flat frame.
    i = vp.inertia
    assert i[0, 0] == i[1, 1] and np.count_nonzero(i - np.diag(np.diag(i))) == 0
    assert i[0, 0] == pytest.approx(0.01948) and i[2, 2] == pytest.approx(0.03511)
    assert d.value("stack_mass_kg") == pytest.approx(0.893)
    assert any("above the stated maximum" in n for n in d.notes)


# --------------------------------------------------------------------------- bad params files


def _buho_doc() -> dict:
    return yaml.safe_load((PARAMS / "buho_negro.yaml").read_text())


def _write(tmp_path: Path, doc, name="bad.yaml") -> Path:
    p = tmp_path / name
    p.write_text(doc if isinstance(doc, str) else yaml.safe_dump(doc))
    return p


def _params(doc: dict) -> dict:
    return doc["/**"]["ros__parameters"]


def _mutate_missing(d):
    del _params(d)["rotors"]["kt_n_s2_rad2"]


def _mutate_negative_mass(d):
    _params(d)["vehicle"]["mass_kg"] = -5.86


def _mutate_inertia(d):
    _params(d)["vehicle"]["ixy_kg_m2"] = 0.5


def _mutate_omega(d):
    _params(d)["rotors"]["omega_min_rad_s"] = 470.0


def _mutate_unknown(d):
    _params(d)["vehicle"]["masss_kg"] = 5.0


def _set(section, key, value):
    def mutate(d):
        _params(d)[section][key] = value
    return mutate


def _set_effect(name, **values):
    def mutate(d):
        eff = _params(d)["effects"]
        eff["enabled"] = [name]
        eff[name] = values
    return mutate


BAD = [
    ("missing key", _mutate_missing, "rotors.kt_n_s2_rad2", "missing"),
    ("negative mass", _mutate_negative_mass, "vehicle.mass_kg", "expected 0.001..10000 kg, got -5.86"),
    ("inertia not positive definite", _mutate_inertia, "vehicle.ixx_kg_m2", "inertia tensor must be positive definite"),
    ("omega_min >= omega_cmd_max", _mutate_omega, "rotors.omega_min_rad_s",
     "expected omega_min_rad_s < omega_cmd_max_rad_s"),
    ("unknown key", _mutate_unknown, "vehicle.masss_kg", "unknown key"),
    # issue 12: values that passed validation and then overflowed or hung the simulator
    ("thrust 1e308", _set("rotors", "kt_n_s2_rad2", 1e308), "rotors.kt_n_s2_rad2",
     "expected 1e-12..1e+06 N s^2/rad^2, got 1e+308"),
    ("thrust at full command 1e8", _set("rotors", "kt_n_s2_rad2", 500.0), "rotors.kt_n_s2_rad2",
     "expected a thrust at full command kt*omega_cmd_max^2 of 0.0001..1e+06 N per rotor, got 1.07023e+08 N"),
    ("inertia 1e308", _set("vehicle", "ixx_kg_m2", 1e308), "vehicle.ixx_kg_m2",
     "inertia tensor must be positive definite"),
    ("inertia too large for mass and size", _set("vehicle", "izz_kg_m2", 100.0), "vehicle.izz_kg_m2",
     "expected 5.86e-06..13.2 kg m^2 (radius of gyration 0.001..1.5 m for 5.86 kg and rotors up to 0.5 m out), "
     "got 100"),
    ("position 1e308", _set("rotors", "x_flu_m", [1e308, -0.35, 0.35, -0.35]), "rotors.x_flu_m",
     "expected rotor positions within 100 m of the centre of mass, got one at inf m"),
    ("mass 1e-300", _set("vehicle", "mass_kg", 1e-300), "vehicle.mass_kg", "expected 0.001..10000 kg, got 1e-300"),
    ("dt 1e-12", lambda d: _params(d).update(simulation={"dt_s": 1e-12}), "simulation.dt_s",
     "expected 1e-05..0.1 s, got 1e-12"),
    ("tau inf", _set("rotors", "tau_up_s", float("inf")), "rotors.tau_up_s", "expected a finite number, got inf"),
    ("huge integer", _set("vehicle", "mass_kg", 10**400), "vehicle.mass_kg", "expected a finite number, got 1000"),
    ("NaN in controller", lambda d: _params(d).update(controller={"rate_hz": float("nan")}),
     "controller.rate_hz", "expected a finite number, got nan"),
    ("effect motor outside the rotors", _set_effect("motor_efficiency", motor=9, efficiency=0.8),
     "effects.motor_efficiency.motor", "expected an integer motor index 1..4 (this vehicle has 4 rotors), got 9"),
    ("effect parameter NaN", _set_effect("motor_efficiency", motor=2, efficiency=float("nan")),
     "effects.motor_efficiency.efficiency", "expected a finite number, got nan"),
    ("effect parameter out of range", _set_effect("actuator_delay", delay=1e9),
     "effects.actuator_delay.delay", "expected a finite number in 0..2 [s], got 1e+09"),
]


@pytest.mark.parametrize("what,mutate,key,expected", BAD, ids=[b[0] for b in BAD])
def test_bad_params_file(tmp_path, what, mutate, key, expected):
    doc = _buho_doc()
    mutate(doc)
    path = _write(tmp_path, doc)
    with pytest.raises(ParamsError, match=re.escape(f"{path}: {key}: {expected}")) as info:
        load_params(path)
    assert "\n" not in str(info.value)
    assert info.value.key == key


@pytest.mark.parametrize("what", ["directory", "not UTF-8", "path through a file", "fifo", "too large"])
def test_unreadable_params_path_is_one_line(tmp_path, what):
    """A params path that is a directory, not UTF-8 or unreadable: one ParamsError, no traceback
    (issue 12; the old loader raised IsADirectoryError / UnicodeDecodeError / NotADirectoryError)."""
    path = tmp_path / "p.yaml"
    expected = {"directory": "<file>: expected a params YAML file, got a directory",
                "not UTF-8": "<file>: expected UTF-8 text, got byte 0xff at offset 31",
                "path through a file": "<file>: expected a readable params YAML file (Not a directory)",
                "fifo": "<file>: expected a params YAML file, got not a regular file",
                "too large": "<file>: expected a params YAML file of at most 1000000 bytes, got 1000001"}[what]
    if what == "directory":
        path.mkdir()
    elif what == "not UTF-8":
        path.write_bytes(b"/**:\n  ros__parameters:\n    v: \xff\xfe\n")
    elif what == "path through a file":
        (tmp_path / "file").write_text("x")
        path = tmp_path / "file" / "p.yaml"
    elif what == "fifo":
        os.mkfifo(path)  # opening it would block forever
    else:
        path.write_bytes(b"#" * 1_000_001)
    with pytest.raises(ParamsError) as info:
        load_params(path)
    assert str(info.value) == f"{path}: {expected}"


def test_yaml_nested_too_deep_is_one_line(tmp_path):
    path = _write(tmp_path, "[" * 20000 + "]" * 20000, "deep.yaml")
    with pytest.raises(ParamsError, match=re.escape(f"{path}: ")):
        load_params(path)


def test_not_yaml(tmp_path):
    path = _write(tmp_path, "/**:\n  ros__parameters:\n    vehicle: [unclosed\n")
    with pytest.raises(ParamsError, match=re.escape(f"{path}: line ") + r"\d+: not valid YAML") as info:
        load_params(path)
    assert "\n" not in str(info.value)


# --------------------------------------------------------------------------- CLI


def test_cli_check(capsys):
    assert main(["params", "check", str(PARAMS / "buho_negro.yaml")]) == 0
    out = capsys.readouterr().out
    assert "244.33 rad/s" in out and "0.4023" in out and "3.586" in out


def test_cli_derive_writes_everything(tmp_path, capsys):
    out, sdf, px4, af = (tmp_path / n for n in ("p.yaml", "m.sdf", "p.params", "airframe"))
    rc = main(["params", "derive", str(PARAMS / "derive_buho_negro.yaml"), "--out", str(out),
               "--sdf", str(sdf), "--px4", str(px4), "--airframe", str(af)])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "kt1 (D2/D1)^3 (P2/P1)" in printed and "omega_hover_rad_s" in printed
    _assert_same(load_params(out), load_params(PARAMS / "buho_negro.yaml"), rel=1e-9, abs_pos=1e-6)
    assert sdf.read_text().count("<plugin ") == 4
    assert "SIM_GZ_EC_MAX4\t463\t6" in px4.read_text()
    assert "param set-default CA_ROTOR3_KM -0.0238" in af.read_text()
    assert not list(tmp_path.glob("*.tmp"))


def test_cli_export(tmp_path):
    sdf = tmp_path / "m.sdf"
    assert main(["params", "export", str(PARAMS / "quad_c_3dr.yaml"), "--sdf", str(sdf)]) == 0
    assert "<motorConstant>2.2844e-05</motorConstant>" in sdf.read_text()


@pytest.mark.parametrize("what,mutate,key,expected", BAD[:2], ids=[b[0] for b in BAD[:2]])
def test_cli_bad_params_file_writes_nothing(tmp_path, capsys, what, mutate, key, expected):
    doc = _buho_doc()
    mutate(doc)
    bad = _write(tmp_path, doc)
    sdf = tmp_path / "out.sdf"
    sdf.write_text("keep me")  # an existing output must not be overwritten
    px4 = tmp_path / "out.params"
    # --force: the existing output may be replaced, so only the bad params file stops the run
    assert main(["params", "export", str(bad), "--sdf", str(sdf), "--px4", str(px4), "--force"]) != 0
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"rotortwin: error: {bad}: {key}: {expected}")
    assert "\n" not in err
    assert sdf.read_text() == "keep me"
    assert not px4.exists()
    assert main(["params", "check", str(bad)]) != 0


def test_cli_bad_spec_writes_nothing(tmp_path, capsys):
    spec = yaml.safe_load((PARAMS / "derive_buho_negro.yaml").read_text())
    spec["torque"]["km_m"] = -0.1
    bad = _write(tmp_path, spec, "spec.yaml")
    out = tmp_path / "p.yaml"
    out.write_text("keep me")
    sdf = tmp_path / "p.sdf"
    assert main(["params", "derive", str(bad), "--out", str(out), "--sdf", str(sdf), "--force"]) != 0
    err = capsys.readouterr().err
    assert f"{bad}: torque.km_m: expected >= 0" in err
    assert out.read_text() == "keep me" and not sdf.exists()


def test_cli_bad_output_dir_writes_nothing(tmp_path, capsys):
    out = tmp_path / "p.yaml"
    (tmp_path / "a_file").write_text("")
    rc = main(["params", "derive", str(PARAMS / "derive_buho_negro.yaml"), "--out", str(out),
               "--sdf", str(tmp_path / "a_file" / "m.sdf")])
    assert rc != 0
    assert "is a file" in capsys.readouterr().err
    assert not out.exists()


def test_cli_entry_point_exit_code(tmp_path):
    bad = _write(tmp_path, "vehicle: [", "bad.yaml")
    res = subprocess.run([sys.executable, "-m", "twin_nodes", "params", "check", str(bad)],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"rotortwin: error: {bad}: line ")


# --------------------------------------------------------------------------- issue 28: every value range-checked

SIH = PARAMS / "px4_sih_quadx.yaml"


def _sih_doc() -> dict:
    return yaml.safe_load(SIH.read_text())


def _on_line(d):
    """Every rotor on the x axis: no moment arm about x (roll)."""
    _params(d)["rotors"]["y_flu_m"] = [0.0, 0.0, 0.0, 0.0]


def _at_centre(d):
    r = _params(d)["rotors"]
    r["x_flu_m"], r["y_flu_m"] = [0.0] * 4, [0.0] * 4


#: (case, which file, mutation, key, message); each of these loaded before issue 28, or crashed
RANGES = [
    ("omega_max 1e-300 (thrust_factor: ZeroDivisionError)", "sih", _set("rotors", "omega_max_rad_s", 1e-300),
     "rotors.omega_max_rad_s", "expected 1..100000 rad/s, got 1e-300"),
    ("omega_cmd_max 1e-300", "sih", _set("rotors", "omega_cmd_max_rad_s", 1e-300),
     "rotors.omega_cmd_max_rad_s", "expected 1..100000 rad/s, got 1e-300"),
    ("omega_cmd_max 1e-300 (omega_squared)", "buho", _set("rotors", "omega_cmd_max_rad_s", 1e-300),
     "rotors.omega_cmd_max_rad_s", "expected 1..100000 rad/s, got 1e-300"),
    ("thrust_max 1e-300", "sih", _set("rotors", "thrust_max_n", 1e-300),
     "rotors.thrust_max_n", "expected 0.0001..1e+06 N, got 1e-300"),
    ("kt 1e-300", "buho", _set("rotors", "kt_n_s2_rad2", 1e-300),
     "rotors.kt_n_s2_rad2", "expected 1e-12..1e+06 N s^2/rad^2, got 1e-300"),
    ("kt given 1e-300 (thrust_factor)", "sih", _set("rotors", "kt_n_s2_rad2", 1e-300),
     "rotors.kt_n_s2_rad2", "expected 1e-12..1e+06 N s^2/rad^2 (default thrust_max_n / omega_max_rad_s^2), "
                            "got 1e-300"),
    ("km 1e-300", "buho", _set("rotors", "km_m", 1e-300), "rotors.km_m", "expected 0.0001..1 m, got 1e-300"),
    ("km 0 (no yaw authority)", "sih", _set("rotors", "km_m", 0.0), "rotors.km_m", "expected 0.0001..1 m, got 0"),
    ("all rotors at the centre", "buho", _at_centre, "rotors.x_flu_m",
     "expected rotor positions that span roll and pitch (an RMS spread about their centroid of at least "
     "0.001 m along every horizontal axis: a moment arm about both), got 0 m"),
    ("all rotors on one line", "sih", _on_line, "rotors.x_flu_m",
     "expected rotor positions that span roll and pitch"),
    ("controller rate 1e-300 Hz", "sih", lambda d: _params(d).update(controller={"rate_hz": 1e-300}),
     "controller.rate_hz", "expected 1..10000 Hz, got 1e-300"),
    ("controller tilt 120 deg", "sih", lambda d: _params(d).update(controller={"tilt_max_deg": 120.0}),
     "controller.tilt_max_deg", "expected > 0 and <= 89 deg, got 120.0"),
    ("controller gain -1", "buho", lambda d: _params(d).update(controller={"rate_p_1_s": -1.0}),
     "controller.rate_p_1_s", "expected 0..100000, got -1.0"),
    ("controller thr_min >= thr_max", "sih", lambda d: _params(d).update(controller={"thr_min": 0.5, "thr_max": 0.4}),
     "controller.thr_min", "expected < thr_max (0.4), got 0.5"),
]


@pytest.mark.parametrize("what,base,mutate,key,expected", RANGES, ids=[r[0] for r in RANGES])
def test_params_value_out_of_range(tmp_path, what, base, mutate, key, expected):
    doc = _sih_doc() if base == "sih" else _buho_doc()
    mutate(doc)
    path = _write(tmp_path, doc)
    with pytest.raises(ParamsError, match=re.escape(f"{path}: {key}: {expected}")) as info:
        load_params(path)
    assert "\n" not in str(info.value)


def test_in_memory_edits_are_range_checked():
    """``VehicleParams.replace*`` re-validates: the same ranges hold for edited params."""
    vp = load_params(SIH)
    for change, key in (({"omega_max_rad_s": 1e-300}, "rotors.omega_max_rad_s"),
                        ({"kt_n_s2_rad2": 1e-300}, "rotors.kt_n_s2_rad2"),
                        ({"y_flu_m": (0.0, 0.0, 0.0, 0.0)}, "rotors.x_flu_m")):
        with pytest.raises(ParamsError, match=re.escape(f": {key}: expected")):
            vp.replace_rotors(**change)
    with pytest.raises(ParamsError, match=re.escape(": controller.rate_hz: expected 1..10000 Hz")):
        vp.replace(controller={"rate_hz": 0.5})


@pytest.mark.parametrize("argv", [
    ["params", "check", "{P}"],
    ["simulate", "--params", "{P}", "--out", "{O}/s.ulg"],
    ["discover", "{O}/missing.ulg", "--params", "{P}", "--json", "{O}/r.json", "--no-closed-loop"],
], ids=["params check", "simulate", "discover"])
def test_cli_omega_max_1e300_is_one_line(tmp_path, capsys, monkeypatch, argv):
    """``omega_max_rad_s: 1e-300`` raised ZeroDivisionError in every command (issue 28)."""
    doc = _sih_doc()
    _params(doc)["rotors"]["omega_max_rad_s"] = 1e-300
    bad = _write(tmp_path, doc)
    out = tmp_path / "out"
    out.mkdir()
    monkeypatch.chdir(out)
    rc = main([a.replace("{P}", str(bad)).replace("{O}", str(out)) for a in argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert err == [f"rotortwin: error: {bad}: rotors.omega_max_rad_s: expected 1..100000 rad/s, got 1e-300"]
    assert list(out.iterdir()) == []


# --------------------------------------------------------------------------- duplicate keys


def test_duplicate_key_in_params_file_is_refused(tmp_path):
    text = SIH.read_text()
    assert text.count("      km_m: 0.02\n") == 1
    bad = _write(tmp_path, text.replace("      km_m: 0.02\n", "      km_m: 0.02\n      km_m: 0.03\n"))
    line = text.splitlines().index("      km_m: 0.02") + 2
    with pytest.raises(ParamsError, match=re.escape(f"{bad}: km_m: duplicate key at line {line} "
                                                    f"(first at line {line - 1})")):
        load_params(bad)


def test_duplicate_key_cli_one_line(tmp_path, capsys):
    text = SIH.read_text().replace("    vehicle:\n", "    vehicle:\n      mass_kg: 9.0\n", 1)
    bad = _write(tmp_path, text)
    assert main(["params", "check", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"rotortwin: error: {bad}: mass_kg: duplicate key at line "), err


def test_duplicate_key_in_spec_and_plan_is_refused(tmp_path):
    from twin_nodes.mavlink.mission import load_plan

    spec = (PARAMS / "derive_buho_negro.yaml").read_text()
    assert "\n  km_m: 0.0238\n" in spec
    bad = _write(tmp_path, spec.replace("\n  km_m: 0.0238\n", "\n  km_m: 0.0238\n  km_m: 0.0\n"), "spec.yaml")
    with pytest.raises(ParamsError, match=re.escape(f"{bad}: km_m: duplicate key at line ")):
        derive_file(bad)
    plans = sorted((PARAMS.parent / "missions").glob("*.plan.yaml"))
    assert plans
    text = plans[0].read_text()
    top = next(ln for ln in text.splitlines() if ln and ln[0].isalpha() and ":" in ln)
    bad = _write(tmp_path, text + "\n" + top + "\n", "plan.yaml")
    with pytest.raises(ParamsError, match=re.escape(f"{bad}: {top.split(':')[0]}: duplicate key at line ")):
        load_plan(bad)


def test_yaml_merge_keys_may_still_override():
    """YAML's merge key (``<<: *base``) is not a duplicate: the mapping's own key wins, as specified."""
    from twin_nodes.base.yamlio import safe_load

    assert safe_load("base: &b {a: 1, b: 2}\nx:\n  <<: *b\n  a: 3\n")["x"] == {"a": 3, "b": 2}
    with pytest.raises(Exception, match="duplicate key 'a'"):
        safe_load("x: {a: 1, a: 2}\n")


def test_no_plain_yaml_load_of_user_files():
    """Every YAML file is read through twin_nodes.base.yamlio (duplicate keys refused)."""
    root = PARAMS.parent / "twin_nodes"
    offenders = [f"{p.relative_to(root)}:{i}" for p in root.rglob("*.py") if p.name != "yamlio.py"
                 for i, line in enumerate(p.read_text().splitlines(), 1)
                 if re.search(r"yaml\.(safe_load|load|full_load|unsafe_load)\(", line)]
    assert offenders == []


# --------------------------------------------------------------------------- a log's PX4 parameters

_QUAD = [(0.2, 0.2), (-0.2, -0.2), (0.2, -0.2), (-0.2, 0.2)]


def _ca(**changes) -> dict:
    p = {"CA_ROTOR_COUNT": 4}
    for i, (x, y) in enumerate(_QUAD):
        p[f"CA_ROTOR{i}_PX"], p[f"CA_ROTOR{i}_PY"] = x, y
    p.update(changes)
    return p


@pytest.mark.parametrize("changes,key,expected", [
    ({"CA_ROTOR0_PX": float("inf")}, "CA_ROTOR0_PX", "expected a finite number -100..100 m, got inf"),
    ({"CA_ROTOR2_PY": float("nan")}, "CA_ROTOR2_PY", "expected a finite number -100..100 m, got nan"),
    ({"CA_ROTOR1_PZ": 1e30}, "CA_ROTOR1_PZ", "expected a finite number -100..100 m, got 1e+30"),
    ({"CA_ROTOR_COUNT": -4}, "CA_ROTOR_COUNT", "expected an integer 0..32, got -4"),
    ({"CA_ROTOR_COUNT": 2.5}, "CA_ROTOR_COUNT", "expected an integer 0..32, got 2.5"),
    ({"CA_ROTOR_COUNT": 1e9}, "CA_ROTOR_COUNT", "expected an integer 0..32, got 1e+09"),
    ({"SYS_AUTOSTART": float("nan")}, "SYS_AUTOSTART", "expected an integer 0..99999999, got nan"),
    ({"CA_ROTOR3_KM": float("inf")}, "CA_ROTOR3_KM", "expected a finite number -1..1, got inf"),
    ({f"CA_ROTOR{i}_PY": 0.0 for i in range(4)}, "CA_ROTOR0_PX", "expected rotor positions CA_ROTOR0..3_PX/PY "
                                                                 "that span roll and pitch"),
])
def test_log_rotor_parameters_range_checked(changes, key, expected):
    from twin_nodes.vehicle.px4_params import rotor_layout

    assert rotor_layout(_ca(), "f.ulg").x_flu_m == (0.2, -0.2, 0.2, -0.2)
    with pytest.raises(ParamsError, match=re.escape(f"f.ulg: {key}: {expected}")):
        rotor_layout(_ca(**changes), "f.ulg")


def test_log_sensor_timing_rates_range_checked():
    from twin_nodes.vehicle.px4_params import sensor_timing

    assert sensor_timing({"IMU_GYRO_CUTOFF": 40.0}).gyro_filter_s == pytest.approx(2 ** 0.5 / (2 * np.pi * 40))
    assert sensor_timing({"IMU_GYRO_CUTOFF": 0.0}).gyro_filter_s == 0.0
    with pytest.raises(ParamsError, match=re.escape("f.ulg: IMU_GYRO_CUTOFF: expected 0 (off) or 1..100000 Hz, "
                                                    "got 1e-300")):
        sensor_timing({"IMU_GYRO_CUTOFF": 1e-300}, "f.ulg")


@pytest.mark.parametrize("changes,line", [
    ({"CA_ROTOR0_PX": float("inf")}, "CA_ROTOR0_PX: expected a finite number -100..100 m, got inf"),
    ({"CA_ROTOR_COUNT": -4}, "CA_ROTOR_COUNT: expected an integer 0..32, got -4"),
], ids=["CA_ROTOR0_PX inf", "CA_ROTOR_COUNT -4"])
def test_cli_from_ulog_bad_log_parameters(tmp_path, capsys, changes, line):
    """``params from-ulog`` on a log whose CA_* parameters are unusable (a traceback or silently accepted
    before issue 28): one line naming the log and the parameter, nothing written."""
    import ulog_cases as C
    from twin_nodes.logs.ulog_write import write_px4_ulog

    log = write_px4_ulog(tmp_path / "f.ulg", C.small_topics(20.0, 50.0), {"MPC_THR_HOVER": 0.5, **_ca(**changes)},
                         {"ver_sw": "test"}, start_us=C.T0_US)
    out = tmp_path / "p.yaml"
    assert main(["params", "from-ulog", str(log), "--out", str(out), "--mass-kg", "1.0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert [ln for ln in err if not ln.startswith("rotortwin: warning:")] == [f"rotortwin: error: {log}: {line}"]
    assert not out.exists()


def test_cli_sys_autostart_nan_is_one_line(tmp_path, capsys, monkeypatch):
    """``SYS_AUTOSTART = nan`` in a log: ``compare``/``discover`` without --params pick the vehicle by it
    (``int(nan)``: a ValueError traceback before issue 28)."""
    import ulog_cases as C
    from twin_nodes.logs.ulog_write import write_px4_ulog

    log = write_px4_ulog(tmp_path / "f.ulg", C.small_topics(20.0, 50.0),
                         {"MPC_THR_HOVER": 0.5, **_ca(SYS_AUTOSTART=float("nan"))}, {"ver_sw": "test"},
                         start_us=C.T0_US)
    out = tmp_path / "out"
    out.mkdir()
    monkeypatch.chdir(out)
    for argv in (["compare", "--offline", str(log), "--quiet", "--json", "m.json"],
                 ["discover", str(log), "--no-closed-loop", "--json", "r.json"]):
        assert main(argv) == 2, argv
        err = [ln for ln in capsys.readouterr().err.strip().splitlines() if not ln.startswith("rotortwin: warning:")]
        assert err == [f"rotortwin: error: {log}: SYS_AUTOSTART: expected an integer 0..99999999, got nan"], argv
    assert list(out.iterdir()) == []
