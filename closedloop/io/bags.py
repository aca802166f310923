"""Quasi-static samples from ROS bags of ``sensor_msgs/JointState`` (ROS 1, ROS 2 sqlite3 and MCAP).

The thesis's data are joint readings taken while the robot stands still with its
loop closed (ch. 3.5: "the manipulator is moved to a set of configurations ...
and the joint angles recorded").  A bag holds the whole stream, motion included;
this module finds the standstills and turns each into one log row.

Reading uses the pure-Python ``rosbags`` library (``pip install
".[ros]"`` in the checkout): no ROS installation.  ``AnyReader`` opens a ROS 1
``.bag`` file and a ROS 2 bag directory (``metadata.yaml`` with ``.db3`` or
``.mcap`` files) alike.

Standstill detection.  For every stamp ``t_k`` of the merged joint state
``q(t_k)`` (joints matched by name; messages that carry only some joints update
those), the speed is

    v_k = max_j |qdot_j(t_k)|                       (the message's velocities), or
    v_k = max_j |q_j(t_k + w/2) - q_j(t_k - w/2)| / w   (central difference over a
                                                     window w when velocities are absent)

A standstill is a maximal run of stamps with ``v_k < threshold`` lasting at least
``settle`` seconds, split where the position jumps by more than ``spread`` (two
poses a few milliradians apart are joined by a move slower than the threshold);
its sample is the mean of ``q`` over the run (the reading noise drops by
sqrt(messages)).  One sample per standstill, so the one-to-one match with the
commanded configurations holds as long as the robot never pauses for ``settle``
seconds while moving.

Several fixtures in one recording are told apart by topic (each JointState
topic is its own loop), by time windows (``name=t0:t1``, seconds from the start
of the bag) or by gaps (standstills more than ``gap`` seconds apart start a new
fixture: the recording paused while the fixture was moved).  The loop name goes
into the ``loop`` column of the CSV, which ``calibrate`` uses to assign rows.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from closedloop.errors import InputError, require
from closedloop.io.logs import JointLog

log = logging.getLogger(__name__)

JOINT_STATE_TYPES = ("sensor_msgs/msg/JointState", "sensor_msgs/JointState")
BAG_SUFFIXES = (".bag", ".mcap", ".db3")


class BagError(InputError):
    """A bag cannot be read or holds no usable joint states."""


@dataclass
class ExtractOptions:
    """How standstills are found and grouped.

    Attributes:
        threshold: speed below which the robot stands still [rad/s or m/s].
        settle: shortest standstill kept [s].
        window: finite-difference window when the messages carry no velocities [s].
        topics: JointState topics to read (None: all of them).
        split: ``None`` (one loop), ``"topic"``, ``"gap"`` or ``"window"``.
        gap: with ``split="gap"``: a new fixture after this many seconds between standstills.
        windows: with ``split="window"``: loop name -> (t0, t1) seconds from the bag start.
        names: loop names for ``split="topic"`` (topic -> name) or ``"gap"`` (in order).
        trim: fraction of each standstill dropped at both ends before averaging.
        spread: a standstill splits where the position jumps by more than this [rad or m].
    """

    threshold: float = 0.01
    settle: float = 0.5
    window: float = 0.2
    topics: list[str] | None = None
    split: str | None = None
    gap: float = 5.0
    windows: dict[str, tuple[float, float]] = field(default_factory=dict)
    names: dict[str, str] | list[str] | None = None
    trim: float = 0.1
    spread: float = 1e-3


@dataclass
class Stream:
    """Merged joint states of one topic: times [s from bag start], positions and speeds."""

    topic: str
    t: np.ndarray  # (M,)
    q: np.ndarray  # (M, n_joints)
    qd: np.ndarray | None  # (M, n_joints) when every message had velocities


@dataclass
class Standstill:
    """One quasi-static sample: mean reading over a standstill."""

    topic: str
    t0: float
    t1: float
    q: np.ndarray
    n: int
    loop: str | None = None


def is_bag(path: str | Path) -> bool:
    """A ROS 1 ``.bag``, a ROS 2 bag directory (``metadata.yaml``) or a bare ``.mcap``/``.db3``."""
    p = Path(path)
    return (p.is_dir() and (p / "metadata.yaml").is_file()) or p.suffix.lower() in BAG_SUFFIXES


def _reader(path: Path):
    require("rosbags", f"{path}: reading a ROS bag", "ros")
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    if not path.exists():
        raise BagError(f"{path}: no such bag")
    if not is_bag(path):
        raise BagError(
            f"{path}: not a ROS bag (a ROS 1 .bag, a ROS 2 bag folder with its metadata.yaml, or a "
            f".mcap/.db3 file){'; a CSV log goes straight to calibrate' if path.suffix.lower() == '.csv' else ''}"
        )
    from closedloop.io.files import note_input

    for f in [path] if path.is_file() else path.iterdir():
        note_input(f)
    if path.is_file() and path.suffix.lower() in (".mcap", ".db3") and (path.parent / "metadata.yaml").is_file():
        path = path.parent  # a ROS 2 bag is its directory
    return AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))


def read_streams(path: str | Path, joints: list[str], topics: list[str] | None = None) -> list[Stream]:
    """Joint states of ``joints`` (matched by name) per JointState topic of the bag."""
    path = Path(path)
    reader = _reader(path)
    try:
        reader.open()
    except Exception as exc:  # rosbags raises its own errors for unreadable bags
        raise BagError(f"{path}: not a readable ROS bag ({str(exc).splitlines()[0] if str(exc) else exc})") from None
    try:
        conns = [
            c for c in reader.connections if c.msgtype in JOINT_STATE_TYPES and (topics is None or c.topic in topics)
        ]
        if not conns:
            found = sorted({f"{c.topic} ({c.msgtype})" for c in reader.connections})
            want = f" on topic(s) {', '.join(topics)}" if topics else ""
            raise BagError(f"{path}: no sensor_msgs/JointState messages{want} (topics: {', '.join(found) or 'none'})")
        start = reader.start_time
        by_topic: dict[str, list] = {}
        messages = reader.messages(connections=conns)
        last: bytes | None = None  # the last message read whole: a damaged stretch starts after it
        while True:
            try:
                conn, stamp, raw = next(messages)
            except StopIteration:
                break
            except Exception as exc:  # the container itself (chunk, record or index) is damaged
                raise BagError(f"{_damaged_at(path, last, None)} ({_first_line(exc)})") from None
            try:
                msg = reader.deserialize(raw, conn.msgtype)
                hs = msg.header.stamp
                t_ns = int(hs.sec) * 1_000_000_000 + int(hs.nanosec) if (hs.sec or hs.nanosec) else int(stamp)
                item = (t_ns, list(msg.name), np.asarray(msg.position, float), np.asarray(msg.velocity, float))
            except Exception as exc:  # a message whose bytes do not decode
                raise BagError(f"{_damaged_at(path, last, bytes(raw))} ({_first_line(exc)})") from None
            by_topic.setdefault(conn.topic, []).append(item)
            last = bytes(raw)
        t_ref = min(min(m[0] for m in v) for v in by_topic.values()) if by_topic else start
    finally:
        reader.close()
    merged = [_merge(path, topic, msgs, joints, t_ref) for topic, msgs in sorted(by_topic.items())]
    streams = [s for s in merged if s is not None]
    if not streams and by_topic:  # a misspelt --joints, or the model of another robot: say what the bag has
        held = sorted({n for msgs in by_topic.values() for _, names, _, _ in msgs for n in names})
        raise BagError(
            f"{path}: no JointState topic reports any of the joint(s) asked ({_some(joints)}); the bag's "
            f"joints: {_some(held)}"
        )
    return streams


def _some(names: list[str], n: int = 6) -> str:
    """The first `n` of `names`, and how many more, for a one-line message."""
    return ", ".join(names[:n]) + (f" and {len(names) - n} more" if len(names) > n else "")


def _first_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text[:200]


def _storage_files(path: Path) -> list[Path]:
    """The files holding a bag's bytes: the file itself, or a ROS 2 bag folder's .mcap/.db3 files."""
    if path.is_file():
        return [path]
    return sorted(p for p in path.iterdir() if p.suffix.lower() in (".mcap", ".db3")) if path.is_dir() else []


def _damaged_at(path: Path, last: bytes | None, bad: bytes | None) -> str:
    """``FILE: damaged at byte N`` -- where the undecodable message `bad` starts, else just after the last
    message read whole (`last`), found in the file (uncompressed chunks hold messages verbatim)."""
    import mmap

    for f in _storage_files(path):
        try:
            with f.open("rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as mm:
                if bad is not None and len(bad) >= 16:
                    k = mm.find(bad)
                    if k >= 0:
                        return f"{f}: damaged message at byte {k} of {len(mm)}"
                if last is not None and len(last) >= 16:
                    k = mm.find(last)
                    if k >= 0:
                        return f"{f}: damaged after byte {k + len(last)} of {len(mm)} (the last message read whole)"
                at = _mcap_damage(mm) if f.suffix.lower() == ".mcap" else None
                if at is not None:
                    return f"{f}: damaged record at byte {at} of {len(mm)}"
                if last is None:
                    return f"{f}: damaged before its first message could be read (the file is {len(mm)} bytes)"
        except (OSError, ValueError):
            continue
    return f"{path}: damaged (compressed chunks: the byte offset cannot be told)"


def _mcap_damage(mm) -> int | None:
    """Offset of the first MCAP record that cannot be right (a length past its container, an opcode MCAP
    does not define, a chunk whose CRC fails, or a record inside an uncompressed chunk that is so), or None.
    Layout: magic, then records ``opcode:u8 length:u64 content``; a chunk (0x06) holds ``start:u64 end:u64
    size:u64 crc:u32 compression:str records:bytes`` (MCAP specification)."""
    import struct
    import zlib

    def walk(start: int, stop: int, top: bool) -> int | None:
        k = start
        while k < stop:
            if k + 9 > stop:
                return k
            op, n = mm[k], struct.unpack_from("<Q", mm, k + 1)[0]
            if not 0x01 <= op <= 0x0F or k + 9 + n > stop:
                return k
            if op == 0x06 and top:  # a chunk: check its CRC, walk its records when uncompressed
                c = k + 9
                size, crc = struct.unpack_from("<QI", mm, c + 16)
                clen = struct.unpack_from("<I", mm, c + 28)[0]
                if c + 32 + clen + 8 > k + 9 + n:
                    return k
                compression = bytes(mm[c + 32 : c + 32 + clen])
                rlen = struct.unpack_from("<Q", mm, c + 32 + clen)[0]
                r0 = c + 32 + clen + 8
                if r0 + rlen > k + 9 + n:
                    return k
                if not compression:
                    if crc and zlib.crc32(mm[r0 : r0 + rlen]) != crc:
                        inner = walk(r0, r0 + rlen, False)
                        return inner if inner is not None else k
                    inner = walk(r0, r0 + rlen, False)
                    if inner is not None:
                        return inner
            if op == 0x0F:  # the footer: the end
                return None
            k += 9 + n
        return None

    if bytes(mm[:8]) != b"\x89MCAP0\r\n":
        return 0
    try:
        return walk(8, len(mm) - 8, True)
    except struct.error:
        return None


def _merge(path: Path, topic: str, msgs: list, joints: list[str], t_ref: int) -> Stream | None:
    """Carry every joint's last value forward; keep stamps once all joints have been seen."""
    msgs.sort(key=lambda m: m[0])
    idx = {j: k for k, j in enumerate(joints)}
    seen = {n for _, names, _, _ in msgs for n in names}
    if not seen & set(joints):
        log.info("%s: topic %s has none of the model's joints; skipped", path, topic)
        return None
    missing = [j for j in joints if j not in seen]
    if missing:
        raise BagError(
            f"{path}: topic {topic} never reports joint(s) {', '.join(missing)} (it has: {', '.join(sorted(seen)[:8])})"
        )
    # every message's cells placed in a table of messages x joints, its joints flagged as set there; each
    # joint then carries its last set value forward (a value set to nan included), at once
    counts = np.array([len(names) for _, names, _, _ in msgs])
    for (t_ns, names, pos, _), n in zip(msgs, counts):
        if len(pos) != n:
            raise BagError(
                f"{path}: topic {topic}: a message at t={(t_ns - t_ref) / 1e9:.3f} s has "
                f"{n} names and {len(pos)} positions"
            )
    columns: dict[tuple, np.ndarray] = {}  # a message's joint names -> their columns (-1: not a joint of ours)
    cols = np.concatenate([_columns(columns, names, idx) for _, names, _, _ in msgs])
    rows = np.repeat(np.arange(len(msgs)), counts)
    ours = cols >= 0
    rows, cols = rows[ours], cols[ours]
    pos = np.concatenate([p for _, _, p, _ in msgs])[ours]
    vel = np.concatenate([v if len(v) == n else np.full(n, np.nan) for (_, _, _, v), n in zip(msgs, counts)])[ours]
    last = np.full((len(msgs), len(joints)), -1)
    last[rows, cols] = rows
    last = np.maximum.accumulate(last, axis=0)  # the message that last set each joint
    q_set = np.full((len(msgs), len(joints)), np.nan)
    v_set = np.full((len(msgs), len(joints)), np.nan)
    q_set[rows, cols], v_set[rows, cols] = pos, vel
    take = np.maximum(last, 0), np.arange(len(joints))
    q = np.where(last >= 0, q_set[take], np.nan)
    v = np.where(last >= 0, v_set[take], np.nan)
    keep = np.all(np.isfinite(q), axis=1)  # once every joint has a value
    if not keep.any():
        return Stream(topic, np.array([]), np.array([]), np.array([]))
    stamps = np.array([t_ns for t_ns, _, _, _ in msgs], dtype=np.int64)[keep]
    t, q, v = (stamps - t_ref) / 1e9, q[keep], v[keep]
    return Stream(topic, t, q, v if np.all(np.isfinite(v)) else None)


