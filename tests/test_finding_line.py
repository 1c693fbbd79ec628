"""``rotortwin finding DISCOVER_JSON`` (and the last line of ``rotortwin discover``, of ``make demo``): the
finding in one line, read from a discover result; bad input is one line, exit 2."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from twin_nodes.cli.discover import finding_line

REPO = Path(__file__).resolve().parents[1]


def _result(effects, before=0.0252, after=0.0117):
    return {"effects": effects, "baseline": {"closed_loop_heldout": {"throttle_rmse": before}},
            "after": {"closed_loop_heldout": {"throttle_rmse": after}}}


def test_a_confirmed_effect_with_its_parameters_verdict_and_throttle_before_after():
    res = _result([{"name": "motor_efficiency", "verdict": "confirmed", "params": {"motor": 3.0, "efficiency": 0.84956}},
                   {"name": "mass", "verdict": "rejected", "params": {"mass": 1.0}}])
    assert finding_line(res) == ("finding: motor_efficiency (motor 3, efficiency 0.8496), confirmed; "
                                 "held-out throttle RMSE 2.52 % -> 1.17 %")


def test_likely_effects_are_named_and_nothing_found_says_so():
    res = _result([{"name": "inertia", "verdict": "likely", "params": {"ixx": 0.0375}}])
    assert finding_line(res).startswith("finding: inertia (ixx 0.0375), likely; held-out throttle RMSE")
    none = {"effects": [{"name": "mass", "verdict": "rejected", "params": {}}]}  # --no-closed-loop: no RMSE
    assert finding_line(none) == "finding: no missing physics found"


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "twin_nodes", "finding", *args], capture_output=True, text=True,
                          cwd=REPO, timeout=120)


def test_cli_prints_the_line_and_refuses_what_is_not_a_discover_result(tmp_path):
    good = tmp_path / "d.json"
    good.write_text(json.dumps(_result([{"name": "wind", "verdict": "confirmed", "params": {"vx": 3.0}}])))
    r = _cli(str(good))
    assert r.returncode == 0 and r.stdout == "finding: wind (vx 3), confirmed; held-out throttle RMSE 2.52 % -> 1.17 %\n"
    bad = tmp_path / "bad.json"
    bad.write_text('{"effects": 3}')
    for path, msg in ((tmp_path / "none.json", "<file>: file not found"),
                      (bad, "effects: expected the JSON of 'rotortwin discover --json'"),
                      (REPO / "README.md", "<file>: expected the JSON of 'rotortwin discover --json'")):
        r = _cli(str(path))
        assert r.returncode == 2 and r.stderr.count("\n") == 1 and msg in r.stderr, r.stderr
