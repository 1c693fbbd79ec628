"""The per-user code cache of the generated numba modules (twin_nodes.physics.codecache, model._import_source).

* a module compiled once is loaded by the next import (a hit), in this process or another;
* another source, another numpy/numba/CPU (the env key) gives another module name: never a stale entry;
  a file whose bytes are not the source is rewritten, and its old compiled code is not loaded (a miss);
* a corrupt index or data file is a miss: the function is compiled again, saved anew, then loaded;
* a read-only code cache holding the entry is loaded from, with no write; one without it falls back to the
  data cache folder; where nothing can be written (a full disk) the code is compiled in this process, with
  no error; two processes writing the same entry at once both run and leave a loadable entry;
* the stepper and discovery's kernels give the same bytes compiled, loaded from the cache, and compiled
  with no disk cache at all;
* after ``rotortwin fleet warm`` (what ``make setup`` runs) a fleet flight compiles none of our code (slow).
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from twin_nodes.base import io
from twin_nodes.physics import codecache, model

ROOT = Path(__file__).resolve().parents[1]

_SRC = """from numba import njit


@njit(cache=True)
def f(x):
    return x * {k} + 1.0
"""


@pytest.fixture
def caches(tmp_path, monkeypatch):
    """Fresh $ROTORTWIN_CODE_CACHE (code) and $ROTORTWIN_CACHE (data) folders."""
    code, data = tmp_path / "code", tmp_path / "data"
    monkeypatch.setenv("ROTORTWIN_CODE_CACHE", str(code))
    monkeypatch.setenv("ROTORTWIN_CACHE", str(data))
    monkeypatch.setattr(io, "_CACHE_DIRS", {})
    monkeypatch.setattr(codecache, "_CODE_DIRS", {})
    return code, data


def _load(name: str, src: str, monkeypatch):
    """A fresh import of ``src`` as ``name`` (new dispatchers: they ask the disk cache) and f(2.0) with its
    cache counts."""
    monkeypatch.delitem(sys.modules, name, raising=False)
    mod = model._import_source(name, src)
    y = mod.f(2.0)
    st = mod.f.stats
    return mod, y, sum(st.cache_hits.values()), sum(st.cache_misses.values())


def _name(src: str) -> str:
    return "rotortwin_gen_t" + hashlib.sha256(src.encode()).hexdigest()[:12]


def test_hit_after_the_first_compile(caches, monkeypatch):
    code, data = caches
    src = _SRC.format(k=3.0)
    mod, y, hits, misses = _load(_name(src), src, monkeypatch)
    assert (y, hits, misses) == (7.0, 0, 1)
    assert Path(mod.__file__).parent == code and Path(mod.__file__).read_text() == src
    assert list(code.glob("__pycache__/*.f-*.nbi")) and list(code.glob("__pycache__/*.f-*.nbc"))
    assert not data.exists() or not list(data.glob("rotortwin_*"))  # the data cache holds no code
    _, y, hits, misses = _load(_name(src), src, monkeypatch)
    assert (y, hits, misses) == (7.0, 1, 0)


def test_other_source_or_environment_is_another_module():
    src = model._generate_source(model._registry())
    name = model._module_name(src)
    assert model._module_name(src + "\n# edited\n") != name
    key = codecache.env_key()
    try:
        codecache._ENV_KEY[0] = hashlib.sha256(b"another numpy").hexdigest()  # another numpy/numba/CPU
        assert model._module_name(src) != name
    finally:
        codecache._ENV_KEY[0] = key
    assert model._module_name(src) == name


def test_changed_source_under_the_same_name_is_a_miss(caches, monkeypatch):
    name = "rotortwin_gen_t_changed"
    _, y, _, misses = _load(name, _SRC.format(k=3.0), monkeypatch)
    assert (y, misses) == (7.0, 1)
    # same co_code, another constant: numba's bytecode key alone would not see it; the file's bytes do
    _, y, hits, misses = _load(name, _SRC.format(k=5.0), monkeypatch)
    assert (y, hits, misses) == (11.0, 0, 1)


@pytest.mark.parametrize("what", ["index_truncated", "index_garbage", "data_garbage", "data_truncated"])
def test_corrupt_entry_is_compiled_again(what, caches, monkeypatch):
    code, _ = caches
    src = _SRC.format(k=3.0)
    name = _name(src)
    _load(name, src, monkeypatch)
    kind = "nbi" if what.startswith("index") else "nbc"
    (f,) = code.glob(f"__pycache__/{name}.f-*.{kind}")
    raw = f.read_bytes()
    f.write_bytes(raw[: len(raw) // 2] if what.endswith("truncated") else b"\x80\x05not a pickle" * 7)
    _, y, hits, misses = _load(name, src, monkeypatch)
    assert (y, hits, misses) == (7.0, 0, 1)  # compiled again, no error
    _, y, hits, misses = _load(name, src, monkeypatch)
    assert (y, hits, misses) == (7.0, 1, 0)  # and saved anew


def _no_writes(monkeypatch, err=errno.EROFS):
    """Every write of the code cache fails as on a read-only mount (root ignores chmod) or a full disk."""
    from numba.core import caching

    def refuse(*a, **k):
        raise OSError(err, os.strerror(err))

    monkeypatch.setattr(caching.IndexDataCacheFile, "_open_for_write", refuse)
    monkeypatch.setattr(model, "_write_module", refuse)
    monkeypatch.setattr(codecache, "_writable", lambda folder: False)


def test_read_only_code_cache_is_loaded_from(caches, monkeypatch):
    code, data = caches
    src = _SRC.format(k=3.0)
    name = _name(src)
    _load(name, src, monkeypatch)
    before = sorted(p.name for p in code.rglob("*"))
    monkeypatch.setattr(codecache, "_CODE_DIRS", {})
    _no_writes(monkeypatch)
    assert codecache.code_dir() == (code, False)
    mod, y, hits, misses = _load(name, src, monkeypatch)
    assert (y, hits, misses) == (7.0, 1, 0) and Path(mod.__file__).parent == code
    assert sorted(p.name for p in code.rglob("*")) == before


def test_read_only_code_cache_without_the_entry_falls_back_to_the_data_cache(caches, monkeypatch):
    code, data = caches
    code.mkdir(mode=0o700)
    monkeypatch.setattr(codecache, "_writable", lambda folder: False)
    src = _SRC.format(k=3.0)
    mod, y, hits, misses = _load(_name(src), src, monkeypatch)
    assert (y, misses) == (7.0, 1) and Path(mod.__file__).parent == data
    assert not list(code.iterdir())
    _, y, hits, misses = _load(_name(src), src, monkeypatch)
    assert (y, hits, misses) == (7.0, 1, 0)


@pytest.mark.skipif(os.getuid() == 0, reason="root writes a read-only folder anyway (the simulated case runs)")
def test_read_only_code_cache_by_its_mode(caches, monkeypatch):
    code, data = caches
    src = _SRC.format(k=3.0)
    name = _name(src)
    _load(name, src, monkeypatch)
    for d in (code / "__pycache__", code):
        d.chmod(0o500)
    try:
        monkeypatch.setattr(codecache, "_CODE_DIRS", {})
        _, y, hits, misses = _load(name, src, monkeypatch)
        assert (y, hits, misses) == (7.0, 1, 0)
        src2 = _SRC.format(k=4.0)
        mod, y, _, _ = _load(_name(src2), src2, monkeypatch)
        assert y == 9.0 and Path(mod.__file__).parent == data
    finally:
        for d in (code, code / "__pycache__"):
            d.chmod(0o700)


def test_nothing_writable_compiles_in_process_without_error(caches, monkeypatch):
    _no_writes(monkeypatch, errno.ENOSPC)  # a full disk: the module file and numba's files cannot be written
    src = _SRC.format(k=3.0)
    from numba.core.caching import NullCache

    code, data = caches
    mod, y, hits, misses = _load(_name(src), src, monkeypatch)
    assert (y, hits, misses) == (7.0, 0, 1) and isinstance(mod.f._cache, NullCache)  # compiled, no disk cache
    assert mod.f(np.float64(4.0)) == 13.0
    assert not [p for p in (*code.rglob("*"), *data.rglob("*")) if p.suffix in (".py", ".nbi", ".nbc")]


def test_full_disk_while_saving_is_no_error(caches, monkeypatch):
    from numba.core import caching

    code, _ = caches

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(caching.IndexDataCacheFile, "_open_for_write", full)
    src = _SRC.format(k=3.0)
    _, y, hits, misses = _load(_name(src), src, monkeypatch)  # the module file written, numba's save fails
    assert (y, hits, misses) == (7.0, 0, 1)
    assert not list(code.glob("__pycache__/*.nb*"))


_WRITER = """
import sys, time
from twin_nodes.physics import model
t = float(sys.argv[3])
while time.time() < t:
    pass
