"""Data in and out, segmentation into cycles and alignment (thesis 9.5.1).

A record is a sampled time series: `time` (s), `angle` (rad), `torque` (N m, the measured external
torque, positive in the direction of increasing angle), optionally `command` (N m, the commanded
perturbation, used as instrument), `event` (non-zero at cycle onsets) and `block` (integer id of
independent continuous recordings; segments never cross a block boundary).  CSV has those column names
in a header row; HDF5 has datasets of the same names (attribute `units` on each).

Cycles are cut at onsets (from events, from a list of onset times, or from peak velocity), each with a
`pad` of neighbouring samples on both sides (needed by the lags and by the zero-phase pre-filter),
aligned (none, peak velocity, then optional RMS re-alignment within a maximum shift), and the ensemble
mean th_0(t), tau_0(t) removed (eq. 7.9).  `recut` cuts an ensemble's cycles again at moved onsets (the
model-based re-alignment of `impedance.timing`).
"""

from __future__ import annotations

import csv
import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from closedloop.errors import InputError, require

log = logging.getLogger(__name__)
UNITS = {"time": "s", "angle": "rad", "torque": "N m", "command": "N m", "event": "1", "block": "1"}


class ImpedanceDataError(InputError):
    """An impedance data file or segmentation request is wrong."""


@dataclass
class Record:
    """A continuous recording (or several independent blocks of one).

    `valid` marks the rows whose angle, torque (and command) are finite: cycles touching an invalid row
    are left out by `segment`.  `notes` says what reading the file changed or ignored."""

    time: np.ndarray
    angle: np.ndarray
    torque: np.ndarray
    command: np.ndarray | None = None
    event: np.ndarray | None = None
    block: np.ndarray | None = None
    valid: np.ndarray | None = None
    notes: list[str] = field(default_factory=list)

    @property
    def fs(self) -> float:
        """Sampling rate (Hz): samples per second over each block (time rounded in a file averages out)."""
        b = self.block if self.block is not None else np.zeros(len(self.time), int)
        edges = np.flatnonzero(np.r_[True, np.diff(b) != 0, True])
        steps = spans = 0.0
        for i, j in zip(edges[:-1], edges[1:]):
            if j - i > 1:
                steps += j - i - 1
                spans += self.time[j - 1] - self.time[i]
        return float(steps / spans)

    def columns(self) -> dict[str, np.ndarray]:
        return {
            k: v
            for k, v in (
                ("time", self.time),
                ("angle", self.angle),
                ("torque", self.torque),
                ("command", self.command),
                ("event", self.event),
                ("block", self.block),
            )
            if v is not None
        }


def record_bytes(rec: Record, fmt: str = "csv") -> bytes:
    """The record as the bytes of a CSV file (header of column names) or an HDF5 file (one dataset per
    column, attribute `units`)."""
    cols = rec.columns()
    if fmt in ("h5", "hdf5", ".h5", ".hdf5"):
        import io

        h5py = require("h5py", "an HDF5 record", "impedance")
        buf = io.BytesIO()
        with h5py.File(buf, "w") as f:
            for k, v in cols.items():
                f.create_dataset(k, data=v).attrs["units"] = UNITS[k]
        return buf.getvalue()
    import io

    fmts = {"time": "%.6f", "event": "%d", "block": "%d"}
    arr = np.column_stack([cols[k] for k in cols])
    text = io.StringIO()
    np.savetxt(text, arr, delimiter=",", header=",".join(cols), comments="", fmt=[fmts.get(k, "%.9g") for k in cols])
    return text.getvalue().encode()


def write_record(path: str | Path, rec: Record) -> None:
    """CSV (header of column names) or HDF5 (.h5/.hdf5), written whole (`closedloop.io.files`)."""
    from closedloop.io.files import atomic_write_text

    path = Path(path)
    atomic_write_text(path, record_bytes(rec, path.suffix.lower()))