def _columns(known: dict[tuple, np.ndarray], names: list[str], idx: dict[str, int]) -> np.ndarray:
    """The columns of a message's joint `names` (-1 for a joint not asked for), found once per order of
    names (`known`)."""
    key = tuple(names)
    found = known.get(key)
    if found is None:
        found = known[key] = np.array([idx.get(n, -1) for n in names], dtype=int)
    return found


def speeds(stream: Stream, window: float) -> np.ndarray:
    """``max_j |qdot_j|`` per stamp: the message velocities, else a central difference over ``window``."""
    if stream.qd is not None:
        return np.abs(stream.qd).max(axis=1)
    t, q = stream.t, stream.q
    lo = np.searchsorted(t, t - window / 2.0, side="left")
    hi = np.clip(np.searchsorted(t, t + window / 2.0, side="right") - 1, 0, len(t) - 1)
    dt = t[hi] - t[lo]
    with np.errstate(invalid="ignore", divide="ignore"):
        v = np.abs(q[hi] - q[lo]).max(axis=1) / dt
    return np.where(dt > 0, v, np.inf)


def _plateaus(q: np.ndarray, spread: float) -> list[tuple[int, int]]:
    """Split a still run where the position leaves the current plateau by more than ``spread``.

    Two poses a few milliradians apart are joined by a move too slow to exceed the speed threshold;
    the jump between them still shows in the positions: a segment ends when three consecutive
    samples lie more than ``spread`` (max over joints) from the mean of the segment so far.
    """
    out, start, total, n_out = [], 0, q[0].copy(), 0
    for k in range(1, len(q)):
        ref = total / (k - start)
        if np.abs(q[k] - ref).max() > spread:
            n_out += 1
            if n_out >= 3:
                out.append((start, k - 2))
                start, total, n_out = k - 2, q[k - 2 : k + 1].sum(axis=0), 0
                continue
        else:
            n_out = 0
        total += q[k]
    out.append((start, len(q)))
    return out


