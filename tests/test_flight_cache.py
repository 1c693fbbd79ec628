"""The generated-flight cache (twin_nodes.prove.flight_cache): flown once per key, again when the key changes,
an unflyable flight remembered under its key."""

from __future__ import annotations

import json

import pytest

from twin_nodes.prove.flight_cache import keyed_flight


def test_flown_once_per_key_and_again_when_it_changes(tmp_path):
    flown = []

    def fly_to(path):
        flown.append(path.name)
        path.write_bytes(b"ULog")
        return {"duration_s": 1.0 + len(flown)}

    p, facts = keyed_flight(tmp_path, "f1", "k1", fly_to, {"id": "f1"})
    assert p == tmp_path / "f1.ulg" and p.read_bytes() == b"ULog" and facts == {"duration_s": 2.0}
    assert flown == ["f1.tmp.ulg"] and not (tmp_path / "f1.tmp.ulg").exists()
    meta = json.loads((tmp_path / "f1.meta.json").read_text())
    assert meta == {"key": "k1", "id": "f1", "facts": {"duration_s": 2.0}}
    assert keyed_flight(tmp_path, "f1", "k1", fly_to) == (p, {"duration_s": 2.0}) and len(flown) == 1
    assert keyed_flight(tmp_path, "f1", "k2", fly_to)[1] == {"duration_s": 3.0} and len(flown) == 2


def test_an_unflyable_flight_is_remembered_only_when_asked(tmp_path):
    calls = []

    def fails(path):
        calls.append(1)
        raise RuntimeError("diverged at t=3.00 s")

    for _ in range(2):
        with pytest.raises(RuntimeError, match="diverged"):
            keyed_flight(tmp_path, "g", "k", fails, remember_errors=True)
    assert len(calls) == 1 and not (tmp_path / "g.ulg").exists()
    with pytest.raises(RuntimeError):
        keyed_flight(tmp_path, "h", "k", fails)
    assert len(calls) == 2 and not (tmp_path / "h.meta.json").exists()