def parse_columns(text: str | None) -> dict[str, str]:
    """``--columns torque=tau,command=perturbation``: our column name -> the file's column name."""
    if not text:
        return {}
    out = {}
    for part in text.split(","):
        k, eq, v = (t.strip() for t in part.partition("="))
        if not eq or not v:
            raise ImpedanceDataError(f"--columns {part}: expected NAME=COLUMN (e.g. torque=tau)")
        if k.lower() not in UNITS:
            raise ImpedanceDataError(f"--columns {part}: '{k}' is not one of {', '.join(UNITS)}")
        out[k.lower()] = v.lower()
    return out


def is_hdf5(path: str | Path) -> bool:
    """HDF5 by its signature (a CSV named .h5 is read as the CSV it is)."""
    try:
        with open(path, "rb") as fh:
            return fh.read(8) == b"\x89HDF\r\n\x1a\n"
    except OSError:
        return False


def read_record(path: str | Path, columns: dict[str, str] | None = None, torque_sign: float = 1.0) -> Record:
    """Read a CSV or HDF5 record and check it before any estimation.

    `columns` maps our names (time, angle, torque, command, event, block) to the file's; columns that map
    to none are reported in `Record.notes`.  Time must be finite and never repeat (the row is named); a
    step back in time or a gap (more than 1.5 sampling intervals) starts a new block, so no cycle is cut
    across it; rows with a non-finite angle, torque or command are kept but marked invalid (the cycles
    that touch them are left out by `segment`).  `torque_sign` -1 flips a torque recorded with the opposite
    sign."""
    path = Path(path)
    if not path.is_file():
        raise ImpedanceDataError(f"{path}: no such file")
    rename = {v: k for k, v in (columns or {}).items()}
    if is_hdf5(path):
        h5py = require("h5py", f"{path} (an HDF5 record)", "impedance")
        try:
            with h5py.File(path, "r") as f:
                raw = {k.lower(): f[k] for k in f.keys() if isinstance(f[k], h5py.Dataset)}
                raw = {k: np.asarray(v[()], float).ravel() for k, v in raw.items() if v.ndim <= 1}
        except (OSError, ValueError, TypeError) as exc:
            raise ImpedanceDataError(f"{path}: not a readable HDF5 record ({exc})") from None
        lens = {len(v) for v in raw.values()}
        if len(lens) > 1:
            raise ImpedanceDataError(f"{path}: datasets of different lengths {sorted(lens)}")
        header = list(raw)
    else:
        try:
            with open(path, newline="") as fh:
                header = [h.strip().lower() for h in next(csv.reader(fh), [])]
        except UnicodeDecodeError:
            raise ImpedanceDataError(f"{path}: not a text CSV (nor an HDF5 file)") from None
        if not header:
            raise ImpedanceDataError(f"{path}: empty file")
        try:
            arr = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
        except ValueError as exc:  # numpy names the data row from 0 and the column from 1: the file's line, the name
            hit = re.search(r"string '(.*)' to \w+ at row (\d+), column (\d+)", str(exc))
            if hit and 0 < int(hit.group(3)) <= len(header):
                line, name = int(hit.group(2)) + 2, header[int(hit.group(3)) - 1]
                raise ImpedanceDataError(
                    f"{path} line {line}, column '{name}': '{hit.group(1)}' is not a number"
                ) from None
            raise ImpedanceDataError(f"{path}: not a numeric CSV ({exc})") from None
        if arr.shape[1] != len(header):
            raise ImpedanceDataError(f"{path}: {len(header)} header columns but {arr.shape[1]} data columns")
        raw = {h: arr[:, i] for i, h in enumerate(header)}
    for ours, theirs in (columns or {}).items():
        if theirs not in raw:
            raise ImpedanceDataError(
                f"{path}: --columns {ours}={theirs}: no column '{theirs}' (have {', '.join(header)})"
            )
    cols: dict[str, np.ndarray] = {}
    unknown = []
    for h in header:
        name = rename[h] if h in rename else (None if h in (columns or {}) else h)
        if name in UNITS and name not in cols:
            cols[name] = raw[h]
        else:
            unknown.append(h)
    for k in ("time", "angle", "torque"):
        if k not in cols:
            raise ImpedanceDataError(
                f"{path}: missing column '{k}' (need time, angle, torque; map yours with --columns {k}=NAME)"
            )
    notes = []
    if unknown:
        notes.append(f"{path.name}: ignored columns {', '.join(unknown)} (map them with --columns NAME=COLUMN)")
    t = cols["time"]
    n = len(t)
    if n < 10:
        raise ImpedanceDataError(f"{path}: {n} rows; a record needs at least 10")
    bad_t = np.flatnonzero(~np.isfinite(t))
    if bad_t.size:
        raise ImpedanceDataError(f"{path}: column 'time' row {bad_t[0] + 2} is not finite")
    for k in ("event", "block"):
        if k in cols:
            bad = np.flatnonzero(~np.isfinite(cols[k]))
            if bad.size:
                raise ImpedanceDataError(f"{path}: column '{k}' row {bad[0] + 2} is not finite")
    valid = np.ones(n, bool)
    for k in ("angle", "torque", "command"):
        if k in cols:
            valid &= np.isfinite(cols[k])
    if not valid.all():
        bad = np.flatnonzero(~valid)
        notes.append(
            f"{path.name}: {bad.size} rows with a non-finite angle, torque or command (first at row "
            f"{bad[0] + 2}): the cycles they touch are left out"
        )
    block = cols["block"].astype(int) if "block" in cols else np.zeros(n, int)
    dt = np.diff(t)
    same = np.diff(block) == 0
    dup = np.flatnonzero(same & (dt == 0))
    if dup.size:
        raise ImpedanceDataError(f"{path}: row {dup[0] + 3} repeats the time {t[dup[0] + 1]:g} s of the row before")
    step = float(np.median(dt[same & (dt > 0)])) if np.any(same & (dt > 0)) else 0.0
    if step <= 0:
        raise ImpedanceDataError(f"{path}: time must increase")
    back = same & (dt < 0)
    gap = same & (dt > 1.5 * step)
    if back.any() or gap.any():
        parts = []
        if gap.any():
            g = np.flatnonzero(gap)
            parts.append(f"{g.size} gaps in time (largest {dt[g].max():.3g} s, first after row {g[0] + 2})")
        if back.any():
            parts.append(f"{int(back.sum())} steps back in time (first at row {np.flatnonzero(back)[0] + 3})")
        notes.append(f"{path.name}: {' and '.join(parts)}: the record is split there; no cycle crosses them")
    brk = np.r_[False, ~same | back | gap]
    blocks = None if "block" not in cols and not brk.any() else np.cumsum(brk)  # none given, none found
    sign = float(torque_sign)
    event = cols.get("event")
    return Record(
        t,
        cols["angle"],
        sign * cols["torque"],
        None if "command" not in cols else cols["command"],
        event,
        blocks,
        None if valid.all() else valid,
        notes,
    )


