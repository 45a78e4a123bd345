"""Bags: rosbag2 layout with MCAP storage (writer and reader), no rosbag2_py needed.

A bag is a directory ``<name>/`` holding ``<name>_0.mcap`` and ``metadata.yaml``
(rosbag2 format version 9: storage mcap, serialization cdr). The MCAP file has the
``ros2`` profile, one ``ros2msg`` schema per message type (the full definition text,
dependencies appended as rosbag2 does), raw CDR messages, chunk CRCs and data CRCs,
and the run's configuration and model as MCAP metadata records. Independent tools
(the ``rosbags`` library, the ``mcap`` reader) read it.

Writers are context managers whose ``finish()`` is safe to call twice. Chunks are
small and flushed on request, so after a SIGKILL everything up to the last flushed
chunk is still readable (:func:`iter_messages` tolerates a truncated file).
"""

from __future__ import annotations

import glob
import os
import time
from dataclasses import dataclass, field
from functools import lru_cache
from typing import TYPE_CHECKING

import yaml

from piezo_stage.core.errors import ConfigError, DataError
from piezo_stage.core.types import Doc
from piezo_stage.io.files import atomic_write

if TYPE_CHECKING:
    from mcap.records import Channel, Schema

# What our publishers offer, by kind (see nodes/_common.py): (depth, transient local)
QOS_KINDS = {"data": (5000, False), "latched": (1, True), "events": (20, True),
             "diag": (50, False)}