def standstills(stream: Stream, opts: ExtractOptions) -> list[Standstill]:
    """Runs of ``speed < threshold`` lasting ``settle`` seconds, split at position jumps larger than
    ``spread``, one mean sample each (module doc); samples farther from the run's median than five
    times the reading noise (its MAD, at most ``spread / 4``: the ends of a move) are left out."""
    if len(stream.t) == 0:
        return []
    still = speeds(stream, opts.window) < opts.threshold
    edges = np.diff(np.concatenate([[0], still.astype(int), [0]]))
    runs = zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1))  # run = [start, stop)
    out = []
    for a0, b0 in runs:
        for da, db in _plateaus(stream.q[a0:b0], opts.spread):
            a, b = a0 + da, a0 + db
            t0, t1 = stream.t[a], stream.t[b - 1]
            if t1 - t0 < opts.settle:
                continue
            cut = int(opts.trim * (b - a))
            q = stream.q[a + cut : b - cut] if b - a - 2 * cut > 0 else stream.q[a:b]
            dev = np.abs(q - np.median(q, axis=0))
            sig = 1.4826 * np.median(dev, axis=0)  # robust noise level per joint (MAD)
            keep = np.all(dev <= np.minimum(5.0 * sig + 1e-12, opts.spread / 4), axis=1)
            out.append(Standstill(stream.topic, float(t0), float(t1), q[keep].mean(axis=0), int(keep.sum())))
    return out