mod = model._import_source(sys.argv[1], sys.argv[2])
print(mod.f(2.0), sum(mod.f.stats.cache_hits.values()))
"""


def test_concurrent_writers_of_one_entry(caches):
    import time

    code, data = caches
    src = _SRC.format(k=3.0)
    name = _name(src)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    start = str(time.time() + 4.0)  # both start writing at once (after their imports)
    procs = [subprocess.Popen([sys.executable, "-c", _WRITER, name, src, start], env=env, cwd=ROOT,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(3)]
    outs = [p.communicate(timeout=300) for p in procs]
    assert all(p.returncode == 0 for p in procs), [o[1] for o in outs]
    assert all(o[0].split()[0] == "7.0" for o in outs)
    assert not list(code.rglob("*.tmp*"))  # no temporary left
    r = subprocess.run([sys.executable, "-c", _WRITER, name, src, "0"], env=env, cwd=ROOT, capture_output=True,
                       text=True, timeout=300)
    assert r.stdout.split() == ["7.0", "1"], r.stderr  # loaded


#: a subprocess header recording the module of every function numba compiles (``compiled``)
_COMPILED = """
from numba.core import event
compiled = []
class L(event.Listener):
    def on_start(self, e):
        pass
    def on_end(self, e):
        compiled.append(e.data["dispatcher"].py_func.__module__)