@dataclass
class AlignmentReport:
    """Shifts applied to each kept cycle (samples) and their diagnostics."""

    method: str
    shifts: np.ndarray
    fs: float
    max_shift: int
    warnings: list[str] = field(default_factory=list)

    def histogram(self) -> dict[str, list]:
        ms = self.shifts / self.fs * 1e3
        edges = np.arange(np.floor(ms.min()) - 0.5, np.ceil(ms.max()) + 1.5, max(1.0, 1e3 / self.fs))
        cnt, edges = np.histogram(ms, bins=edges)
        return {"edges_ms": edges.round(3).tolist(), "counts": cnt.tolist()}

    def summary(self) -> dict:
        ms = self.shifts / self.fs * 1e3
        return {
            "method": self.method,
            "mean_ms": float(ms.mean()),
            "std_ms": float(ms.std()),
            "max_abs_ms": float(np.abs(ms).max()),
            "at_limit": int(np.sum(np.abs(self.shifts) >= self.max_shift)) if self.max_shift else 0,
            "histogram": self.histogram(),
            "warnings": self.warnings,
        }


@dataclass
class Ensemble:
    """Aligned cycles with `pad` samples on each side: raw (n, L + 2 pad) arrays and their means."""

    fs: float
    pad: int
    length: int
    angle: np.ndarray
    torque: np.ndarray
    command: np.ndarray | None
    onsets: np.ndarray  # (n, 2): block, sample index of the (aligned) onset
    alignment: AlignmentReport | None = None
    excluded: dict[str, int] = field(default_factory=dict)

    @property
    def n(self) -> int:
        return self.angle.shape[0]

    @property
    def t(self) -> np.ndarray:
        """Time within the cycle of the core samples (s)."""
        return np.arange(self.length) / self.fs

    def mean(self) -> tuple[np.ndarray, np.ndarray]:
        return self.angle.mean(0), self.torque.mean(0)

    def deltas(self, ref: "Ensemble | None" = None):
        """Perturbations about the ensemble mean (of `ref`, default self): dth, dtau, dcommand."""
        ref = ref or self
        du = None
        if self.command is not None:
            assert ref.command is not None  # an ensemble with a command is compared with one cut from the same record
            du = self.command - ref.command.mean(0)
        return self.angle - ref.angle.mean(0), self.torque - ref.torque.mean(0), du

    def subset(self, idx: np.ndarray) -> "Ensemble":
        c = None if self.command is None else self.command[idx]
        return Ensemble(
            self.fs,
            self.pad,
            self.length,
            self.angle[idx],
            self.torque[idx],
            c,
            self.onsets[idx],
            self.alignment,
            dict(self.excluded),
        )


