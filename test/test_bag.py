"""Bags: rosbag2 layout with MCAP storage, read back by independent readers."""

import os
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT
from piezo_stage.core.errors import DataError
from piezo_stage.core.estimation.record import Record
from piezo_stage.io.bag import (
    BagWriter,
    iter_messages,
    mcap_path,
    new_bag_dir,
    read_bag_record,
    read_metadata,
    scan_bag,
    write_record_bag,
)


def _rec(n=3000, fs=1000.0):
    t = np.arange(n) / fs
    v = 75 - 75 * np.cos(2 * np.pi * t)
    return Record(t, {"x": v, "y": v[::-1].copy()}, {"x": 0.5 * v, "y": 0.4 * v[::-1]})


def test_round_trip_and_independent_readers(tmp_path):
    rec = _rec()
    path = tmp_path / "b1"
    write_record_bag(path, rec, metadata={"piezo_stage_config": {"yaml": "a: 1"}})
    assert (path / "metadata.yaml").exists() and (path / "b1_0.mcap").exists()
    back = read_bag_record(path)
    np.testing.assert_allclose(back.t, rec.t, atol=1e-9)
    np.testing.assert_allclose(back.v["x"], rec.v["x"])
    np.testing.assert_allclose(back.w["y"], rec.w["y"], atol=1e-9)
    assert read_metadata(path)["piezo_stage_config"] == {"yaml": "a: 1"}
    # the mcap library's seeking reader, with CRC validation of chunks
    from mcap.reader import make_reader
    with open(path / "b1_0.mcap", "rb") as fh:
        r = make_reader(fh, validate_crcs=True)
        summary = r.get_summary()
        assert summary.statistics.message_count == len(rec)
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        assert sum(1 for _ in r.iter_messages()) == len(rec)
    # the rosbags library reads the rosbag2 directory
    from rosbags.highlevel import AnyReader
    with AnyReader([path]) as reader:
        assert reader.message_count == len(rec)
        conns = [c for c in reader.connections if c.topic == "/stage/joint_states"]
        msgs = [reader.deserialize(raw, c.msgtype)
                for c, _, raw in reader.messages(connections=conns)]
        assert len(msgs) == len(rec)
        np.testing.assert_allclose(msgs[10].position[0], rec.w["x"][10] * 1e-6)


def test_never_overwritten(tmp_path):
    p = tmp_path / "b"
    write_record_bag(p, _rec(50))
    with pytest.raises(DataError, match="already exists"):
        BagWriter(p)
    d1 = new_bag_dir(tmp_path)
    os.makedirs(d1)
    assert new_bag_dir(tmp_path) != d1


def test_finish_twice_is_safe(tmp_path):
    """A second finish changes nothing: the bag stays complete and readable."""
    b = BagWriter(tmp_path / "b")
    b.add_topic("/stage/joint_states", "sensor_msgs/msg/JointState")
    b.finish()
    files = sorted(p.name for p in (tmp_path / "b").iterdir())
    before = {n: (tmp_path / "b" / n).read_bytes() for n in files}
    b.finish()
    assert sorted(p.name for p in (tmp_path / "b").iterdir()) == files
    assert {n: (tmp_path / "b" / n).read_bytes() for n in files} == before
    scan = scan_bag(mcap_path(tmp_path / "b"))
    assert "metadata.yaml" in files and scan.complete and scan.damage() == ""


def test_truncated_bag_readable_up_to_last_flushed_chunk(tmp_path):
    path = tmp_path / "kill"
    code = f"""
import os, signal, numpy as np
from piezo_stage.io.bag import BagWriter, serialize, _typestore
ts = _typestore()
S = ts.types['std_msgs/msg/String']
b = BagWriter({str(path)!r})
b.add_topic('/t', 'std_msgs/msg/String')
for k in range(1000):
    b.write('/t', serialize(S(data='m%d' % k), 'std_msgs/msg/String'), k * 1000)
    if k == 599:
        b.flush()
os.kill(os.getpid(), signal.SIGKILL)
"""
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT,
                       env=dict(os.environ, PYTHONPATH=ROOT))
    assert r.returncode == -9
    n = sum(1 for _ in iter_messages(path))
    assert n == 600  # everything up to the flush, nothing after


@pytest.mark.parametrize("content", [b"", b"garbage" * 10])
def test_unreadable_bag(tmp_path, content):
    p = tmp_path / "x.mcap"
    p.write_bytes(content)
    with pytest.raises(DataError):
        read_bag_record(p)


