"""Data in and out, segmentation into cycles and alignment (thesis 9.5.1).

A record is a sampled time series: `time` (s), `angle` (rad), `torque` (N m, the measured external
torque, positive in the direction of increasing angle), optionally `command` (N m, the commanded
perturbation, used as instrument), `event` (non-zero at cycle onsets) and `block` (integer id of
independent continuous recordings; segments never cross a block boundary).  CSV has those column names
in a header row; HDF5 has datasets of the same names (attribute `units` on each).

Cycles are cut at onsets (from events, from a list of onset times, or from peak velocity), each with a
`pad` of neighbouring samples on both sides (needed by the lags and by the zero-phase pre-filter),
aligned (none, peak velocity, then optional RMS re-alignment within a maximum shift), and the ensemble
mean th_0(t), tau_0(t) removed (eq. 7.9).
"""

from __future__ import annotations

import csv
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.signal import butter, sosfiltfilt

from closedloop.errors import InputError

log = logging.getLogger(__name__)
UNITS = {"time": "s", "angle": "rad", "torque": "N m", "command": "N m", "event": "1", "block": "1"}


class ImpedanceDataError(InputError):
    """An impedance data file or segmentation request is wrong."""


@dataclass
class Record:
    """A continuous recording (or several independent blocks of one)."""

    time: np.ndarray
    angle: np.ndarray
    torque: np.ndarray
    command: np.ndarray | None = None
    event: np.ndarray | None = None
    block: np.ndarray | None = None

    @property
    def fs(self) -> float:
        d = np.diff(self.time[: min(len(self.time), 1000)])
        return float(1.0 / np.median(d))

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


def write_record(path: str | Path, rec: Record) -> None:
    """CSV (header of column names) or HDF5 (.h5/.hdf5, one dataset per column, units attribute)."""
    path = Path(path)
    cols = rec.columns()
    if path.suffix in (".h5", ".hdf5"):
        import h5py

        with h5py.File(path, "w") as f:
            for k, v in cols.items():
                f.create_dataset(k, data=v).attrs["units"] = UNITS[k]
        return
    fmt = {"time": "%.6f", "event": "%d", "block": "%d"}
    arr = np.column_stack([cols[k] for k in cols])
    np.savetxt(path, arr, delimiter=",", header=",".join(cols), comments="", fmt=[fmt.get(k, "%.9g") for k in cols])


def read_record(path: str | Path) -> Record:
    """Read a CSV or HDF5 record; missing required columns or NaNs raise `ImpedanceDataError`."""
    path = Path(path)
    if not path.is_file():
        raise ImpedanceDataError(f"{path}: no such file")
    if path.suffix in (".h5", ".hdf5"):
        import h5py

        with h5py.File(path, "r") as f:
            cols = {k: np.asarray(f[k][()], float) for k in UNITS if k in f}
    else:
        with open(path, newline="") as fh:
            header = [h.strip().lower() for h in next(csv.reader(fh), [])]
        try:
            arr = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
        except ValueError as exc:
            raise ImpedanceDataError(f"{path}: not a numeric CSV ({exc})") from None
        if arr.shape[1] != len(header):
            raise ImpedanceDataError(f"{path}: {len(header)} header columns but {arr.shape[1]} data columns")
        cols = {h: arr[:, i] for i, h in enumerate(header)}
    for k in ("time", "angle", "torque"):
        if k not in cols:
            raise ImpedanceDataError(f"{path}: missing column '{k}' (need time, angle, torque)")
    for k, v in cols.items():
        bad = np.flatnonzero(~np.isfinite(v))
        if bad.size:
            raise ImpedanceDataError(f"{path}: column '{k}' row {bad[0] + 1} is not finite")
    if len(cols["time"]) < 10 or np.any(np.diff(cols["time"]) <= 0) and "block" not in cols:
        raise ImpedanceDataError(f"{path}: time must increase and have at least 10 rows")
    return Record(
        cols["time"],
        cols["angle"],
        cols["torque"],
        cols.get("command"),
        cols.get("event"),
        cols["block"].astype(int) if "block" in cols else None,
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
        du = None if self.command is None else self.command - ref.command.mean(0)
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
    sos = butter(2, cutoff, fs=fs, output="sos")
    return np.gradient(sosfiltfilt(sos, x, axis=-1), 1.0 / fs, axis=-1)


def onsets_from_peak_velocity(rec: Record, period: float, lead: float | None = None) -> list[tuple[int, int]]:
    """Onsets `lead` s (default period/4) before each peak of positive velocity (3 Hz-smoothed, peaks
    at least 0.6 period apart, refined to the centroid of the velocity above 90 % of the peak).

    With strong perturbations the responses move the velocity peak by tens of ms (and any per-cycle
    alignment by ~8 ms in the thesis's simulation), which spoils the mean removal: prefer an event
    channel (the pacing clicks, thesis 9.1) when there is one."""
    from scipy.signal import find_peaks

    fs, lead = rec.fs, period / 4 if lead is None else lead
    out = []
    for b, idx in _blocks(rec):
        v = _smooth_velocity(rec.angle[idx], fs, 3.0)
        pk, _ = find_peaks(v, distance=max(1, int(0.6 * period * fs)), height=0.3 * np.max(v))
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
    if L < 10:
        raise ImpedanceDataError("cannot infer the cycle length: give --period")
    S = int(round(max_shift_s * fs)) if align != "none" else 0
    P = int(round(pad_s * fs))
    blocks = dict(_blocks(rec))
    excluded = {"irregular length": 0, "incomplete padding": 0, "outlier": 0}
    cand = []
    for b, starts in by_block.items():
        starts = sorted(starts)
        nb = len(blocks[b])
        for j, s in enumerate(starts):
            nxt = starts[j + 1] - s if j + 1 < len(starts) else None
            if nxt is not None and abs(nxt - L) > length_tol * L:
                excluded["irregular length"] += 1
            elif s - P - S < 0 or s + L + P + S > nb:
                excluded["incomplete padding"] += 1
            else:
                cand.append((b, s))
    if len(cand) < 3:
        raise ImpedanceDataError(f"only {len(cand)} complete cycles (excluded: {excluded})")
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
    for w in rep.warnings:
        log.warning(w)
    return shifts