def _label(samples: list[Standstill], opts: ExtractOptions, path: Path) -> None:
    """Assign loop names: by topic, window or gap (module doc); None when not split."""
    names = opts.names
    if opts.split is None:
        return
    if opts.split == "topic":
        mapping = names if isinstance(names, dict) else {}
        for s in samples:
            s.loop = mapping.get(s.topic) or re.sub(r"[^A-Za-z0-9_]+", "_", s.topic).strip("_") or "loop"
    elif opts.split == "window":
        if not opts.windows:
            raise BagError(f"{path}: split by window needs windows name=t0:t1")
        for s in samples:
            mid = 0.5 * (s.t0 + s.t1)
            hit = [n for n, (a, b) in opts.windows.items() if a <= mid <= b]
            s.loop = hit[0] if hit else None
    elif opts.split == "gap":
        seq = list(names) if isinstance(names, list) else []
        k = 0
        for i, s in enumerate(samples):
            if i and s.t0 - samples[i - 1].t1 > opts.gap:
                k += 1
            s.loop = seq[k] if k < len(seq) else f"fixture{k + 1}"
    else:
        raise BagError(f"{path}: unknown split '{opts.split}' (use topic, window or gap)")


def extract(
    path: str | Path, joints: list[str], opts: ExtractOptions | None = None
) -> tuple[JointLog, list[Standstill]]:
    """The quasi-static samples of a bag as a :class:`JointLog` (plus the standstills found).

    Extra columns: ``t_start``, ``t_end`` (seconds from the bag start) and
    ``messages`` per sample; a ``loop`` column when the samples are split.
    """
    opts = opts or ExtractOptions()
    path = Path(path)
    streams = read_streams(path, joints, opts.topics)
    if not streams:
        raise BagError(f"{path}: no JointState topic reports the model's joints ({', '.join(joints[:6])} ...)")
    samples = [s for st in streams for s in standstills(st, opts)]
    samples.sort(key=lambda s: s.t0)
    _label(samples, opts, path)
    if opts.split == "window":
        samples = [s for s in samples if s.loop is not None]
    if not samples:
        raise BagError(
            f"{path}: no standstill of at least {opts.settle} s below {opts.threshold} rad/s "
            f"(try a larger --threshold or a shorter --settle)"
        )
    log.info("%s: %d standstills from %d topic(s)", path, len(samples), len(streams))
    extra = {
        "t_start": np.array([s.t0 for s in samples]),
        "t_end": np.array([s.t1 for s in samples]),
        "messages": np.array([float(s.n) for s in samples]),
    }
    loop = np.array([s.loop for s in samples]) if opts.split else None
    return JointLog(list(joints), np.array([s.q for s in samples]), path, loop, extra), samples


def parse_windows(items: list[str]) -> dict[str, tuple[float, float]]:
    """``name=t0:t1`` items (seconds from the bag start)."""
    out = {}
    for item in items:
        name, eq, rng = item.partition("=")
        a, colon, b = rng.partition(":")
        try:
            if not eq or not colon:
                raise ValueError
            out[name.strip()] = (float(a), float(b))
        except ValueError:
            raise InputError(f"--window {item}: expected NAME=T0:T1 (seconds from the bag start)") from None
        t0, t1 = out[name.strip()]
        if not (np.isfinite(t0) and np.isfinite(t1) and 0.0 <= t0 < t1):
            raise InputError(f"--window {item}: T0 must be >= 0 and below T1 (seconds from the bag start)")
    return out