def test_bag_without_needed_topics(tmp_path):
    from piezo_stage.io.bag import _typestore, serialize
    S = _typestore().types["std_msgs/msg/String"]
    with BagWriter(tmp_path / "b") as b:
        b.add_topic("/chatter", "std_msgs/msg/String")
        b.write("/chatter", serialize(S(data="hi"), "std_msgs/msg/String"), 1)
    with pytest.raises(DataError, match="lacks the needed topic"):
        read_bag_record(tmp_path / "b")


def test_identify_on_a_bag(tmp_path, plant_config_path):
    from piezo_stage.core.model.plant import Plant
    from piezo_stage.io.plant_file import load_plant_config
    cfg = load_plant_config(plant_config_path)
    t = np.arange(2000) / 1000
    v = 75 - 75 * np.cos(2 * np.pi * t)
    w = Plant(cfg, 1000).run(v, np.zeros_like(v))
    write_record_bag(tmp_path / "run", Record(t, {"x": v, "y": 0 * v}, w))
    r = subprocess.run([sys.executable, "-m", "piezo_stage.cli", "identify",
                        str(tmp_path / "run"), "--axis", "x", "--coupling", "off"],
                       capture_output=True, text=True, cwd=ROOT,
                       env=dict(os.environ, PYTHONPATH=ROOT))
    assert r.returncode == 0, r.stderr
    row = [line.split() for line in r.stdout.splitlines() if line.split()[:1] == ["x"]][0]
    assert float(row[3]) < 0.105
    r = subprocess.run([sys.executable, "-m", "piezo_stage.cli", "identify",
                        str(tmp_path / "nothing")], capture_output=True, text=True,
                       cwd=ROOT, env=dict(os.environ, PYTHONPATH=ROOT))
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1


def _chunked_bag(path, n=300):
    import piezo_stage_msgs_adapters as A
    w = BagWriter(path, chunk_size=2000)
    w.add_topic("/s/joint_states", "sensor_msgs/msg/JointState")
    for k in range(n):
        w.write("/s/joint_states", A.joint_state_cdr(k * 1_000_000, {"x": k * 1e-3, "y": 0.0},
                                                     {"x": 1.0 * k, "y": 0.0}), k * 1_000_000)
    w.finish()
    return mcap_path(path)


def _chunk_offsets(data):
    offs, off = [], 8
    while off < len(data) and data[off] != 15:
        if data[off] == 6:
            offs.append(off)
        off += 9 + int.from_bytes(data[off + 1:off + 9], "little")
    return offs


def test_a_corrupt_chunk_is_named_and_the_rest_is_read(tmp_path, capsys):
    p = _chunked_bag(tmp_path / "c")
    b = bytearray(open(p, "rb").read())
    b[_chunk_offsets(b)[2] + 200] ^= 0xFF
    open(p, "wb").write(b)
    got = [t for t, *_ in iter_messages(tmp_path / "c")]
    err = capsys.readouterr().err
    assert "chunk 2" in err and "corrupt" in err and "message(s) lost" in err
    lost = int(err.split("; ")[-1].split(" message")[0])
    assert lost > 0 and len(got) == 300 - lost  # not silently cut at the bad chunk
    rec = read_bag_record(tmp_path / "c")  # a hole is said, not glossed:
    assert not rec.uniform  # the stamps keep it; on a grid, it splits the record
    from piezo_stage.core.estimation.record import on_grid
    g = on_grid(rec)
    assert g.uniform and g.unmeasured() == lost, (g.unmeasured(), lost)
    assert "1 hole(s)" in g.notes[-1] and "2 segments" in g.notes[-1], g.notes


def test_nothing_usable_is_an_error(tmp_path):
    p = _chunked_bag(tmp_path / "z", n=20)
    b = bytearray(open(p, "rb").read())
    for off in _chunk_offsets(b):
        b[off + 60] ^= 0xFF
    open(p, "wb").write(b)
    with pytest.raises(DataError, match="nothing usable"):
        list(iter_messages(tmp_path / "z"))


