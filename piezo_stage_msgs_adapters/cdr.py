"""Standard messages straight to and from their CDR bytes, for the per-sample topics.

rclpy turns every message into Python objects and back (about 20-60 us per message and
hop here); at 1 kHz through four processes that is a good part of the loop. These
codecs read and write the same wire format the RMW does (OMG CDR, XCDR1, as Fast DDS
and Cyclone DDS send ROS 2 messages; XCDR2 plain and big-endian are read too), so a
node can ``publish(bytes)`` and subscribe with ``raw=True`` while every other tool sees
ordinary sensor_msgs/geometry_msgs messages. Tested against rclpy.serialization.

Layout rules used: a 4-byte encapsulation header (0x00 0x01 = CDR little-endian), then
the fields in order, each aligned to its size relative to the end of that header
(8-byte primitives to 8 in XCDR1, to 4 in XCDR2); strings are uint32 length including
the NUL, then the bytes; sequences are a uint32 count, then the elements.
"""

from __future__ import annotations

import functools
import struct

from piezo_stage.core.errors import DataError

__all__ = ["CdrReader", "encode_joint_state", "decode_joint_state", "encode_point_stamped",
           "decode_point_stamped", "encode_vector3_stamped", "decode_vector3_stamped"]

_ENCAPSULATIONS = {0x00: (">", 8), 0x01: ("<", 8),   # CDR (XCDR1) big / little endian
                   0x06: (">", 4), 0x07: ("<", 4)}   # PLAIN_CDR2 big / little endian


class CdrReader:
    """Sequential reader over one serialized message (raises DataError when the bytes
    do not hold what is asked for)."""

    __slots__ = ("buf", "pos", "end", "a8")

    def __init__(self, data: bytes | bytearray | memoryview):
        if len(data) < 4 or data[0] != 0 or data[1] not in _ENCAPSULATIONS:
            raise DataError(f"CDR: unsupported or missing encapsulation header "
                            f"{bytes(data[:2]).hex() or '(empty)'}")
        self.end, self.a8 = _ENCAPSULATIONS[data[1]]
        self.buf, self.pos = data, 4

    def _take(self, fmt: str, size: int, align: int):
        self.pos += -(self.pos - 4) % align
        try:
            v = struct.unpack_from(self.end + fmt, self.buf, self.pos)
        except struct.error:
            raise DataError("CDR: message truncated") from None
        self.pos += size
        return v

    def u32(self) -> int:
        return self._take("I", 4, 4)[0]

    def stamp(self) -> int:
        """builtin_interfaces/Time -> ns."""
        sec, nsec = self._take("iI", 8, 4)
        return sec * 1_000_000_000 + nsec

    def string(self) -> str:
        n = self.u32()
        raw = bytes(self.buf[self.pos:self.pos + n])
        if n == 0 or len(raw) != n or raw[-1] != 0:
            raise DataError("CDR: malformed string")
        self.pos += n
        return raw[:-1].decode("utf-8", "replace")

    def count(self, item_size: int) -> int:
        n = self.u32()
        if n * item_size > len(self.buf) - self.pos:
            raise DataError("CDR: sequence longer than the message")
        return n

    def doubles(self, n: int) -> tuple:
        return self._take(f"{n}d", 8 * n, self.a8) if n else ()

    def double_seq(self) -> tuple:
        return self.doubles(self.count(8))