def _blocks(rec: Record) -> list[tuple[int, np.ndarray]]:
    b = rec.block if rec.block is not None else np.zeros(len(rec.time), int)
    return [(int(v), np.flatnonzero(b == v)) for v in np.unique(b)]


def onsets_from_events(rec: Record) -> list[tuple[int, int]]:
    """Rising edges of the event channel: (block, sample index within the block)."""
    if rec.event is None:
        raise ImpedanceDataError("segmentation by events needs an 'event' column")
    out = []
    for b, idx in _blocks(rec):
        e = rec.event[idx] != 0
        out += [(b, int(i)) for i in np.flatnonzero(e & ~np.r_[False, e[:-1]])]
    return out


def onsets_from_times(rec: Record, times: np.ndarray) -> list[tuple[int, int]]:
    """Onsets at the given times (s): the sample nearest to each, in its block."""
    out = []
    for b, idx in _blocks(rec):
        t = rec.time[idx]
        for tt in np.asarray(times, float):
            if t[0] <= tt <= t[-1]:
                out.append((b, int(np.argmin(np.abs(t - tt)))))
    return out


def _smooth_velocity(x: np.ndarray, fs: float, cutoff: float = 10.0) -> np.ndarray:
    from closedloop.impedance.filters import filtfilt

    return np.gradient(filtfilt(x, 2, cutoff, fs), 1.0 / fs, axis=-1)


def onsets_from_peak_velocity(rec: Record, period: float, lead: float | None = None) -> list[tuple[int, int]]:
    """Onsets `lead` s (default period/4) before each peak of positive velocity (3 Hz-smoothed, peaks
    at least 0.6 period apart, refined to the centroid of the velocity above 90 % of the peak).

    With strong perturbations the responses move the velocity peak by tens of ms (and any per-cycle
    alignment by ~8 ms in the thesis's simulation), which spoils the mean removal: prefer an event
    channel (the pacing clicks, thesis 9.1) when there is one."""
    from closedloop.impedance.filters import find_peaks

    fs, lead = rec.fs, period / 4 if lead is None else lead
    out = []
    for b, idx in _blocks(rec):
        a = rec.angle[idx]
        ok = np.isfinite(a)
        if not ok.all():  # invalid rows: bridged for the onsets only (their cycles are left out later)
            a = np.interp(np.arange(a.size), np.flatnonzero(ok), a[ok]) if ok.sum() > 1 else np.zeros_like(a)
        v = _smooth_velocity(a, fs, 3.0)
        pk = find_peaks(v, height=0.3 * np.max(v), distance=max(1, int(0.6 * period * fs)))
        h = int(0.25 * period * fs)
        for p in pk:
            seg = v[max(p - h, 0) : p + h]
            w = np.clip(seg - 0.9 * v[p], 0, None)
            c = max(p - h, 0) + (w * np.arange(len(seg))).sum() / w.sum()
            out.append((b, int(round(c - lead * fs))))
    return out


