"""Issue 28: ``launch_scripts/px4_sitl_twin.sh --speed-factor 0`` must not hand PX4
``PX4_SIM_SPEED_FACTOR=0``: PX4's rcS multiplies its link-loss timeouts by it and saves them
(``COM_DL_LOSS_T = 10 x``, ...), so 0 made PX4 report "connection to ground station lost" 96 times
in 27 s.  A fake PX4 binary and a fake ``rotortwin`` record what the script gives them."""

from __future__ import annotations

import os
import stat
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "launch_scripts" / "px4_sitl_twin.sh"


def _exe(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    path.chmod(path.stat().st_mode | stat.S_IXUSR)


def _run(tmp_path: Path, *args: str) -> tuple[dict[str, str], str, subprocess.CompletedProcess]:
    px4 = tmp_path / "PX4-Autopilot"
    out = tmp_path / "out"
    _exe(px4 / "build" / "px4_sitl_default" / "bin" / "px4", f'#!/bin/sh\nenv | grep "^PX4_" > "{out}/px4_env"\n')
    # the bridge (the script's first process, which it waits for): records its arguments, ends soon
    _exe(tmp_path / "rotortwin", f'#!/bin/sh\necho "$@" >> "{out}/rotortwin_args"\nsleep 1\n')
    env = {k: v for k, v in os.environ.items() if not k.startswith("PX4_")}
    env["ROTORTWIN"] = str(tmp_path / "rotortwin")
    r = subprocess.run(["bash", str(SCRIPT), "--px4", str(px4), "--out", str(out), *args], env=env,
                       capture_output=True, text=True, timeout=60)
    px4_env = {}
    if (out / "px4_env").exists():
        px4_env = dict(line.split("=", 1) for line in (out / "px4_env").read_text().splitlines() if "=" in line)
    bridge = (out / "rotortwin_args").read_text() if (out / "rotortwin_args").exists() else ""
    return px4_env, bridge, r


def test_unpaced_bridge_gives_px4_a_speed_factor_it_understands(tmp_path):
    px4_env, bridge, r = _run(tmp_path, "--speed-factor", "0")
    assert r.returncode == 0, r.stderr
    assert "--speed-factor 0" in bridge, bridge            # the simulator runs unpaced ...
    assert float(px4_env["PX4_SIM_SPEED_FACTOR"]) == 20.0, px4_env  # ... PX4's timeouts scaled x20, never 0
    assert px4_env["PX4_SYS_AUTOSTART"] == "10016"


@pytest.mark.parametrize("args, bridge_speed, px4_speed", [
    (("--speed-factor", "2"), "2", 2.0),
    (("--speed-factor", "0", "--px4-speed-factor", "8"), "0", 8.0),
    ((), "1", 1.0),
])
def test_speed_factors(tmp_path, args, bridge_speed, px4_speed):
    px4_env, bridge, r = _run(tmp_path, *args)
    assert r.returncode == 0, r.stderr
    assert f"--speed-factor {bridge_speed}" in bridge
    assert float(px4_env["PX4_SIM_SPEED_FACTOR"]) == px4_speed


@pytest.mark.parametrize("args", [("--speed-factor", "fast"), ("--speed-factor", "0", "--px4-speed-factor", "0"),
                                  ("--speed-factor", "-1")])
def test_bad_speed_factors_are_refused(tmp_path, args):
    px4_env, bridge, r = _run(tmp_path, *args)
    assert r.returncode == 2 and "speed-factor" in r.stderr and not px4_env and not bridge, r.stderr