class _Writer:
    """XCDR1 little-endian, what rmw_fastrtps writes."""

    __slots__ = ("parts", "pos")

    def __init__(self):
        self.parts, self.pos = [b"\x00\x01\x00\x00"], 0

    def _put(self, b: bytes, align: int):
        pad = -self.pos % align
        if pad:
            self.parts.append(b"\x00" * pad)
        self.parts.append(b)
        self.pos += pad + len(b)

    def header(self, ns: int, frame_id: str):
        ns = int(ns)
        self._put(struct.pack("<iI", ns // 1_000_000_000, ns % 1_000_000_000), 4)
        self.string(frame_id)

    def string(self, s: str):
        b = s.encode() + b"\x00"
        self._put(struct.pack("<I", len(b)) + b, 4)

    def double_seq(self, vals):
        n = len(vals)
        self._put(struct.pack("<I", n), 4)
        if n:
            self._put(struct.pack(f"<{n}d", *vals), 8)

    def doubles(self, *vals):
        self._put(struct.pack(f"<{len(vals)}d", *vals), 8)

    def bytes(self) -> bytes:
        return b"".join(self.parts)


@functools.lru_cache(maxsize=64)
def _joint_state_layout(frame_id: str, names: tuple, counts: tuple):
    """Template bytes (zero stamp and values) of a JointState layout and the offsets
    and packers of its stamp and value blocks: encoding is then a copy and a few packs."""
    w = _Writer()
    w.header(0, frame_id)
    w._put(struct.pack("<I", len(names)), 4)
    for n in names:
        w.string(n)
    blocks: list[tuple[int, struct.Struct] | None] = []
    for n in counts:
        w._put(struct.pack("<I", n), 4)
        if n:
            w._put(bytes(8 * n), 8)
            blocks.append((4 + w.pos - 8 * n, struct.Struct(f"<{n}d")))
        else:
            blocks.append(None)
    return w.bytes(), tuple(blocks)


_STAMP_LE = struct.Struct("<iI")
_XYZ_LE = struct.Struct("<3d")


def encode_joint_state(ns: int, frame_id: str, names, position=(), velocity=(),
                       effort=()) -> bytes:
    """sensor_msgs/msg/JointState as CDR bytes."""
    seqs = (position, velocity, effort)
    template, blocks = _joint_state_layout(frame_id, tuple(names),
                                           tuple(len(x) for x in seqs))
    buf = bytearray(template)
    ns = int(ns)
    _STAMP_LE.pack_into(buf, 4, ns // 1_000_000_000, ns % 1_000_000_000)
    for blk, vals in zip(blocks, seqs):
        if blk is not None:
            blk[1].pack_into(buf, blk[0], *vals)
    return bytes(buf)


# the layouts the loop's own messages have (the driver's joint states, the feedforward's
# references): a message of one of them is read with one unpack, the layout proved
# byte for byte (everything but the stamp and the values must match its template)
_KNOWN: dict[int, list] = {}


def known_joint_state_layout(frame_id: str, names: tuple, counts: tuple) -> None:
    """Register a JointState layout for ``decode_joint_state``'s one-unpack path."""
    template, blocks = _joint_state_layout(frame_id, tuple(names), tuple(counts))
    spans, cut = [], 12  # the parts outside the stamp (bytes 4-12) and the values
    for blk in blocks:
        if blk is not None:
            spans.append((cut, blk[0]))
            cut = blk[0] + blk[1].size
    spans.append((cut, len(template)))
    entry = (template, tuple(spans), blocks, frame_id, list(names), tuple(counts))
    if entry not in _KNOWN.setdefault(len(template), []):
        _KNOWN[len(template)].append(entry)


def _decode_known(data):
    for template, spans, blocks, frame, names, counts in _KNOWN.get(len(data), ()):
        if data[:4] == template[:4] and all(data[a:b] == template[a:b] for a, b in spans):
            sec, nsec = _STAMP_LE.unpack_from(data, 4)
            vals = [blk[1].unpack_from(data, blk[0]) if blk is not None else ()
                    for blk in blocks]
            return sec * 1_000_000_000 + nsec, frame, list(names), *vals
    return None


def decode_joint_state(data: bytes | bytearray | memoryview):
    """-> (stamp ns, frame_id, names, position, velocity, effort) from CDR bytes."""
    known = _decode_known(data) if len(data) in _KNOWN else None
    if known is not None:
        return known
    r = CdrReader(data)
    ns, frame = r.stamp(), r.string()
    names = [r.string() for _ in range(r.count(5))]
    return ns, frame, names, r.double_seq(), r.double_seq(), r.double_seq()


@functools.lru_cache(maxsize=64)
def _point_stamped_layout(frame_id: str) -> tuple[bytes, int]:
    """Template bytes (zero stamp and values) of a PointStamped with this frame, and
    the offset of its x, y, z: encoding is then a copy and two packs."""
    w = _Writer()
    w.header(0, frame_id)
    w.doubles(0.0, 0.0, 0.0)
    template = w.bytes()
    return template, len(template) - 24


def encode_point_stamped(ns: int, frame_id: str, x: float, y: float, z: float) -> bytes:
    """geometry_msgs/msg/PointStamped (also the layout of Vector3Stamped) as CDR bytes."""
    template, at = _point_stamped_layout(frame_id)
    buf = bytearray(template)
    ns = int(ns)
    _STAMP_LE.pack_into(buf, 4, ns // 1_000_000_000, ns % 1_000_000_000)
    _XYZ_LE.pack_into(buf, at, x, y, z)
    return bytes(buf)


_STAMPED_HEAD = struct.Struct("<iII")  # stamp (sec, nanosec), the frame_id's length


def decode_point_stamped(data: bytes):
    """-> (stamp ns, frame_id, (x, y, z)); Vector3Stamped has the same layout. XCDR1
    little-endian, what the RMW sends, is read in one pass (the driver takes a command
    a sample); anything else, or bytes that do not hold a whole message, the general
    way (``CdrReader``: other encodings read, malformed ones refused)."""
    if len(data) >= 16 and data[0] == 0 and data[1] == 0x01:
        sec, nsec, n = _STAMPED_HEAD.unpack_from(data, 4)
        end = 16 + n
        at = end + (-(end - 4) % 8)
        if n > 0 and at + 24 <= len(data) and data[end - 1] == 0:
            return (sec * 1_000_000_000 + nsec,
                    bytes(data[16:end - 1]).decode("utf-8", "replace"),
                    _XYZ_LE.unpack_from(data, at))
    r = CdrReader(data)
    return r.stamp(), r.string(), r.doubles(3)


encode_vector3_stamped = encode_point_stamped
decode_vector3_stamped = decode_point_stamped


def decode_joint_trajectory(data: bytes, max_points: int | None = None):
    """trajectory_msgs/JointTrajectory bytes -> (joint names, t [s] array, positions
    array (points, joints) [m]) without building a Python object per point: when every
    point has the same layout (positions only, or the same array lengths, as planners
    send), the points are strided views of the buffer. The layout is proved, not
    guessed: every point's four counts are read (strided too) and must equal the first
    point's. Returns None for a layout this does not cover (the caller then
    deserializes the ordinary way). More than ``max_points`` points: DataError before
    anything else is decoded.

    Alignment: point 0 may carry padding the others do not (it starts wherever the
    joint names ended); from point 1 on, the padding repeats every two points (a point's
    padding depends only on where it starts, modulo 8). So point 0 is read on its own
    and points 1, 3, 5... and 2, 4, 6... are two strided views."""
    import numpy as np
    r = CdrReader(data)
    r.stamp()
    r.string()                      # header.frame_id
    names = [r.string() for _ in range(r.count(5))]
    n = r.count(4 * 6)              # each point: 4 counts and a duration at least
    if max_points is not None and n > max_points:
        raise DataError(f"trajectory: {n} points, more than the {max_points} accepted "
                        "(max_trajectory_points)")

    def point():
        """One point: (offsets of its 4 counts, the counts, offset of its positions,
        offset of its time_from_start)."""
        counts, co, p_off = [], [], 0
        for j in range(4):          # positions, velocities, accelerations, effort
            r.pos += -(r.pos - 4) % 4
            co.append(r.pos)
            k = r.count(8)
            if k:  # (an empty sequence has no element to align)
                r.pos += -(r.pos - 4) % r.a8
            if j == 0:
                p_off = r.pos
            counts.append(k)
            r.pos += 8 * k
        r._take("iI", 8, 4)
        return co, counts, p_off, r.pos - 8
    if n == 0:
        return names, np.zeros(0), np.zeros((0, len(names)))
    first = [point()]
    ends = [r.pos]                  # where each point read one by one ends
    for _ in range(min(n, 3) - 1):
        first.append(point())
        ends.append(r.pos)
    if any(f[1] != first[0][1] for f in first):
        return None  # points with different array lengths
    k = first[0][1][0]
    if k != len(names):
        return None
    period = ends[2] - ends[0] if n > 2 else 0   # two points, from point 1 on
    m = {1: n // 2, 2: (n - 1) // 2}             # points 1, 3, 5... and 2, 4, 6...
    last = ends[0] + (m[2] * period if n > 2 else 0) + (
        (ends[1] - ends[0]) if n % 2 == 0 else 0)  # the end of point n - 1
    # (the serialized buffer may carry a few bytes past the message's end)
    if last > len(data):
        return None  # not one repeating layout: let the caller deserialize
    f8, i4, u4 = (np.dtype(r.end + c) for c in ("f8", "i4", "u4"))
    for par in (1, 2):  # every point's counts are the first point's: the layout holds
        if m[par] < 1 or par >= len(first):
            continue
        for j, off in enumerate(first[par][0]):
            c = np.ndarray((m[par],), u4, buffer=data, offset=off, strides=(period,))
            if np.any(c != first[0][1][j]):
                return None
    pos = np.zeros((n, k))
    t = np.zeros(n)
    for par, (_, _, p_off, d_off) in enumerate(first):
        cnt = 1 if par == 0 else m[par]
        step = period or 8
        rows = slice(0, 1) if par == 0 else slice(par, None, 2)
        if k:
            pos[rows] = np.ndarray((cnt, k), f8, buffer=data, offset=p_off,
                                   strides=(step, 8))
        sec = np.ndarray((cnt,), i4, buffer=data, offset=d_off, strides=(step,))
        nsec = np.ndarray((cnt,), u4, buffer=data, offset=d_off + 4, strides=(step,))
        t[rows] = sec + nsec * 1e-9
    return names, t, pos
