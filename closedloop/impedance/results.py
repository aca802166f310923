"""Result tables (CSV or JSON) and truth files.

Results: one row per instant - time (s), I (kg m^2), B (N m s/rad), K (N m/rad), their band limits
(`I_lo`, `I_hi`, ...; bias-aware: widened by the simulated bias `I_bias`, ...), natural frequency `wn` (rad/s), damping ratio `zeta`, free-run VAF per instant
(%), regressor condition number.  The JSON form adds a `summary` (method, options, cycles, exclusions,
alignment diagnostics, overall VAF, warnings, posture values, errors against truth).
Truth: CSV with columns t, I, B, K (and optional K_muscle, theta0).
"""

from __future__ import annotations

import io
import json
from dataclasses import asdict
from pathlib import Path

import numpy as np

from closedloop.impedance.data import ImpedanceDataError
from closedloop.io.files import atomic_write_text


def table(est, bands=None, fit=None) -> dict[str, np.ndarray]:
    cols = {"time": est.t, "I": est.I, "B": est.B, "K": est.K}
    if bands is not None:
        for k in "IBK":
            cols[f"{k}_lo"], cols[f"{k}_hi"] = bands.lo[k], bands.hi[k]
        if bands.bias is not None:
            for k in "IBK":
                cols[f"{k}_bias"] = bands.bias[k]
    cols["wn"], cols["zeta"] = est.wn, est.zeta
    if fit is not None:
        cols["vaf"] = fit.vaf_t
    cols["cond"] = est.cond
    return cols


def write_results(path: str | Path, est, bands=None, fit=None, summary: dict | None = None) -> Path:
    """The results table as CSV, or as JSON with the summary, options and units; written whole."""
    path = Path(path)
    cols = table(est, bands, fit)
    if path.suffix == ".json":

        def clean(a):
            return [None if not np.isfinite(x) else float(x) for x in np.asarray(a, float)]

        doc = {
            "summary": summary or {},
            "options": asdict(est.options),
            "units": {
                "time": "s",
                "I": "kg m^2",
                "B": "N m s/rad",
                "K": "N m/rad",
                "wn": "rad/s",
                "zeta": "1",
                "vaf": "%",
            },
            "table": {k: clean(v) for k, v in cols.items()},
        }
        atomic_write_text(path, json.dumps(doc, indent=1, default=_default))
    else:
        buf = io.StringIO()
        np.savetxt(
            buf, np.column_stack(list(cols.values())), delimiter=",", header=",".join(cols), comments="", fmt="%.6g"
        )
        atomic_write_text(path, buf.getvalue())
    return path


def _default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    return str(o)


def write_truth(path: str | Path, truth: dict[str, np.ndarray]) -> None:
    """Truth CSV (t, I, B, K [, K_muscle, theta0]), written whole."""
    keys = [k for k in ("t", "I", "B", "K", "K_muscle", "theta0") if k in truth]
    buf = io.StringIO()
    np.savetxt(
        buf, np.column_stack([truth[k] for k in keys]), delimiter=",", header=",".join(keys), comments="", fmt="%.9g"
    )
    atomic_write_text(path, buf.getvalue())


def read_truth(path: str | Path) -> dict[str, np.ndarray]:
    path = Path(path)
    if not path.is_file():
        raise ImpedanceDataError(f"{path}: no such file")
    try:
        with open(path) as fh:
            head = [h.strip() for h in fh.readline().split(",")]
        arr = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except (ValueError, UnicodeDecodeError) as exc:
        raise ImpedanceDataError(f"{path}: not a numeric CSV ({str(exc).splitlines()[0]})") from None
    if arr.shape[1] != len(head) or arr.shape[0] < 2:
        raise ImpedanceDataError(
            f"{path}: {len(head)} header columns, {arr.shape[1]} data columns, {arr.shape[0]} rows"
        )
    bad = np.argwhere(~np.isfinite(arr))
    if bad.size:
        raise ImpedanceDataError(f"{path}: row {bad[0][0] + 2}, column '{head[bad[0][1]]}' is not finite")
    cols = {h: arr[:, i] for i, h in enumerate(head)}
    for k in ("t", "I", "B", "K"):
        if k not in cols:
            raise ImpedanceDataError(f"{path}: truth file needs columns t, I, B, K (missing '{k}')")
    return cols


def resample_truth(truth: dict[str, np.ndarray], t: np.ndarray) -> dict[str, np.ndarray]:
    """Truth on the estimate's time grid (linear interpolation)."""
    out = {"t": t}
    for k, v in truth.items():
        if k != "t":
            out[k] = np.interp(t, truth["t"], v)
    return out
