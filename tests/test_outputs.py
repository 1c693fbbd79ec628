"""The one output guard of every command (twin_nodes/base/outputs.py, cli/paths.py).

Walks the argument parser, so a new subcommand or option cannot miss it: every string argument is a
declared input, a declared output, or one of the few non-paths listed here; every declared output
is tried against every declared input (the same path, a symbolic link, a hard link, a path inside an
input folder) and must be refused before the command runs, the input's bytes unchanged.  Then the
audit's data-loss cases end to end through ``rotortwin``, staging (nothing partial on an error,
Ctrl-C or SIGTERM), ``--force``, and unwritable places.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from twin_nodes.base.errors import TwinError
from twin_nodes.base.outputs import STAGE_PREFIX, Output, Staging, check
from twin_nodes.cli import build_parser, main
from twin_nodes.cli.paths import PathArgs, run_guarded

ROOT = Path(__file__).resolve().parents[1]
FLIGHT = ROOT / "bags" / "sim_quadx_weak_motor3.ulg"
PARAMS = ROOT / "params" / "px4_sih_quadx.yaml"
RT = [sys.executable, "-m", "twin_nodes"]

#: string arguments that are not paths (URLs, hosts, names, SQL, topic names, ROS arguments)
NON_PATHS = {"host", "url", "motor_channels", "effect", "scheduler", "sql", "topic", "wait_for", "ros_args",
             "pairs", "home", "name"}
_NOT_VALUES = (argparse._HelpAction, argparse._VersionAction, argparse._SubParsersAction,
               argparse._StoreTrueAction, argparse._StoreFalseAction, argparse._StoreConstAction)


def _leaves(p: argparse.ArgumentParser, prefix: tuple[str, ...] = ()):
    yield prefix, p
    for a in p._actions:
        if isinstance(a, argparse._SubParsersAction):
            for name, sp in a.choices.items():
                yield from _leaves(sp, prefix + (name,))


def _paths(p: argparse.ArgumentParser) -> PathArgs | None:
    pa = p.get_default("_paths")
    return pa if isinstance(pa, PathArgs) and pa.parser is p else None


COMMANDS = [(pre, p) for pre, p in _leaves(build_parser()) if pre]
WITH_OUTPUTS = [(pre, p) for pre, p in COMMANDS if _paths(p) and _paths(p).outputs]


def test_every_string_argument_is_a_declared_path_or_a_known_non_path():
    unknown = []
    for pre, p in COMMANDS:
        pa = _paths(p)
        declared = set(pa.inputs) | {o.dest for o in pa.outputs} if pa else set()
        for a in p._actions:
            if isinstance(a, _NOT_VALUES) or a.type is not None or a.choices is not None:
                continue
            if a.dest not in declared and a.dest not in NON_PATHS:
                unknown.append(f"rotortwin {' '.join(pre)}: {a.option_strings or a.dest}")
    assert not unknown, f"declare these with twin_nodes.cli.paths.declare (input or output): {unknown}"


def test_the_commands_with_outputs_are_the_ones_we_know():
    names = {" ".join(pre) for pre, _ in WITH_OUTPUTS}
    # every command that writes a file the user names; a new one joins the list (and the tests below)
    assert {"discover", "prove", "simulate", "compare", "regress", "survey", "metrics", "record",
            "params derive", "params export", "params from-ulog", "identify motor", "identify hover",
            "identify delay", "identify regress", "identify noise", "live", "live tlog", "live foxglove",
            "live layout", "fleet discover", "fleet compare", "fleet report", "fleet simulate"} <= names
    for pre, p in WITH_OUTPUTS:
        assert any("--force" in a.option_strings for a in p._actions), pre


def _argv(pre: tuple[str, ...], p: argparse.ArgumentParser, tmp: Path, override: dict[str, str]) -> list[str]:
    """A parseable command line: each input a file of its own (folders for catalogs), each output a
    fresh path, except those in ``override`` (dest -> value)."""
    pa = _paths(p)
    outs = {o.dest: o for o in pa.outputs}
    argv = list(pre)
    if pre == ("record",):
        argv.append(override.get("out", str(tmp / "fresh_bag")))
    for a in p._actions:
        if isinstance(a, _NOT_VALUES) or (pre == ("record",) and a.dest == "out"):
            continue
        needed = not a.option_strings and a.nargs != "?" or a.required or a.dest in override
        if not needed:
            continue
        if a.dest in override:
            val = override[a.dest]
        elif a.dest in outs:
            val = str(tmp / f"new_{a.dest}")
        elif a.dest in pa.inputs:
            val = str(tmp / f"in_{a.dest}")
        elif a.choices:
            val = next(iter(a.choices))
        else:
            val = "1"
        argv += ([a.option_strings[-1]] if a.option_strings else []) + [val]
    return argv


def _make_inputs(pa: PathArgs, tmp: Path) -> dict[str, Path]:
    made = {}
    for dest in pa.inputs:
        f = tmp / f"in_{dest}"
        if dest == "catalog":
            f.mkdir(exist_ok=True)
            (f / "row.parquet").write_bytes(b"catalog row " + dest.encode())
        else:
            f.write_bytes(b"input bytes of " + dest.encode())
        made[dest] = f
    return made


def _snapshot(paths: dict[str, Path]) -> dict[str, bytes]:
    out = {}
    for k, p in paths.items():
        out[k] = p.read_bytes() if p.is_file() else b"".join(q.read_bytes() for q in sorted(p.rglob("*")))
    return out


def _guard(argv: list[str]) -> tuple[bool, str]:
    """Parse ``argv`` and run the guard with a command that only records that it ran."""
    args = build_parser().parse_args(argv)
    ran = []
    try:
        run_guarded(lambda a: ran.append(a) or 0, args)
    except TwinError as exc:
        assert not ran
        return False, str(exc)
    return True, ""


@pytest.mark.parametrize("pre,p", WITH_OUTPUTS, ids=[" ".join(pre) for pre, _ in WITH_OUTPUTS])
def test_every_output_refuses_every_input(pre, p, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    pa = _paths(p)
    inputs = _make_inputs(pa, tmp_path)
    before = _snapshot(inputs)
    tried = 0
    for out in pa.outputs:
        if pre == ("record",) and out.dest == "recover_out":
            base = {"out": "recover", "bag": str(inputs["bag"])}
        elif pre == ("record",):
            base = {}
        else:
            base = {}
        for dest, path in inputs.items():
            if pre == ("record",) and out.dest == "out" and dest == "bag":
                continue  # 'record OUT' has no input; 'bag' belongs to 'record recover'
            link = tmp_path / f"link_{out.dest}_{dest}"
            link.symlink_to(path)
            cases = [str(path), str(link)]
            if path.is_file():
                hard = tmp_path / f"hard_{out.dest}_{dest}"
                os.link(path, hard)
                cases.append(str(hard))
            else:
                cases.append(str(path / "inside"))
            for value in cases:
                argv = _argv(pre, p, tmp_path, {**base, dest: str(path), out.dest: value})
                if pre == ("record",) and out.dest == "out":
                    argv[1] = value
                ok, msg = _guard(argv)
                assert not ok, f"rotortwin {' '.join(argv)}: the guard let {out.option} = {dest} through"
                assert "\n" not in msg and (out.option in msg or "input" in msg), msg
                tried += 1
    assert tried >= (3 if pa.inputs else 0)
    assert _snapshot(inputs) == before
    assert not list(tmp_path.glob(f"{STAGE_PREFIX}*"))


@pytest.mark.parametrize("pre,p", WITH_OUTPUTS, ids=[" ".join(pre) for pre, _ in WITH_OUTPUTS])
def test_every_output_refuses_an_existing_file_unless_force(pre, p, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    pa = _paths(p)
    _make_inputs(pa, tmp_path)
    for out in pa.outputs:
        if out.kind == "update" or (pre == ("record",)):
            continue
        existing = tmp_path / f"existing_{out.dest}"
        if out.kind == "file":
            existing.write_bytes(b"precious")
        else:
            existing.mkdir()
            (existing / "precious.txt").write_bytes(b"precious")
        ok, msg = _guard(_argv(pre, p, tmp_path, {out.dest: str(existing)}))
        assert not ok and "--force" in msg, msg
        ok, _ = _guard(_argv(pre, p, tmp_path, {out.dest: str(existing)}) + ["--force"])
        assert ok
        kept = existing.read_bytes() if out.kind == "file" else (existing / "precious.txt").read_bytes()
        assert kept == b"precious"  # the recording command wrote nothing, so nothing was replaced


def test_a_path_through_a_file_is_refused_before_the_run(tmp_path):
    f = tmp_path / "a_file"
    f.write_text("x")
    rc = main(["discover", str(FLIGHT), "--json", str(f / "out.json")])
    assert rc == 2
    assert f.read_text() == "x"


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs /proc (a folder no one may create files in)")
def test_an_unwritable_folder_is_refused_before_the_run(capsys):
    rc = main(["simulate", "--out", "/proc/self/new_flight.ulg"])
    assert rc == 2
    assert "writable" in capsys.readouterr().err


# -- the audit's data-loss cases, end to end -------------------------------------------------------------


@pytest.fixture()
def inputs(tmp_path):
    flight = tmp_path / "F.ulg"
    shutil.copy(FLIGHT, flight)
    params = tmp_path / "P.yaml"
    shutil.copy(PARAMS, params)
    plan = tmp_path / "m.plan.yaml"
    shutil.copy(ROOT / "missions" / "triangle.plan.yaml", plan)
    tlog = tmp_path / "F.tlog"
    tlog.write_bytes(os.urandom(64))
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "bag.mcap").write_bytes(b"\x89MCAP0\r\n baseline")
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    link = tmp_path / "P_link.yaml"
    link.symlink_to(params)
    return dict(flight=flight, params=params, plan=plan, tlog=tlog, bag=bag, link=link, dir=tmp_path)


AUDIT_CASES = [
    ("discover {flight} --json {flight}", "flight"),
    ("discover {flight} --params {params} --json {params}", "params"),
    ("discover {flight} --params {params} --out-params {params}", "params"),
    ("discover {flight} --params {params} --out-params {link}", "params"),
    ("survey {flight} --md {flight}", "flight"),
    ("survey {flight} --params {params} --json {params}", "params"),
    ("identify hover {flight} --params {params} --out {params}", "params"),
    ("identify delay {flight} --out {flight}", "flight"),
    ("identify regress {flight} --params {params} --out {link}", "params"),
    ("simulate --params {params} --out {params}", "params"),
    ("simulate --params {params} --plan {plan} --out {plan}", "plan"),
    ("live tlog {tlog} --json {tlog}", "tlog"),
    ("regress {bag} --offline --json {bag}/bag.mcap", "bag"),
    ("regress {bag}/bag.mcap --offline --json {bag}/other.json", "bag"),
    ("compare {flight} --offline --report {dir}", "flight"),
    ("params from-ulog {flight} --out {flight}", "flight"),
]


@pytest.mark.parametrize("cmd,victim", AUDIT_CASES, ids=[c for c, _ in AUDIT_CASES])
def test_the_audits_data_loss_cases_are_refused(cmd, victim, inputs, capsys):
    before = {k: (v.read_bytes() if v.is_file() else sorted(os.listdir(v))) for k, v in inputs.items()}
    rc = main(cmd.format(**{k: str(v) for k, v in inputs.items()}).split())
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2, err
    assert len(err) == 1 and err[0].startswith("rotortwin: error: "), err
    after = {k: (v.read_bytes() if v.is_file() else sorted(os.listdir(v))) for k, v in inputs.items()}
    assert after == before


# -- staging: nothing partial ---------------------------------------------------------------------------


def test_staged_outputs_appear_only_on_commit(tmp_path):
    ns = argparse.Namespace(json=str(tmp_path / "sub" / "r.json"), report=str(tmp_path / "rep"))
    st = Staging(check([Output("json", "--json"), Output("report", "--report", kind="dir")], ns, [])).begin()
    w_json, w_rep = st.plan[0].write, st.plan[1].write
    w_json.write_text("{}")
    w_rep.mkdir()
    (w_rep / "index.html").write_text("<html>")
    assert not (tmp_path / "sub").exists() and not (tmp_path / "rep").exists()
    done = st.commit()
    assert (tmp_path / "sub" / "r.json").read_text() == "{}"
    assert (tmp_path / "rep" / "index.html").exists()
    assert len(done) == 2
    assert not list(tmp_path.rglob(f"{STAGE_PREFIX}*"))


@pytest.mark.parametrize("exc", [TwinError("x: y: z"), KeyboardInterrupt(), RuntimeError("bug")])
def test_a_failed_command_leaves_nothing(exc, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    args = build_parser().parse_args(["discover", str(FLIGHT), "--json", "d.json", "--report", "rep",
                                      "--out-params", "p.yaml"])

    def half_done(a):
        Path(a.json_out).write_text("{}")  # the JSON was written, then the report failed
        Path(a.report).mkdir()
        raise exc

    with pytest.raises(type(exc)):
        run_guarded(half_done, args)
    assert sorted(os.listdir(tmp_path)) == []


def test_force_writes_into_a_folder_and_keeps_what_else_is_there(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "rep").mkdir()
    (tmp_path / "rep" / "mine.txt").write_text("keep")
    (tmp_path / "rep" / "index.html").write_text("old")
    args = build_parser().parse_args(["discover", str(FLIGHT), "--report", "rep", "--force"])

    def write(a):
        Path(a.report).mkdir()
        (Path(a.report) / "index.html").write_text("new")
        return 0

    assert run_guarded(write, args) == 0
    assert (tmp_path / "rep" / "mine.txt").read_text() == "keep"
    assert (tmp_path / "rep" / "index.html").read_text() == "new"


def test_a_stage_left_by_a_killed_run_is_removed_by_the_next(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = tmp_path / f"{STAGE_PREFIX}{dead.pid}-abc"
    stale.mkdir()
    (stale / "half.json").write_text("{")
    ns = argparse.Namespace(json=str(tmp_path / "r.json"))
    st = Staging(check([Output("json", "--json")], ns, [])).begin()
    assert not stale.exists()
    st.abort()


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_during_discover_leaves_no_output(sig, tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    # the child gets SIGINT's default action whatever this process inherited or was left with: an ignored
    # SIGINT survives exec, and a Python started with it ignored never raises KeyboardInterrupt (in the clean-
    # clone suite the discover ran to the end, rc 0, after the signal)
    proc = subprocess.Popen([*RT, "discover", str(FLIGHT), "--params", str(PARAMS), "--json", "d.json", "--report", "rep"],
                            cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not list(tmp_path.glob(f"{STAGE_PREFIX}*")):
        time.sleep(0.05)
    assert list(tmp_path.glob(f"{STAGE_PREFIX}*")), "discover staged its outputs"
    time.sleep(1.0)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode in (130, 143, -sig), err
    assert os.listdir(tmp_path) == [], os.listdir(tmp_path)


def test_a_forked_worker_stopped_by_sigterm_dies_quietly(tmp_path):
    """Pool workers forked during a command inherit its SIGTERM handler: they must end as SIGTERM
    says, without the traceback of the interrupt meant for the command itself."""
    code = f"""