def segment(
    rec: Record,
    onsets: list[tuple[int, int]],
    period: float | None = None,
    pad_s: float = 0.35,
    max_shift_s: float = 0.05,
    length_tol: float = 0.2,
    align: str = "none",
    rms_iterations: int = 1,
) -> Ensemble:
    """Cut cycles of fixed length (median onset spacing, or `period`) with padding; exclusion rules:
    irregular spacing (outside +-length_tol of the length), incomplete padding, RMS outliers (> 5x the
    median RMS deviation from the mean).  Then align (`none`, `peak-velocity`, `rms`, `peak-velocity+rms`).
    """
    fs = rec.fs
    if not onsets:
        raise ImpedanceDataError("no cycle onsets found")
    by_block: dict[int, list[int]] = {}
    for b, i in onsets:
        by_block.setdefault(b, []).append(i)
    spacing = np.concatenate([np.diff(sorted(v)) for v in by_block.values()] + [np.zeros(0)])
    L = int(round(period * fs)) if period else int(np.median(spacing)) if spacing.size else 0
    if period and spacing.size >= 3 and abs(np.median(spacing) / fs - period) > length_tol * period:
        raise ImpedanceDataError(
            f"--period {period:g}: the onsets are {np.median(spacing) / fs:.4g} s apart (median of "
            f"{spacing.size}): most cycles would be left out as irregular (give that period, or leave it out)"
        )
    if L < 10:
        raise ImpedanceDataError("cannot infer the cycle length: give --period")
    S = int(round(max_shift_s * fs)) if align != "none" else 0
    P = int(round(pad_s * fs))
    blocks = dict(_blocks(rec))
    excluded = {"irregular length": 0, "incomplete padding": 0, "non-finite samples": 0, "outlier": 0}
    cand = []
    for b, starts in by_block.items():
        starts = sorted(starts)
        nb = len(blocks[b])
        bad = None if rec.valid is None else np.r_[0, np.cumsum(~rec.valid[blocks[b]])]
        for j, s in enumerate(starts):
            nxt = starts[j + 1] - s if j + 1 < len(starts) else None
            if nxt is not None and abs(nxt - L) > length_tol * L:
                excluded["irregular length"] += 1
            elif s - P - S < 0 or s + L + P + S > nb:
                excluded["incomplete padding"] += 1
            elif bad is not None and bad[s + L + P + S] - bad[s - P - S] > 0:
                excluded["non-finite samples"] += 1
            else:
                cand.append((b, s))
    if len(cand) < 3:
        why = ", ".join(f"{k} {v}" for k, v in excluded.items() if v) or "none"
        raise ImpedanceDataError(f"only {len(cand)} complete cycles; at least 3 are needed (left out: {why})")
    width = L + 2 * (P + S)

    def cut(sig, shifts):
        return np.stack([sig[blocks[b]][s - P - S + d : s - P - S + d + width] for (b, s), d in zip(cand, shifts)])

    shifts = np.zeros(len(cand), int)
    rep = AlignmentReport(align, shifts, fs, S)
    if align != "none":
        shifts = _align(cut(rec.angle, shifts), fs, P + S, L, S, align, rms_iterations, rep)
    core = slice(S, S + L + 2 * P)
    ang = cut(rec.angle, shifts)[:, core]
    dev = np.sqrt(np.mean((ang - ang.mean(0)) ** 2, axis=1))
    keep = dev <= 5 * np.median(dev)
    excluded["outlier"] = int(np.sum(~keep))
    torq = cut(rec.torque, shifts)[:, core][keep]
    cmd = None if rec.command is None else cut(rec.command, shifts)[:, core][keep]
    rep.shifts = shifts[keep]
    onset_arr = np.array([(b, s + d) for (b, s), d in zip(cand, shifts)])[keep]
    if any(excluded.values()):
        log.info("excluded cycles: %s", excluded)
    return Ensemble(fs, P, L, ang[keep], torq, cmd, onset_arr, rep, excluded)