def test_bag_repair_makes_a_killed_writers_bag_readable_by_standard_readers(tmp_path):
    import subprocess
    import sys

    from mcap.reader import make_reader
    from rosbags.rosbag2 import Reader

    from conftest import ROOT
    p = _chunked_bag(tmp_path / "k")
    d = open(p, "rb").read()
    open(p, "wb").write(d[:len(d) // 2])  # the writer was killed mid-file
    with open(p, "rb") as fh, pytest.raises(Exception):
        make_reader(fh).get_summary().statistics  # noqa: B018 - what fails today
    r = subprocess.run([sys.executable, "-m", "piezo_stage.cli", "bag", "repair",
                        str(tmp_path / "k")], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    n = sum(1 for _ in iter_messages(tmp_path / "k"))
    assert 100 < n < 300
    with open(p, "rb") as fh:
        assert make_reader(fh).get_summary().statistics.message_count == n
    with Reader(tmp_path / "k") as bag:  # rosbag2 layout: metadata.yaml agrees
        assert bag.message_count == n
    assert os.path.exists(p + ".orig")


def test_metadata_is_rosbag2_v9_with_qos_as_offered(tmp_path):
    """metadata.yaml as rosbag2 Jazzy reads it: QoS profiles as a YAML list (what rosbags'
    own v9 writer emits), transient local where the publisher latches; rosbags' rosbag2
    reader (metadata.yaml, not the MCAP summary) parses it and gets the durability."""
    import yaml
    from rosbags.interfaces import QosDurability
    from rosbags.rosbag2 import Reader, Writer
    from rosbags.typesys import Stores, get_typestore
    with BagWriter(tmp_path / "q") as b:
        b.add_topic("/s/joint_states", "sensor_msgs/msg/JointState")
        b.add_topic("/s/model", "std_msgs/msg/String", "latched")
        b.add_topic("/s/state", "diagnostic_msgs/msg/DiagnosticArray", "events")
        ts = get_typestore(Stores.ROS2_JAZZY)
        b.write("/s/model", bytes(ts.serialize_cdr(ts.types["std_msgs/msg/String"](
            data="m"), "std_msgs/msg/String")), 5)
    info = yaml.safe_load((tmp_path / "q" / "metadata.yaml").read_text())[
        "rosbag2_bagfile_information"]
    assert info["version"] == 9
    topics = {t["topic_metadata"]["name"]: t["topic_metadata"]
              for t in info["topics_with_message_count"]}
    # rosbags' writer, same version, for the shape of a profile
    ref_dir = tmp_path / "ref"
    with Writer(ref_dir, version=9) as w:
        w.add_connection("/t", "std_msgs/msg/String", typestore=ts)
    ref = yaml.safe_load((ref_dir / "metadata.yaml").read_text())[
        "rosbag2_bagfile_information"]["topics_with_message_count"][0]["topic_metadata"]
    for meta in topics.values():
        assert isinstance(meta["offered_qos_profiles"], list)
        for prof in meta["offered_qos_profiles"]:
            assert isinstance(prof, dict) and set(prof) == {
                "history", "depth", "reliability", "durability", "deadline", "lifespan",
                "liveliness", "liveliness_lease_duration", "avoid_ros_namespace_conventions"}
        assert isinstance(ref["offered_qos_profiles"], list)
    assert topics["/s/model"]["offered_qos_profiles"][0]["durability"] == "transient_local"
    assert topics["/s/joint_states"]["offered_qos_profiles"][0]["durability"] == "volatile"
    with Reader(tmp_path / "q") as r:  # rosbag2 reader on metadata.yaml
        qos = {c.topic: c.ext.offered_qos_profiles for c in r.connections}
        assert qos["/s/model"][0].durability == QosDurability.TRANSIENT_LOCAL
        assert qos["/s/state"][0].depth == 20
        assert r.message_count == 1


def test_joint_states_an_outside_node_sent_are_left_out_of_the_record(tmp_path, capfd):
    """A bag also holds what outside nodes sent on joint_states (the faults bench sends
    repeated and foreign joints): both readers leave such messages out, the record
    reader saying how many in one line, instead of refusing the whole bag."""
    import numpy as np

    from piezo_stage.core.estimation.record import Record
    from piezo_stage.io.bag import BagWriter, read_bag_record, write_record_bag
    from piezo_stage.io.run_bag import read_run
    from piezo_stage_msgs_adapters.cdr import encode_joint_state
    path = str(tmp_path / "run")
    t = np.arange(200) / 100.0
    write_record_bag(path, Record(t, {"x": np.sin(t), "y": np.cos(t)},
                                  {"x": np.sin(t), "y": np.cos(t)}))
    hostile = str(tmp_path / "hostile")
    with BagWriter(hostile) as bag:
        bag.add_topic("/stage/joint_states", "sensor_msgs/msg/JointState")
        for k in range(200):
            ns = int(k * 1e7)
            bag.write("/stage/joint_states", encode_joint_state(
                ns, "stage", ["x", "y"], [1e-6 * k, 2e-6], (), [1.0, 2.0]), ns)
        for names in (["x", "x"], ["a", "b"]):
            bag.write("/stage/joint_states", encode_joint_state(
                5_000_000, "stage", names, [1e-6, 1e-6], (), [1.0, 1.0]), 5_000_000)
    rec = read_bag_record(hostile)
    assert len(rec) == 200 and set(rec.w) == {"x", "y"}
    assert "2 joint_states message(s) that are not the stage's samples" in capfd.readouterr().err
    run = read_run(hostile)
    assert len(run.t_ns) == 200 and run.skipped == 2
    assert len(read_bag_record(path)) == 200