event.register("numba:compile", L())
"""

_SAME = """
import hashlib, json, sys
import numpy as np
""" + _COMPILED + """if sys.argv[1] == "none":  # no disk cache at all: every write refused
    from numba.core import caching
    from twin_nodes.physics import codecache, model
    def refuse(*a, **k):
        raise OSError(28, "No space left on device")
    caching.IndexDataCacheFile._open_for_write = refuse
    model._write_module = refuse
    codecache._writable = lambda folder: False
from twin_nodes.discovery.kernels import kernels
from twin_nodes.physics.effects import default_ext
from twin_nodes.vehicle.params import shipped
from twin_nodes.physics.model import Multirotor
m = Multirotor(shipped("buho_negro").with_effect("battery_sag").with_effect("linear_drag", k_n_s_m=0.2))
x0 = m.initial_state(position_enu=(0, 0, 5), velocity_enu=(1.0, -0.5, 0.2), rotor_state="hover")
U = np.linspace(0.3, 0.7, 400).reshape(100, 4)
ext = np.tile(default_ext(), (100, 1))
X = m.simulate(x0, U, 0.002, ext, 2)
F = m.wrench_terms(X[:-1], ext)
S = kernels(m).lag_states(m.P, U, ext, 0.002, 1, np.zeros(4), 2, 50)
h = hashlib.sha256()
for a in (X, S, *(v for pair in F.values() for v in pair)):
    h.update(np.ascontiguousarray(a).tobytes())
print(json.dumps({"hash": h.hexdigest(), "generated_compiled": sum(c.startswith("rotortwin_") for c in compiled),
                  "file": m._mod.__file__}))
"""


def test_results_identical_with_and_without_the_cache(tmp_path):
    def run(mode, code):
        env = {**os.environ, "PYTHONPATH": str(ROOT), "ROTORTWIN_CODE_CACHE": str(tmp_path / code),
               "ROTORTWIN_CACHE": str(tmp_path / f"data_{code}")}
        r = subprocess.run([sys.executable, "-c", _SAME, mode], env=env, cwd=ROOT, capture_output=True, text=True,
                           timeout=600)
        assert r.returncode == 0, r.stderr
        return json.loads(r.stdout.strip().splitlines()[-1])

    cold = run("cache", "code")  # compiled, saved
    warm = run("cache", "code")  # loaded
    none = run("none", "empty")  # compiled, never saved or loaded (an empty folder no write reaches)
    assert cold["generated_compiled"] > 0 and warm["generated_compiled"] == 0 and none["generated_compiled"] > 0
    assert Path(cold["file"]).parent == tmp_path / "code"
    assert cold["hash"] == warm["hash"] == none["hash"]


_FLIGHT = """
import json, sys
""" + _COMPILED + """from twin_nodes.fleet.flight import analyse
row = analyse(sys.argv[1], "discover", None, None, True)
print(json.dumps({"kind": row.get("flight_kind"), "ours": sorted({c for c in compiled
                  if c.startswith(("rotortwin_", "twin_nodes."))})}))
"""


@pytest.mark.slow
def test_a_flight_after_fleet_warm_compiles_nothing(tmp_path):
    """What ``make setup`` runs (``rotortwin fleet warm``) leaves nothing of ours for a fleet flight to compile."""
    fleet = ROOT.parent / "shared" / "flightlogs" / "fleet_quadx_v6c"
    flight = fleet / "ZweiterFlugtag" / "log_19_2023-6-7-10-51-18.ulg"  # a short free flight
    if not flight.is_file():
        from conftest import missing_shared
        missing_shared("flightlogs/fleet_quadx_v6c")
    env = {**os.environ, "PYTHONPATH": str(ROOT), "ROTORTWIN_CODE_CACHE": str(tmp_path / "code"),
           "ROTORTWIN_CACHE": str(tmp_path / "data")}
    r = subprocess.run([sys.executable, "-m", "twin_nodes", "fleet", "warm"], env=env, cwd=ROOT, capture_output=True,
                       text=True, timeout=900)
    assert r.returncode == 0 and str(tmp_path / "code") in r.stdout, r.stderr
    r = subprocess.run([sys.executable, "-c", _FLIGHT, str(flight)], env=env, cwd=ROOT, capture_output=True,
                       text=True, timeout=900)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout.strip().splitlines()[-1]) == {"kind": "free flight", "ours": []}
