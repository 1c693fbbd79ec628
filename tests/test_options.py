"""Every numeric option of every subcommand is range-checked where it enters (issue 28).

The parser is walked (``twin_nodes.cli.build_parser()``, every subparser): an option whose
values are numbers must use a :class:`twin_nodes.cli.options.Number` type (never bare
``float``/``int``), accept its own default, and refuse ``nan``, ``inf``, ``1e999`` and a value
just outside its range with exit code 2 and one stderr line ``rotortwin: error: --opt: expected
...``, before anything runs.  A new option that forgets the type fails here.
"""

from __future__ import annotations

import argparse
import contextlib
import io

import pytest

from twin_nodes.cli import build_parser, main
from twin_nodes.cli.options import Number, finite_float, fraction, integer, port, positive_float


def _walk(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    """(subcommand path, parser) for the root and every subcommand parser."""
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _walk(sub, path + (name,))


def _options():
    out = []
    for path, parser in _walk(build_parser()):
        for action in parser._actions:
            if not action.option_strings or isinstance(action, argparse._SubParsersAction):
                continue
            out.append((path, action))
    return out


OPTIONS = _options()
NUMERIC = [(path, a) for path, a in OPTIONS if isinstance(a.type, Number)]


def _run(argv: list[str]) -> tuple[object, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc: object = main(argv)
        except SystemExit as exc:
            rc = exc.code
    return rc, out.getvalue(), err.getvalue()


def _is_numeric_default(v: object) -> bool:
    if isinstance(v, bool):
        return False
    if isinstance(v, (int, float)):
        return True
    try:
        float(str(v))
    except ValueError:
        return False
    return True


def test_the_walk_finds_the_options():
    """The walk reaches nested subcommands (fleet discover, identify hover, topics echo, bridge sim)."""
    names = {(" ".join(p), a.option_strings[-1]) for p, a in NUMERIC}
    for want in [("discover", "--heldout"), ("compare", "--window"), ("compare", "--rate"), ("compare", "--horizon"),
                 ("identify hover", "--mass-kg"), ("fleet simulate", "--vehicles"), ("fleet discover", "--workers"),
                 ("params from-ulog", "--arm-m"), ("bridge sim", "--port"), ("topics echo", "--count"),
                 ("regress", "--tolerance"), ("live", "--foxglove"), ("mission wait", "--timeout")]:
        assert want in names, want
    assert len(NUMERIC) >= 60


@pytest.mark.parametrize("path,action", OPTIONS, ids=[f"{' '.join(p)} {a.option_strings[-1]}" for p, a in OPTIONS])
def test_no_bare_float_or_int(path, action):
    """No option takes bare float/int (unchecked: nan, inf, negatives pass), and an option whose
    default is a number has a checked numeric type."""
    assert action.type not in (float, int), f"{' '.join(path)} {action.option_strings[-1]}: use twin_nodes.cli.options"
    if action.type is None and action.nargs != 0 and _is_numeric_default(action.default):
        pytest.fail(f"{' '.join(path)} {action.option_strings[-1]}: numeric default {action.default!r} "
                    f"but no checked type")


@pytest.mark.parametrize("path,action", NUMERIC, ids=[f"{' '.join(p)} {a.option_strings[-1]}" for p, a in NUMERIC])
def test_numeric_option_refuses_nan_inf_and_out_of_range(path, action):
    opt = action.option_strings[-1]
    t: Number = action.type
    if action.default not in (None, argparse.SUPPRESS):
        t(action.default)  # the default itself is in range
    if t.lo is not None or t.hi is not None:
        assert any(v in t.bad_values() for v in ("nan", "inf")) and len(t.bad_values()) >= 5
    for bad in t.bad_values():
        rc, out, err = _run([*path, f"{opt}={bad}"])
        lines = err.strip().splitlines()
        assert rc == 2, (bad, rc, err)
        assert lines == [f"rotortwin: error: {opt}: expected {t.describe()}, got {bad}"], (bad, err)
        assert out == ""


def test_values_inside_the_range_are_accepted():
    t = finite_float(0.05, 0.95)
    assert t("0.05") == 0.05 and t("0.95") == 0.95 and t(" 0.5 ") == 0.5
    f = fraction()
    assert f("0.5") == 0.5
    for bad in ("0", "1", "nan", "-0.1", "x"):
        with pytest.raises(argparse.ArgumentTypeError):
            f(bad)
    assert port()("0") == 0 and port()("65535") == 65535
    with pytest.raises(argparse.ArgumentTypeError):
        port()("65536")
    assert integer(0, 10)("10") == 10
    with pytest.raises(argparse.ArgumentTypeError, match=r"expected an integer in \[0, 10\], got 2.0$"):
        integer(0, 10)("2.0")
    with pytest.raises(argparse.ArgumentTypeError, match=r"got 1e999"):
        positive_float()("1e999")
    assert positive_float().describe() == "a number > 0"


@pytest.mark.parametrize("argv,line", [
    (["discover", "x.ulg", "--heldout", "nan"], "rotortwin: error: --heldout: expected a number in [0.05, 0.95], got nan"),
    (["discover", "x.ulg", "--heldout", "1"], "rotortwin: error: --heldout: expected a number in [0.05, 0.95], got 1"),
    (["compare", "x.ulg", "--window", "0"], "rotortwin: error: --window: expected a number in (0, 3600] s, got 0"),
    (["compare", "x.ulg", "--rate", "-1"], "rotortwin: error: --rate: expected a number in [0, 10000], got -1"),
    (["identify", "hover", "x.ulg", "--mass-kg", "-1"],
     "rotortwin: error: --mass-kg: expected a number in [0.001, 10000] kg, got -1"),
    (["fleet", "simulate", "out", "--vehicles", "-1"],
     "rotortwin: error: --vehicles: expected an integer in [1, 1000], got -1"),
    (["fleet", "discover", "x.ulg", "--catalog", "c", "--workers", "0"],
     "rotortwin: error: --workers: expected an integer in [1, 256], got 0"),
])
def test_audit_cases_are_one_line(tmp_path, monkeypatch, argv, line):
    """The audit's cases (issue 28): each was accepted (exit 0, a traceback, or a hang)."""
    monkeypatch.chdir(tmp_path)
    rc, out, err = _run(argv)
    assert (rc, err.strip().splitlines(), out) == (2, [line], "")
    assert list(tmp_path.iterdir()) == []


def test_other_argparse_errors_are_one_line():
    rc, _, err = _run(["params", "from-ulog", "x.ulg"])
    assert rc == 2
    assert err.strip().splitlines() == ["rotortwin: error: params from-ulog: the following arguments are "
                                        "required: --out"]