import multiprocessing as mp, os, signal, sys, time
from twin_nodes.cli import build_parser
from twin_nodes.cli.paths import run_guarded

def default_sigterm():
    sys.exit(0 if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL else 3)

def cmd(args):
    ctx = mp.get_context("fork")
    q = ctx.Process(target=default_sigterm)
    q.start()
    q.join(10)
    print("child sigterm default", q.exitcode == 0)
    p = ctx.Process(target=time.sleep, args=(30,))
    p.start()
    time.sleep(0.5)
    os.kill(p.pid, signal.SIGTERM)
    p.join(10)
    print("child exit", p.exitcode)
    return 0

args = build_parser().parse_args(["simulate", "--out", {str(tmp_path / 'x.ulg')!r}])
sys.exit(run_guarded(cmd, args))
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0, r.stderr
    assert "child exit -15" in r.stdout
    assert "child sigterm default True" in r.stdout  # a pool worker blocked in C must die at once
    assert "Traceback" not in r.stderr and "_Terminated" not in r.stderr


def test_an_error_about_an_output_names_the_users_path(tmp_path, monkeypatch, capsys):
    """A command's own check of an output (identify's file suffix) runs on the staged path: the
    message must still name the path the user typed."""
    monkeypatch.chdir(tmp_path)
    csv = tmp_path / "steps.csv"
    csv.write_text("time_s,command,rpm\n0,0,0\n")
    assert main(["identify", "motor", str(csv), "--out", "d/foo.txt"]) == 2
    err = capsys.readouterr().err.strip()
    assert STAGE_PREFIX not in err and "d/foo.txt: --out: expected a file name ending in" in err, err