def recut(rec: Record, ens: Ensemble, shifts: np.ndarray, method: str = "model") -> Ensemble:
    """The cycles of `ens` cut again from `rec` with their onsets moved by `shifts` (samples, one per cycle;
    positive: later), same length and padding, and the ensemble mean recomputed (eq. 7.9).  A cycle whose
    moved window would leave its block or touch an invalid row keeps its onset.  The alignment report
    records the total shift of each cycle from its original onset."""
    shifts = np.asarray(shifts, int)
    blocks = dict(_blocks(rec))
    P, L = ens.pad, ens.length
    width = L + 2 * P
    ang, torq, cmd, onsets, total = [], [], [], [], []
    prev = ens.alignment.shifts if ens.alignment is not None else np.zeros(ens.n, int)
    for k, ((b, s), d) in enumerate(zip(ens.onsets, shifts)):
        idx = blocks[int(b)]
        lo = s + d - P
        ok = lo >= 0 and lo + width <= idx.size
        if ok and rec.valid is not None:
            ok = bool(rec.valid[idx[lo : lo + width]].all())
        if not ok:
            lo, d = s - P, 0
        sl = idx[lo : lo + width]
        ang.append(rec.angle[sl])
        torq.append(rec.torque[sl])
        if rec.command is not None:
            cmd.append(rec.command[sl])
        onsets.append((b, s + d))
        total.append(prev[k] + d)
    max_shift = ens.alignment.max_shift if ens.alignment is not None else 0
    rep = AlignmentReport(method, np.asarray(total, int), ens.fs, max_shift)
    return Ensemble(
        ens.fs,
        P,
        L,
        np.stack(ang),
        np.stack(torq),
        np.stack(cmd) if cmd else None,
        np.asarray(onsets, int),
        rep,
        dict(ens.excluded),
    )


def _align(
    ang: np.ndarray, fs: float, off: int, L: int, S: int, method: str, iters: int, rep: AlignmentReport
) -> np.ndarray:
    """Shifts (samples, |shift| <= S) by peak velocity and/or RMS re-alignment to the mean (9.5.1)."""
    n = ang.shape[0]
    shifts = np.zeros(n, int)
    if "peak" in method:  # centroid of the 3 Hz-smoothed velocity above 90 % of its peak (sub-sample)
        v = _smooth_velocity(ang, fs, 3.0)[:, off : off + L]
        w = np.clip(v - 0.9 * v.max(axis=1, keepdims=True), 0, None)
        pk = (w * np.arange(L)).sum(1) / w.sum(1)
        shifts = np.clip(np.round(pk - np.median(pk)).astype(int), -S, S)
    if "rms" in method:
        cand = np.arange(-S, S + 1)
        for _ in range(max(1, iters)):
            seg = np.stack([ang[i, off + shifts[i] - S : off + shifts[i] + L + S] for i in range(n)])
            mean = np.mean(seg[:, S : S + L], axis=0)
            win = np.lib.stride_tricks.sliding_window_view(seg, L, axis=1)  # (n, 2S+1, L)
            rms = np.mean((win - mean) ** 2, axis=2)
            shifts = np.clip(shifts + cand[np.argmin(rms, axis=1)], -S, S)
    if method not in ("peak-velocity", "rms", "peak-velocity+rms"):
        raise ImpedanceDataError(f"alignment '{method}': expected none, peak-velocity, rms, peak-velocity+rms")
    ms = shifts / fs * 1e3
    rep.shifts = shifts
    if np.mean(np.abs(shifts) >= S) > 0.05:
        rep.warnings.append(
            f"{np.mean(np.abs(shifts) >= S):.0%} of the cycles hit the maximum shift "
            f"({S / fs * 1e3:.0f} ms): alignment is pulled by the perturbations"
        )
    if np.std(ms) > 5:
        rep.warnings.append(
            f"alignment shifts spread {np.std(ms):.1f} ms (std): perturbation responses pull "
            "peak-velocity and RMS alignment and invent shifts on periodic data; compare with "
            "--align none"
        )
    for w in rep.warnings:  # reported once, by the caller (the CLI prints the summary's warnings)
        log.debug(w)
    return shifts
