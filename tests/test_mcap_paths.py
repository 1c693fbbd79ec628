"""A recording path does what it says (issue 29, item 4): ``OUT.mcap`` is that one MCAP file, any other
``OUT`` a rosbag2 folder of that name.

The single file carries the rosbag2 metadata inside it (the ``rosbag2`` metadata record that ``ros2 bag``'s
MCAP storage writes) and is read as it is by rosbags' ``AnyReader``, by the ``mcap`` library and by
Foxglove (checked here by what Foxglove needs of a ROS 2 MCAP: the ``ros2`` profile, ``ros2msg`` schemas,
``cdr`` channels, a summary with chunk indexes, valid CRCs).  The recorder, ``record recover``, the output
guard, ``regress`` and ``rotortwin compare --mcap`` (the node graph, marked ``ros``) are checked on it.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml
from mcap.reader import make_reader
from test_recording import TYPES, record

from twin_nodes.base.errors import LogError, TwinError
from twin_nodes.base.outputs import Output, check
from twin_nodes.logs.recording import McapRecorder, read_bag, recover, topic_counts

REPO = Path(__file__).resolve().parents[1]


def test_a_path_ending_in_mcap_is_one_file_with_the_rosbag2_metadata_inside(tmp_path):
    run = tmp_path / "run.mcap"
    times = record(run, n=12)
    assert sorted(os.listdir(tmp_path)) == ["run.mcap"]  # no folder, nothing beside it
    # rosbags AnyReader (what read_bag uses)
    from rosbags.highlevel import AnyReader

    from twin_nodes.logs.recording import default_typestore

    with AnyReader([run], default_typestore=default_typestore()) as r:
        assert {c.topic for c in r.connections} == set(TYPES)
        assert sum(1 for _ in r.messages()) == len(times)
    data = read_bag(run)
    assert data["/status"][11][1].data == "tick 11"
    assert topic_counts(run) == {k: 12 for k in TYPES}
    # the mcap library, CRCs validated; what Foxglove needs of a ROS 2 MCAP
    with open(run, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary is not None and summary.chunk_indexes
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        assert summary.statistics.message_count == len(times)
        assert sum(1 for _ in reader.iter_messages()) == len(times)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    info = yaml.safe_load(meta["rosbag2"]["serialized_metadata"])
    assert info["relative_file_paths"] == ["run.mcap"] and info["message_count"] == len(times)
    assert info["storage_identifier"] == "mcap" and info["version"] == 9


def test_a_path_without_suffix_is_a_rosbag2_folder_of_that_name(tmp_path):
    bag = tmp_path / "run"
    record(bag, n=3)
    assert sorted(os.listdir(tmp_path)) == ["run"]
    assert sorted(os.listdir(bag)) == ["metadata.yaml", "run.mcap"]
    assert McapRecorder.mcap_path.fget(SimpleNamespace(path=bag)) == bag / "run.mcap"
    assert McapRecorder.mcap_path.fget(SimpleNamespace(path=tmp_path / "x.mcap")) == tmp_path / "x.mcap"


def test_an_existing_mcap_file_is_refused_and_left_alone(tmp_path):
    run = tmp_path / "run.mcap"
    run.write_bytes(b"keep")
    with pytest.raises(LogError, match=r"run\.mcap: out_dir: expected a new \.mcap file"):
        McapRecorder(run)
    assert run.read_bytes() == b"keep" and sorted(os.listdir(tmp_path)) == ["run.mcap"]


def test_a_killed_single_file_recording_is_recovered_into_a_single_file(tmp_path):
    script = textwrap.dedent(f"""
        import sys, time
        sys.path.insert(0, {str(REPO)!r})
        from twin_nodes.logs.recording import McapRecorder
        rec = McapRecorder(sys.argv[1], chunk_bytes=64 * 1024, chunk_period_s=1e6)
        rec.add_topic("/status", "std_msgs/msg/String")
        for i in range(1500):
            rec.write("/status", {{"data": "x" * 40 + str(i)}}, 1000 + i)
        rec.flush()
        print("READY", flush=True)
        time.sleep(60)
    """)
    run = tmp_path / "live.mcap"
    proc = subprocess.Popen([sys.executable, "-c", script, str(run)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "READY"
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
    assert sorted(os.listdir(tmp_path)) == ["live.mcap"]  # written in place, nothing else left
    rep = recover(run, tmp_path / "fixed.mcap")
    assert rep.n_messages == 1500 and not rep.complete
    assert sorted(os.listdir(tmp_path)) == ["fixed.mcap", "live.mcap"]
    assert read_bag(tmp_path / "fixed.mcap")["/status"][-1][1].data.endswith("1499")


def test_the_guard_checks_an_mcap_path_as_a_file_and_any_other_as_a_folder(tmp_path):
    out = [Output("mcap", "--mcap", kind="bag")]
    (tmp_path / "old.mcap").write_bytes(b"x")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "a").write_text("a")
    (tmp_path / "dir.mcap").mkdir()

    def plan(value, force=False):
        return check(out, SimpleNamespace(mcap=str(tmp_path / value)), [], force=force)

    with pytest.raises(TwinError, match=r"old\.mcap: --mcap: expected a new file; it exists"):
        plan("old.mcap")
    assert plan("old.mcap", force=True)[0].replaces
    with pytest.raises(TwinError, match=r"full: --mcap: expected a new or empty folder"):
        plan("full")
    with pytest.raises(TwinError, match=r"dir\.mcap: --mcap: expected a file path, this is a folder"):
        plan("dir.mcap")
    assert plan("new.mcap")[0].final == tmp_path / "new.mcap"
    assert plan("newbag")[0].final == tmp_path / "newbag"


def test_regress_takes_a_single_mcap_as_the_recording_and_a_bag_mcap_as_its_folder(tmp_path):
    from twin_nodes.cli.graph_regress import _bag_folder
    from twin_nodes.graph.regress import Baseline

    record(tmp_path / "solo.mcap", n=2)
    record(tmp_path / "bag", n=2)
    solo, inner = tmp_path / "solo.mcap", tmp_path / "bag" / "bag.mcap"
    assert Baseline(solo, {}, None, {}, {}).bag_dir == solo
    assert Baseline(inner, {}, None, {}, {}).bag_dir == tmp_path / "bag"
    assert Baseline(tmp_path / "bag", {}, None, {}, {}).bag_dir == tmp_path / "bag"
    assert _bag_folder(str(solo)) == []                      # its folder is not an input
    assert _bag_folder(str(inner)) == [str(tmp_path / "bag")]


@pytest.mark.ros
@pytest.mark.slow
def test_compare_mcap_writes_that_file_and_regress_reads_it(tmp_path):
    """``rotortwin compare F --mcap run.mcap`` writes ``run.mcap`` (not ``run/run.mcap``), says so, and
    ``rotortwin regress run.mcap --offline`` flies it again."""
    flight = REPO / "bags" / "sim_quadx_weak_motor3.ulg"
    run = tmp_path / "run.mcap"
    r = subprocess.run([sys.executable, "-m", "twin_nodes", "compare", str(flight), "--params",
                        str(REPO / "params" / "px4_sih_quadx.yaml"), "--mcap", str(run), "--quiet"],
                       capture_output=True, text=True, timeout=400, cwd=REPO)
    assert r.returncode == 0, r.stderr[-3000:]
    assert sorted(os.listdir(tmp_path)) == ["run.mcap"]
    assert f"wrote: {run}" in r.stderr and f"recording: {run}\n" in r.stderr
    counts = topic_counts(run)
    assert counts["/real/odom"] > 0 and counts["/twin_error/final_json"] >= 1
    g = subprocess.run([sys.executable, "-m", "twin_nodes", "regress", str(run), "--offline", "--json",
                        str(tmp_path / "regress.json")], capture_output=True, text=True, timeout=400, cwd=REPO)
    assert g.returncode in (0, 1), g.stderr[-3000:]
    assert f"regress {run} (offline)" in g.stdout and f"wrote: {tmp_path / 'regress.json'}" in g.stderr