def offered_qos(kind: str = "data") -> list:
    """A topic's offered QoS profiles in rosbag2's version-9 form (a list of mappings
    with lower-case policy names), made with rosbags' own metadata writer."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )
    from rosbags.rosbag2.metadata import dump_qos_v9
    depth, latched = QOS_KINDS[kind]
    zero = QosTime(0, 0)  # "not set": infinite deadline, lifespan and lease
    return dump_qos_v9([Qos(QosHistory.KEEP_LAST, depth, QosReliability.RELIABLE,
                            QosDurability.TRANSIENT_LOCAL if latched else
                            QosDurability.VOLATILE, zero, zero, QosLiveliness.AUTOMATIC,
                            zero, False)])


def qos_profiles(qos) -> list:
    """``qos`` as a version-9 list: a kind name, a list already, or the YAML text that
    MCAP channels carry (either form, older integer policies converted)."""
    if isinstance(qos, str) and qos in QOS_KINDS:
        return offered_qos(qos)
    if isinstance(qos, str):
        from rosbags.rosbag2.metadata import dump_qos_v9, parse_qos
        try:
            return dump_qos_v9(parse_qos(yaml.safe_load(qos) or []))
        except Exception:  # noqa: BLE001 - a foreign channel's text: keep the default
            return offered_qos("data")
    return list(qos)


@lru_cache(maxsize=None)
def _typestore():
    from rosbags.typesys import Stores, get_typestore
    return get_typestore(Stores.ROS2_JAZZY)


def msgdef(msgtype: str) -> str:
    """ros2msg definition text of ``pkg/msg/Type`` with its dependencies appended."""
    text, _ = _typestore().generate_msgdef(msgtype, ros_version=2)
    return text


def serialize(msg, msgtype: str) -> bytes:
    return bytes(_typestore().serialize_cdr(msg, msgtype))


def deserialize(data: bytes, msgtype: str):
    return _typestore().deserialize_cdr(data, msgtype)


def new_bag_dir(root="bags") -> str:
    """bags/<UTC timestamp>/, never an existing folder (a suffix is added instead)."""
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime())
    path = os.path.join(root, stamp)
    k = 1
    while os.path.exists(path):
        path = os.path.join(root, f"{stamp}-{k}")
        k += 1
    return path



def _need_mcap():
    """ConfigError naming the missing package and its install line: rosdep has no key
    for mcap, so a ROS install from package.xml alone lacks it (docs/nodes.md: ROS install)."""
    try:
        import mcap  # noqa: F401
    except ImportError:
        raise ConfigError("bags need the Python package mcap, which rosdep does not "
                          "install: pip install mcap") from None

class BagWriter:
    """Write raw serialized messages into a rosbag2-layout MCAP bag.

    >>> with BagWriter("bags/run1") as bag:
    ...     ch = bag.add_topic("/stage/joint_states", "sensor_msgs/msg/JointState")
    ...     bag.write(ch, cdr_bytes, stamp_ns)
    """

    def __init__(self, path, chunk_size=64 * 1024, compression="zstd", metadata=None):
        _need_mcap()
        from mcap.writer import CompressionType, Writer
        self.path = os.fspath(path)
        if os.path.exists(self.path):
            raise DataError(f"{self.path}: bag already exists (bags are never overwritten)")
        os.makedirs(self.path)
        self.name = os.path.basename(os.path.normpath(self.path))
        self.file_name = f"{self.name}_0.mcap"
        self._fh = open(os.path.join(self.path, self.file_name), "wb")
        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                "none": CompressionType.NONE}[compression]
        self._w = Writer(self._fh, chunk_size=chunk_size, compression=comp,
                         enable_crcs=True, enable_data_crcs=True)
        self._w.start(profile="ros2", library="piezo_stage")
        self._schemas, self.topics, self.counts, self.qos = {}, {}, {}, {}
        self._first = self._last = None
        self._finished = False
        for name, data in (metadata or {}).items():
            self.add_metadata(name, data)
        self._write_metadata_yaml()  # a bag killed before finish() still has one

    def add_topic(self, topic: str, msgtype: str, qos="data") -> int:
        """Register ``topic``; ``qos``: what its publishers offer (see qos_profiles)."""
        if topic in self.topics:
            return self.topics[topic][0]
        if msgtype not in self._schemas:
            self._schemas[msgtype] = self._w.register_schema(
                name=msgtype, encoding="ros2msg", data=msgdef(msgtype).encode())
        profiles = qos_profiles(qos)
        cid = self._w.register_channel(  # rosbag2's MCAP plugin: the list as YAML text
            topic=topic, message_encoding="cdr", schema_id=self._schemas[msgtype],
            metadata={"offered_qos_profiles": yaml.safe_dump(profiles, sort_keys=False)})
        self.topics[topic] = (cid, msgtype)
        self.qos[topic] = profiles
        self.counts[topic] = 0
        return cid

    def add_metadata(self, name: str, data: Doc):
        self._w.add_metadata(name, {str(k): str(v) for k, v in data.items()})

    def write(self, topic: str, data: bytes, log_time_ns: int, publish_time_ns=None):
        cid, _ = self.topics[topic]
        self._w.add_message(channel_id=cid, log_time=int(log_time_ns), data=data,
                            publish_time=int(publish_time_ns or log_time_ns),
                            sequence=self.counts[topic])
        self.counts[topic] += 1
        self._first = log_time_ns if self._first is None else min(self._first, log_time_ns)
        self._last = log_time_ns if self._last is None else max(self._last, log_time_ns)

    def flush(self):
        """Close the current chunk and push it to disk (survives a SIGKILL after this)."""
        if self._finished:
            return
        self._w.flush()  # finishes the chunk in progress and flushes the stream
        os.fsync(self._fh.fileno())

    def _write_metadata_yaml(self):
        first = self._first or 0
        dur = (self._last - first) if self._last is not None else 0
        total = sum(self.counts.values())
        info = {
            "version": 9,
            "storage_identifier": "mcap",
            "duration": {"nanoseconds": int(dur)},
            "starting_time": {"nanoseconds_since_epoch": int(first)},
            "message_count": int(total),
            "topics_with_message_count": [
                {"topic_metadata": {"name": t, "type": mt, "serialization_format": "cdr",
                                    "offered_qos_profiles": self.qos[t],
                                    "type_description_hash": ""},
                 "message_count": int(self.counts[t])}
                for t, (_, mt) in self.topics.items()],
            "compression_format": "",
            "compression_mode": "",
            "relative_file_paths": [self.file_name],
            "files": [{"path": self.file_name,
                       "starting_time": {"nanoseconds_since_epoch": int(first)},
                       "duration": {"nanoseconds": int(dur)},
                       "message_count": int(total)}],
            "custom_data": {},
            "ros_distro": "jazzy",
        }
        with atomic_write(os.path.join(self.path, "metadata.yaml")) as fh:
            yaml.safe_dump({"rosbag2_bagfile_information": info}, fh, sort_keys=False)

    def finish(self):
        if self._finished:
            return
        self._finished = True
        self._w.finish()
        self._fh.flush()
        os.fsync(self._fh.fileno())
        self._fh.close()
        self._write_metadata_yaml()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.finish()
        return False


def mcap_path(path) -> str:
    p = os.fspath(path)
    if os.path.isdir(p):
        files = sorted(glob.glob(os.path.join(p, "*.mcap")))
        if not files:
            raise DataError(f"{p}: no .mcap file in the bag directory")
        return files[0]
    if not os.path.isfile(p):
        raise DataError(f"{p}: no such bag")
    return p


def what_file(path, head: bytes) -> str:
    """What a file that is not an MCAP bag looks like, from its name and first bytes,
    in a few words for an error line ("a YAML file: the bag's metadata.yaml")."""
    name = os.path.basename(os.fspath(path))
    if not head:
        return "an empty file"
    if head.startswith(b"#ROSBAG"):
        return "a ROS 1 bag (convert it with rosbags-convert)"
    if head.startswith(b"SQLite format 3"):
        return "a rosbag2 SQLite3 bag (record with the mcap storage, or convert it)"
    if head.startswith(b"\x89PNG"):
        return "a PNG picture"
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError:
        return "a binary file"
    first = text.lstrip().split("\n", 1)[0]
    if name == "metadata.yaml":
        return "the bag's metadata.yaml (give its directory)"
    if name.endswith((".yaml", ".yml")) or first.endswith(":") or ": " in first:
        return "a YAML file (a model or parameters?)"
    if text.lstrip().startswith(("{", "[")):
        return "a JSON file"
    if "," in first:
        return "a CSV table (a record: identify and gap read it)"
    return "a text file"


@dataclass
class BagScan:
    """What a record-by-record read of an MCAP file recovered (see ``scan_bag``)."""

    path: str
    schemas: dict[int, Schema] = field(default_factory=dict)  # id -> mcap Schema
    channels: dict[int, Channel] = field(default_factory=dict)  # id -> mcap Channel
    messages: list = field(default_factory=list)     # mcap Message, file order
    metadata: list = field(default_factory=list)     # mcap Metadata
    corrupt: list = field(default_factory=list)      # (chunk number, offset, lost, why)
    truncated_at: int | None = None                  # byte offset of a cut-off record
    complete: bool = False                           # the data section ends properly

    def damage(self) -> str:
        """One line on what is missing, or '' when nothing is."""
        parts = [f"chunk {k} at byte {off} is corrupt ({why}; {lost} message(s) lost)"
                 for k, off, lost, why in self.corrupt]
        if self.truncated_at is not None:
            parts.append(f"the file is cut off at byte {self.truncated_at} (writer killed?)")
        elif not self.complete:
            parts.append("the file has no summary (writer killed?)")
        return "; ".join(parts)


def scan_bag(path) -> BagScan:
    """Read an MCAP file record by record, keeping every intact record: a chunk whose
    CRC or compression is broken is skipped and noted (with the number of messages its
    message index says it held), a cut-off tail is noted, and reading goes on past both.
    """
    import io
    _need_mcap()

    from mcap.exceptions import EndOfFile, McapError
    from mcap.records import Channel, Message, MessageIndex, Metadata, Schema
    from mcap.stream_reader import MAGIC_SIZE, StreamReader
    p = mcap_path(path)
    try:
        with open(p, "rb") as fh:
            data = fh.read()
    except OSError as e:
        raise DataError(f"{p}: cannot read ({e.strerror})") from None
    magic = data[:MAGIC_SIZE]
    if len(data) < MAGIC_SIZE or magic[1:5] != b"MCAP":
        raise DataError(f"{p}: {what_file(p, data[:4096])}, not a bag (an MCAP file or "
                        "a directory holding one)")
    scan, off, chunk_no, last_chunk = BagScan(p), MAGIC_SIZE, -1, None
    while off < len(data):
        if off + 9 > len(data):
            scan.truncated_at = off
            break
        op, n = data[off], int.from_bytes(data[off + 1:off + 9], "little")
        end = off + 9 + n
        if end > len(data):
            scan.truncated_at = off
            break
        if op == 15:  # DataEnd (its CRC covers the whole data section): the end
            scan.complete = True
            break
        if op == 6:  # a chunk
            chunk_no += 1
        got = []
        try:  # one record, through mcap's own parser (CRCs checked)
            for r in StreamReader(io.BytesIO(magic + data[off:end]), validate_crcs=True,
                                  record_size_limit=None).records:
                got.append(r)
        except EndOfFile:
            pass  # the one-record stream ended: all of it was read
        except (McapError, EOFError, ValueError, RuntimeError, Exception) as e:  # noqa: BLE001
            if op != 6:  # a broken record outside chunks: the data cannot be followed
                scan.truncated_at = off
                break
            why = str(e).strip().split("\n")[0][:80] or type(e).__name__
            scan.corrupt.append([chunk_no, off, 0, why])
            last_chunk, got = scan.corrupt[-1], []
        if op == 6 and got:
            last_chunk = None
        for r in got:
            if isinstance(r, Schema):
                scan.schemas[r.id] = r
            elif isinstance(r, Channel):
                scan.channels[r.id] = r
            elif isinstance(r, Message):
                scan.messages.append(r)
            elif isinstance(r, Metadata):
                scan.metadata.append(r)
            elif isinstance(r, MessageIndex) and last_chunk is not None:
                last_chunk[2] += len(r.records)  # what the corrupt chunk held
        if scan.complete:
            break
        off = end
    scan.corrupt = [tuple(c) for c in scan.corrupt]
    return scan


def _warn(line):
    import sys
    sys.stderr.write(f"piezo-stage: warning: {line}\n")


def iter_messages(path, topics=None, on_damage=_warn):
    """Yield (topic, msgtype, log_time_ns, raw CDR bytes) in file order.

    Reads the stream front to back; a bag whose writer was killed yields every message
    of its complete chunks. A corrupt chunk is not taken for the end of the data: the
    rest is read record by record (``scan_bag``) and ``on_damage`` gets one line saying
    which chunk is corrupt and how much was lost; DataError when nothing is usable.
    """
    _need_mcap()
    from mcap.exceptions import McapError
    from mcap.reader import NonSeekingReader
    p = mcap_path(path)
    n = 0
    try:
        with open(p, "rb") as fh:
            reader = NonSeekingReader(fh, validate_crcs=True)
            try:
                for schema, channel, message in reader.iter_messages(
                        topics=topics, log_time_order=False):
                    yield (channel.topic, schema.name if schema is not None else "",
                           message.log_time, message.data)
                    n += 1
                return
            except Exception as e:  # noqa: BLE001 - CRC, decompression, truncation...
                if isinstance(e, McapError) and "magic" in str(e).lower() and \
                        "start" in str(e).lower():
                    raise
    except McapError as e:
        raise DataError(f"{p}: not a readable MCAP file ({e})") from None
    except OSError as e:
        raise DataError(f"{p}: cannot read ({e.strerror})") from None
    scan = scan_bag(p)  # the stream stopped early: find out why, salvage the rest
    if scan.corrupt:
        on_damage(f"{p}: {scan.damage()}")
    msgs = [m for m in scan.messages if topics is None
            or scan.channels[m.channel_id].topic in topics]
    if not msgs:
        raise DataError(f"{p}: nothing usable ({scan.damage() or 'no messages'})")
    for m in msgs[n:]:
        ch = scan.channels[m.channel_id]
        yield ch.topic, scan.schemas[ch.schema_id].name, m.log_time, m.data


def repair_bag(path) -> BagScan:
    """Rewrite a damaged bag (killed writer, corrupt chunks) with everything that can be
    read, a summary and a fresh metadata.yaml, so standard readers open it. The original
    file is kept beside it as ``<name>.orig``. Returns the scan of the original."""
    import shutil
    import tempfile
    p = mcap_path(path)
    scan = scan_bag(p)
    if not scan.messages:
        raise DataError(f"{p}: nothing to recover ({scan.damage() or 'no messages'})")
    bag_dir = os.path.dirname(os.path.abspath(p))
    tmp = tempfile.mkdtemp(dir=os.path.dirname(bag_dir), prefix=".repair-")
    try:
        out = BagWriter(os.path.join(tmp, os.path.basename(bag_dir)),
                        metadata={m.name: dict(m.metadata) for m in scan.metadata})
        for ch in scan.channels.values():
            out.add_topic(ch.topic, scan.schemas[ch.schema_id].name,
                          ch.metadata.get("offered_qos_profiles", "data"))
        for m in scan.messages:
            ch = scan.channels[m.channel_id]
            out.write(ch.topic, m.data, m.log_time, m.publish_time)
        out.finish()
        os.replace(p, p + ".orig")
        os.replace(os.path.join(out.path, out.file_name), p)
        if out.file_name != os.path.basename(p):  # metadata.yaml names the file
            out.file_name = os.path.basename(p)
        out.path = bag_dir
        out._write_metadata_yaml()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return scan


def read_metadata(path) -> Doc:
    """MCAP metadata records: name -> dict."""
    _need_mcap()
    from mcap.reader import make_reader
    with open(mcap_path(path), "rb") as fh:
        return {m.name: dict(m.metadata) for m in make_reader(fh).iter_metadata()}


def read_bag_record(path, namespace=None):
    """A Record (t [s], v [V], w [um]) from a bag's ``<ns>/joint_states``.

    sensor_msgs/JointState: measured position in metres, and the voltage applied during
    that sample in ``effort`` (volts), as the stage driver publishes them.
    """
    import numpy as np

    from piezo_stage.core.estimation.record import Record
    from piezo_stage_msgs_adapters.wire import joint_state_um
    pos, volt, bad = {}, {}, 0
    seen = set()
    try:
        for topic, msgtype, _, data in iter_messages(path):
            seen.add(topic)
            if not (topic.endswith("/joint_states") and msgtype == "sensor_msgs/msg/JointState"):
                continue
            if namespace and not topic.startswith(namespace):
                continue
            try:  # an outside node's malformed joint state is not the stage's sample
                st, w, v = joint_state_um(data, f"{path}: joint_states")
            except DataError:
                bad += 1
                continue
            if not w:  # foreign joints only
                bad += 1
                continue
            pos[st] = w
            if v is not None:
                volt[st] = v
    except (DataError, ConfigError):
        raise
    except Exception as e:  # a corrupt message body: one line, not a traceback
        raise DataError(f"{path}: unreadable bag ({type(e).__name__}: {e})") from None
    if bad:
        _warn(f"{path}: {bad} joint_states message(s) that are not the stage's samples "
              "(malformed, or foreign joints) left out")
    if not pos or not volt:
        raise DataError(f"{path}: bag lacks the needed topic (<ns>/joint_states, "
                        f"sensor_msgs/JointState with the applied voltage in effort); it has "
                        f"{', '.join(sorted(seen)) or 'no messages'}")
    stamps = sorted(set(pos) & set(volt))
    if len(stamps) < 3:
        raise DataError(f"{path}: fewer than 3 samples with both position and voltage")
    t = np.array(stamps, dtype=np.int64)
    t = (t - t[0]) / 1e9
    axes = [a for a in ("x", "y") if all(a in pos[s] for s in stamps)]
    return Record(t, {a: np.array([volt[s][a] for s in stamps]) for a in axes},
                  {a: np.array([pos[s][a] for s in stamps]) for a in axes},
                  source=os.fspath(path), voltage_exact=True)


def write_record_bag(path, rec, namespace="/stage", metadata=None):
    """Write a Record as the driver would publish it (joint_states: position in metres,
    applied voltage in effort; header stamps = record time). For fixtures and for
    converting CSV records into bags."""
    import numpy as np

    from piezo_stage_msgs_adapters.wire import UM
    ts = _typestore()
    Time = ts.types["builtin_interfaces/msg/Time"]
    Header = ts.types["std_msgs/msg/Header"]
    JointState = ts.types["sensor_msgs/msg/JointState"]
    axes = [a for a in ("x", "y") if a in rec.w]
    js_t = f"{namespace}/joint_states"
    zeros = np.zeros(len(rec))
    with BagWriter(path, metadata=metadata) as bag:
        bag.add_topic(js_t, "sensor_msgs/msg/JointState")
        for k in range(len(rec)):
            ns = int(round(rec.t[k] * 1e9))
            h = Header(stamp=Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000),
                       frame_id="stage")
            js = JointState(header=h, name=axes,
                            position=np.array([rec.w[a][k] * UM for a in axes]),
                            velocity=np.zeros(0),
                            effort=np.array([rec.v.get(a, zeros)[k] for a in axes]))
            bag.write(js_t, serialize(js, "sensor_msgs/msg/JointState"), ns)
