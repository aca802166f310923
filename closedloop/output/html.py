"""A calibration as one self-contained HTML page (figures embedded as base64 PNG), or PNG files.

Sections: verdict; closure per configuration before and after the fit (and the
held-out folds of the k-fold validation); parameter corrections with their
standard errors; the singular-value spectrum of the whitened, column-scaled
identification Jacobian with the truncation line (thesis 4.2.6: directions below
it are not estimated); outliers; the parameters that are not identified, each
with the combination that is (structural redundancy: the kept parameters that
absorb it; data: the undetermined direction); which output file carries what.

No JavaScript; matplotlib (Agg) draws the figures (``pip install
".[report]"`` in the checkout).  Printing is left to the CLI.
"""

from __future__ import annotations

import base64
import html
import io
import math
from pathlib import Path

import numpy as np

from closedloop.errors import require
from closedloop.io.files import atomic_write_text
from closedloop.output.report import next_poses_words
from closedloop.records import ParamStatus

_CSS = """body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;color:#222}
h1{font-size:1.6em}h2{border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;font-size:.9em;margin:.5em 0}
td,th{border:1px solid #ddd;padding:3px 8px;text-align:right}
th{background:#f3f3f3}td.l,th.l{text-align:left}.verdict{padding:.6em 1em;border-radius:6px;font-size:1.2em}
.ok{background:#e3f5e1}.suspect{background:#fff3cd}.failed{background:#f8d7da}img{max-width:100%}
.small{color:#666;font-size:.85em}"""


def _plt():
    require("matplotlib", "--html/--plots", "report").use("Agg")
    import matplotlib.pyplot as plt

    return plt


def nominal_with_fitted_loops(problem, x: np.ndarray, iterations: int = 8) -> np.ndarray:
    """The nominal robot with the loops' own unknowns (a fixture's pose, a socket) fitted to all the data
    by Gauss-Newton on their columns alone: the fair "before" of a closure plot.  The solver's start takes
    them from one configuration (`Loop.initialize`), which that configuration then closes by construction."""
    cols = sorted({int(c) for block in problem.loop_columns for c in block})
    x = np.asarray(x, dtype=float).copy()
    if not cols:
        return x
    for _ in range(iterations):
        evals = problem.evaluate(x, True, columns=cols)
        r = np.concatenate([e.r.ravel() for e in evals])
        J = np.vstack([e.J.reshape(-1, len(cols)) for e in evals])
        ok = np.isfinite(r) & np.all(np.isfinite(J), axis=1)
        step = np.linalg.lstsq(J[ok], -r[ok], rcond=None)[0]
        x[cols] += step
        if np.linalg.norm(step) < 1e-12:
            break
    return x


def closure_per_configuration(res) -> list[dict]:
    """Per loop: row numbers and per-configuration closure (m, rad) before the fit (the nominal robot with
    its loops' unknowns fitted to all the data, `nominal_with_fitted_loops`) and after it."""
    prob = res.problem
    out = []
    before = nominal_with_fitted_loops(prob, res.fit.initial)
    for values, key in ((before, "before"), (res.fit.values, "after")):
        for k, (b, ev) in enumerate(zip(prob.blocks, prob.evaluate(np.asarray(values), False))):
            lp = b.loop
            if key == "before":
                out.append({"loop": lp.name, "rows": np.asarray(b.rows)})
            d = out[k]
            d[f"{key}_m"] = np.linalg.norm(ev.r[:, list(lp.translation_rows)], axis=1) if lp.translation_rows else None
            d[f"{key}_rad"] = np.linalg.norm(ev.r[:, list(lp.rotation_rows)], axis=1) if lp.rotation_rows else None
            d[f"{key}_px"] = (
                np.linalg.norm(ev.r[:, list(lp.pixel_rows)], axis=1) if getattr(lp, "pixel_rows", None) else None
            )
    return out


def closure_axis(values: np.ndarray, decades: float = 6.0) -> tuple[float, float]:
    """A log axis (low, high) for closures: from a decade below the 2nd percentile of the positive values
    (or `decades` below the largest, whichever is higher) to the largest, so that a few near-zero closures
    (a configuration that closes by chance, an exact fit's 1e-13) do not stretch it over many decades."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v) & (v > 0)]
    if not v.size:
        return 1e-12, 1.0
    hi = float(v.max())
    lo = max(0.1 * float(np.percentile(v, 2)), hi * 10.0**-decades)
    return min(lo, hi), hi


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    _plt().close(fig)
    return buf.getvalue()


def fig_closure(res, report: dict) -> bytes:
    """Closure per configuration, before and after, log scale; held-out folds as lines."""
    plt = _plt()
    per = closure_per_configuration(res)
    units = [("m", 1e3, "mm"), ("rad", 1e3, "mrad"), ("px", 1.0, "px")]
    panels = [(d, u) for d in per for u in units if d.get(f"before_{u[0]}") is not None]
    fig, axes = plt.subplots(len(panels), 1, figsize=(9, 2.6 * len(panels)), squeeze=False)
    cv = {t["loop"]: t for t in (report.get("validation") or {}).get("test", [])}
    for ax, (d, (key, f, unit)) in zip(axes[:, 0], panels):
        x = np.arange(len(d["rows"]))
        before, after = d[f"before_{key}"] * f, d[f"after_{key}"] * f
        held = cv.get(d["loop"], {}).get(f"rms_{key}")
        lo, hi = closure_axis(np.concatenate([before, after]))
        clipped = False
        for v, color, label in ((before, "#c44", "before (nominal model)"), (after, "#2a6", "after (calibrated)")):
            low = v < lo  # drawn on the axis floor, marked: one near-zero value must not stretch the axis
            ax.semilogy(x[~low], v[~low], ".", color=color, label=label)
            if low.any():
                ax.semilogy(x[low], np.full(low.sum(), lo), "v", color=color, ms=5, mfc="none")
                clipped = True
        if held is not None:
            ax.axhline(min(max(held * f, lo), hi), color="#36c", ls="--", label="held-out RMS (k-fold)")
        ax.set_ylim(lo / 1.3, hi * 1.3)
        ax.set_ylabel(f"closure [{unit}]")
        ax.set_title(
            f"loop {d['loop']}: {'position' if key == 'm' else 'rotation' if key == 'rad' else 'image'} "
            "closure per configuration",
            fontsize=10,
        )
        ax.legend(
            fontsize=8,
            title_fontsize=8,
            loc="upper left",
            bbox_to_anchor=(1.01, 1.0),  # beside the axes: no point hidden
            title=f"open triangles:\nbelow {lo:.2g} {unit}" if clipped else None,
        )
    axes[-1, 0].set_xlabel("configuration (log order)")
    fig.tight_layout()
    return _png(fig)


def robot_corrections(res) -> list[int]:
    """Indices of the estimated robot parameters: by kind, so that a loop's own parameters and shared
    loop groups (``ball.tip_x``, named by the group, not by a loop) are left out."""
    return [
        k
        for k in range(len(res.fit.names))
        if res.fit.status[k] == ParamStatus.ESTIMATED and res.problem.params[k].kind != "loop"
    ]


def fig_corrections(res) -> bytes:
    """Estimated corrections (calibrated - initial) with +-1 standard error, lengths and angles apart."""
    plt = _plt()
    prob = res.problem
    est = robot_corrections(res)
    units = [("m", 1e3, "mm"), ("rad", 1e3, "mrad")]
    groups = [(u, f, lab, [k for k in est if prob.params[k].unit == u]) for u, f, lab in units]
    other = [k for k in est if prob.params[k].unit not in ("m", "rad")]  # scale factors, compliance
    groups = [g for g in groups if g[3]] + ([("", 1.0, "scale, compliance, ...", other)] if other else [])
    if not groups:
        return _png(_plt().figure(figsize=(4, 1)))
    fig, axes = plt.subplots(1, len(groups), figsize=(9, 0.22 * max(len(g[3]) for g in groups) + 1.5), squeeze=False)
    for ax, (u, f, lab, idx) in zip(axes[0], groups):
        dv = (res.fit.values[idx] - res.fit.initial[idx]) * f
        sd = np.nan_to_num(res.fit.std[idx]) * f
        y = np.arange(len(idx))
        ax.errorbar(dv, y, xerr=sd, fmt="o", ms=3, color="#36c", ecolor="#999", capsize=2)
        ax.axvline(0, color="k", lw=0.5)
        ax.set_yticks(y, [res.fit.names[k] for k in idx], fontsize=7)
        ax.invert_yaxis()
        ax.set_xlabel(f"correction [{lab}]  (+-1 standard error)")
    fig.tight_layout()
    return _png(fig)


def truncation_threshold(res, snr: float = 1.0) -> float | None:
    """The SVD truncation threshold of the fit (thesis 4.2.6): ``max(1e-10 s_1, snr * sigma_r)``.

    ``sigma_r`` is 1 with a given joint noise (the residual is whitened by it) and the estimated
    level otherwise (a plain loop-closure fit's closure scale, whether a joint noise was given or not).  If that does not reproduce the number of kept directions (options unknown
    here), the line is drawn between the last kept and the first truncated singular value.
    """
    S = np.asarray(res.identifiability.singular_values)
    if not S.size:
        return None
    whitened = not res.noise.sigma_estimated and res.noise.joint_noise is not None
    thr = max(1e-10 * float(S[0]), snr * (1.0 if whitened else float(res.noise.sigma)))
    if int(np.sum(S > thr)) == res.identifiability.rank:
        return thr
    if 0 < res.identifiability.rank < S.size:
        return float(math.sqrt(S[res.identifiability.rank - 1] * max(S[res.identifiability.rank], 1e-300)))
    return None


def fig_spectrum(res, snr: float = 1.0) -> bytes:
    plt = _plt()
    S = np.asarray(res.identifiability.singular_values)
    fig, ax = plt.subplots(figsize=(9, 3))
    if S.size:
        k = np.arange(1, S.size + 1)
        kept = k <= res.identifiability.rank
        ax.semilogy(k[kept], S[kept], "o", color="#2a6", ms=4, label=f"kept ({res.identifiability.rank})")
        ax.semilogy(
            k[~kept],
            np.maximum(S[~kept], 1e-300),
            "x",
            color="#c44",
            label=f"truncated ({S.size - res.identifiability.rank})",
        )
        thr = truncation_threshold(res, snr)
        if thr is not None:
            ax.axhline(thr, color="#c44", ls="--", lw=1, label=f"truncation ({thr:.2g})")
        ax.legend(fontsize=8)
    ax.set_xlabel("index")
    ax.set_ylabel("singular value")
    ax.set_title("whitened, column-scaled identification Jacobian (thesis 4.2.6)", fontsize=10)
    fig.tight_layout()
    return _png(fig)


def fig_accuracy(accuracy) -> bytes:
    """The predicted error over the workspace (`closedloop.analysis.accuracy.WorkspaceAccuracy`), per
    followed frame: against the point's reach (its distance from the base), then against each joint's
    reading; the calibration's own configurations marked as ticks along the axes (where the data are)."""
    plt = _plt()
    frames = list(accuracy.frames)
    J = len(accuracy.joints)
    cols = max(min(J, 4), 1)
    rows_j = -(-J // cols)
    per = 1 + rows_j
    fig = plt.figure(figsize=(2.6 * cols, 2.4 * len(frames) * per))
    grid = fig.add_gridspec(len(frames) * per, cols)
    train = accuracy.training
    for fi, f in enumerate(frames):
        top = fi * per
        ax = fig.add_subplot(grid[top, :])
        y = f.sigma_m * 1e3
        if f.reach is not None:
            ax.plot(f.reach, y, ".", color="#36c", ms=4, label="workspace (predicted)")
        if f.training_reach is not None:
            ax.plot(
                f.training_reach, np.zeros_like(f.training_reach), "|", color="#c44", ms=8, label="calibration data"
            )
        ax.set_xlabel("reach: distance from the base [m]", fontsize=8)
        ax.set_ylabel("predicted error [mm]", fontsize=8)
        ax.set_title(f"loop {f.loop}: {f.frame}, predicted position error over the workspace", fontsize=10)
        ax.legend(fontsize=7, loc="upper left")
        for j, name in enumerate(accuracy.joints):
            a = fig.add_subplot(grid[top + 1 + j // cols, j % cols])
            a.plot(accuracy.readings[:, j], y, ".", color="#36c", ms=3)
            if train is not None and train.shape[1] == J:
                a.plot(train[:, j], np.zeros(train.shape[0]), "|", color="#c44", ms=6)
            a.set_title(f"{name} [rad]", fontsize=8)
            a.tick_params(labelsize=7)
            if j % cols == 0:
                a.set_ylabel("[mm]", fontsize=8)
    fig.tight_layout()
    return _png(fig)


def figures(res, report: dict, snr: float = 1.0, accuracy=None) -> dict[str, bytes]:
    """Figure name -> PNG bytes (with `accuracy`, the predicted accuracy over the workspace too)."""
    out = {
        "closure": fig_closure(res, report),
        "corrections": fig_corrections(res),
        "singular_values": fig_spectrum(res, snr),
    }
    if accuracy is not None and accuracy.frames:
        out["accuracy"] = fig_accuracy(accuracy)
    return out


def write_plots(res, report: dict, out_dir: str | Path, snr: float = 1.0, accuracy=None) -> list[Path]:
    """The figures (`plot_files`) written; returns the paths."""
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    files = plot_files(res, report, out_dir, snr, accuracy)
    for p, data in files.items():
        atomic_write_text(p, data)
    return list(files)


def plot_files(
    res, report: dict, out_dir: str | Path, snr: float = 1.0, accuracy=None, figs: dict[str, bytes] | None = None
) -> dict[Path, bytes]:
    """The figures as the files ``DIR/<name>.png``: path -> PNG bytes; `figs`: `figures` already drawn (for
    the page too: drawing them is most of the cost of ``--html`` and ``--plots``)."""
    if figs is None:
        figs = figures(res, report, snr, accuracy)
    return {Path(out_dir) / f"{name}.png": data for name, data in figs.items()}


# --------------------------------------------------------------------------- page
def _e(x) -> str:
    return html.escape(str(x))


def _table(head: list[str], rows: list[list], left: int = 1) -> str:
    th = "".join(f"<th class='l'>{_e(h)}</th>" if i < left else f"<th>{_e(h)}</th>" for i, h in enumerate(head))
    body = "".join(
        "<tr>"
        + "".join(f"<td class='l'>{_e(c)}</td>" if i < left else f"<td>{_e(c)}</td>" for i, c in enumerate(r))
        + "</tr>"
        for r in rows
    )
    return f"<table><tr>{th}</tr>{body}</table>"


def _g(v, f: float = 1.0, fmt: str = ".4g") -> str:
    return "" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v * f, fmt)


def verdict_of(res, report: dict | None = None) -> tuple[str, list[str]]:
    """The verdict (status, reasons): the report's (it may include the validation), else ``res.verdict``,
    else converged / not converged."""
    v = (report or {}).get("verdict")
    if isinstance(v, dict) and "status" in v:
        return str(v["status"]), [str(r) for r in v.get("reasons", []) or []]
    v = getattr(res, "verdict", None)
    if v is not None:
        return str(getattr(v, "status", v)), list(getattr(v, "reasons", []) or [])
    return ("ok", []) if res.converged else ("failed", [f"the solver did not converge ({res.fit.solver_message})"])


def _sections(res, report: dict, snr: float = 1.0, row_name=None) -> list[str]:
    status, reasons = verdict_of(res, report)
    out = [
        f"<div class='verdict {_e(status)}'>verdict: <b>{_e(status)}</b>"
        + ("".join(f"<br>{_e(r)}" for r in reasons))
        + "</div>"
    ]
    n = sum(r.n for r in res.fit.residuals_after)
    noise = report.get("noise", {})
    out.append(
        _table(
            ["", "value"],
            [
                ["robot", robot_name(res, report)],
                ["model", report.get("model")],
                ["log", report.get("log")],
                ["configurations", n],
                ["parameters estimated", len(res.fit.estimated)],
                ["solver", f"{res.fit.solver_status}, {res.fit.iterations} iterations"],
                ["joint noise", res.noise.describe().removeprefix("joint noise ")],
                ["chi2 / dof", _g(noise.get("chi2_per_dof"))],
            ],
        )
    )
    rows = []
    for b, a in zip(res.fit.residuals_before, res.fit.residuals_after):
        rows.append([b.loop, b.n, _g(b.rms_m, 1e3), _g(a.rms_m, 1e3), _g(b.rms_rad, 1e3), _g(a.rms_rad, 1e3)])
    out.append(
        "<h2>Closure</h2>"
        + _table(["loop", "n", "RMS before [mm]", "after [mm]", "RMS before [mrad]", "after [mrad]"], rows)
    )
    cv = report.get("validation")
    if cv and "skipped" in cv:
        out.append(f"<p>k-fold validation skipped: {html.escape(cv['skipped'])}</p>")
    elif cv:
        conv = cv.get("folds_converged")
        conv = f"; {sum(map(bool, conv))} of {len(conv)} fold fits converged" if conv else ""
        out.append(
            f"<p>{cv['k']}-fold validation (fit on k-1 folds, closure of the held-out fold{conv}):</p>"
            + _table(
                ["loop", "held-out [mm]", "training [mm]", "held-out [mrad]", "training [mrad]"],
                [
                    [
                        t["loop"],
                        _g(t.get("rms_m"), 1e3),
                        _g(tr.get("rms_m"), 1e3),
                        _g(t.get("rms_rad"), 1e3),
                        _g(tr.get("rms_rad"), 1e3),
                    ]
                    for t, tr in zip(cv["test"], cv["train"])
                ],
            )
        )
    out.append("<img alt='closure per configuration' src='data:image/png;base64,{closure}'>")
    out.append(_accuracy(report))
    prob = res.problem
    rows = [
        [
            res.fit.names[k],
            prob.params[k].unit,
            _g(res.fit.initial[k], 1, ".6g"),
            _g(res.fit.values[k], 1, ".6g"),
            _g(res.fit.values[k] - res.fit.initial[k], 1, ".3e"),
            _g(res.fit.std[k], 1, ".2e"),
        ]
        for k in range(len(res.fit.names))
        if res.fit.status[k] == ParamStatus.ESTIMATED
    ]
    out.append(
        "<h2>Parameter corrections</h2>"
        + _table(["parameter", "unit", "initial", "calibrated", "correction", "std. error"], rows)
        + "<img alt='corrections' src='data:image/png;base64,{corrections}'>"
    )
    thr = truncation_threshold(res, snr)
    out.append(
        "<h2>Singular values</h2><p>"
        + _e(f"{res.identifiability.rank} of {len(res.identifiability.singular_values)} directions kept")
        + (_e(f"; truncation at {thr:.3g}") if thr else "")
        + "</p>"
        + "<img alt='singular values' src='data:image/png;base64,{singular_values}'>"
    )
    out.append(_outliers(res, row_name or (lambda i: f"log row {i + 1}")))
    out.append(_not_identified(res))
    out.append(
        "<h2>Which file carries what</h2><p>The calibrated URDF or MJCF carries the joint placements with "
        "the offsets folded in (it takes the raw readings). Scale factors and joint compliance cannot be "
        "expressed in URDF or MJCF: they are in the JSON report (<code>scale_factors</code>, "
        "<code>compliance</code>) and in <code>&lt;model&gt;.sensors.yaml</code> beside the calibrated model; "
        "a joint value for the model is scale * reading. "
        "D-H input gets a calibrated D-H YAML that carries all of them.</p>"
    )
    if res.notes:
        out.append("<h2>Notes</h2><ul>" + "".join(f"<li>{_e(n)}</li>" for n in res.notes) + "</ul>")
    return out


def _accuracy(report: dict) -> str:
    """The predicted accuracy over the workspace (the report's ``accuracy`` section) and its figure."""
    sec = report.get("accuracy") or {}
    ws = sec.get("workspace")
    if not ws:
        return ""
    rows = [
        [
            f["loop"],
            f["frame"],
            _g(f.get("predicted_rms_m"), 1e3, ".3g"),
            _g(f.get("predicted_p95_m"), 1e3, ".3g"),
            _g(f.get("predicted_max_m"), 1e3, ".3g"),
            _g(f.get("predicted_max95_m"), 1e3, ".3g"),
            _g(f.get("predicted_max_rad"), 1e3, ".3g"),
            _g(f.get("predicted_unseen_rms_m"), 1e3, ".3g"),
        ]
        for f in ws["frames"]
    ]
    s = (
        "<h2>Predicted accuracy over the workspace</h2><p>"
        + _e(f"{ws['source']}; error bars from {ws['error_bars']}; base, tool")
        + _e(" and size" if ws.get("size_removed") else "")
        + " removed as no loop sees them.</p>"
        + _table(
            [
                "loop",
                "frame",
                "RMS [mm]",
                "95 % [mm]",
                "max [mm]",
                "max, 95 % bound [mm]",
                "max [mrad]",
                "unseen RMS [mm]",
            ],
            rows,
            left=2,
        )
    )
    reg = sec.get("regions")
    if reg and "test" in reg:
        s += f"<p>{reg['k']} regions of joint space held out in turn (closure of the held-out region):</p>" + _table(
            ["loop", "held-out [mm]", "held-out [mrad]"],
            [[t["loop"], _g(t.get("rms_m"), 1e3), _g(t.get("rms_rad"), 1e3)] for t in reg["test"]],
        )
    tgt = sec.get("target")
    if tgt:
        met = "met" if tgt["met"] else "not met"
        if tgt["met"] and not tgt.get("met_95", True):
            met = "met by the expected largest error, not by its 95 % bound"
        s += "<p>" + _e(f"accuracy target {tgt['describe']}: {met}") + "</p>"
    nxt = sec.get("next_poses")  # calibrate --suggest: where to measure next
    if nxt:
        s += "<p>" + _e(f"where to measure next: {next_poses_words(nxt)}") + "</p>"
    return s + "<img alt='predicted accuracy' src='data:image/png;base64,{accuracy}'>"


def _outliers(res, row_name) -> str:
    s = "<h2>Outliers</h2>"
    if res.outliers.rejected:
        s += "<p>Configurations left out of the final fit (their closure is not noise):</p>" + _table(
            ["row", "loop", "robust standard deviations", "closure after [mm]", "closure after [mrad]"],
            [
                [
                    row_name(rj.row - 1),
                    rj.loop,
                    _g(rj.standardized, 1, ".3g"),
                    _g(rj.closure_m, 1e3),
                    _g(rj.closure_rad, 1e3),
                ]
                for rj in res.outliers.rejected
            ],
        )
    if res.outliers.suspects:
        s += "<p>Configurations the noise model cannot explain (robust fit):</p>" + _table(
            ["row", "loop", "standardized", "p-value", "weight"],
            [
                [row_name(sp.row - 1), sp.loop, _g(sp.standardized), _g(sp.p_value, 1, ".2e"), _g(sp.weight)]
                for sp in res.outliers.suspects
            ],
        )
    rows = []
    for d in closure_per_configuration(res):
        key = next((k for k in ("after_m", "after_rad", "after_px") if d.get(k) is not None), "after_px")
        v = d[key]
        if v is None or not v.size:
            continue
        med = float(np.median(v))
        unit = {"after_m": "mm", "after_rad": "mrad", "after_px": "px"}[key]
        for i in np.argsort(v)[::-1][:5]:
            rows.append(
                [
                    d["loop"],
                    row_name(int(d["rows"][i]) - 1),
                    _g(float(v[i]), 1e3 if key != "after_px" else 1.0) + f" {unit}",
                    _g(float(v[i]) / med if med > 0 else float("nan"), 1, ".3g"),
                ]
            )
    s += "<p>Largest closures after the fit (x median: above ~5 deserves a look at that row):</p>" + _table(
        ["loop", "row", "closure", "x median"], rows
    )
    return s


def _not_identified(res) -> str:
    s = "<h2>Not identified</h2>"
    if res.identifiability.dropped:
        s += (
            "<p>Structurally redundant (removed before solving; its effect equals the combination of kept "
            "parameters shown):</p>"
            + _table(
                ["parameter", "reason / combination"],
                [[d.name, d.describe()] for d in res.identifiability.dropped],
                left=2,
            )
        )
    if res.identifiability.weak:
        s += "<p>Not determined by this data:</p>" + _table(
            ["singular value", "combination"],
            [[_g(c.singular_value, 1, ".3g"), c.describe()] for c in res.identifiability.weak],
            left=2,
        )
    if not res.identifiability.dropped and not res.identifiability.weak:
        s += "<p>Every selected parameter was identified.</p>"
    return s


def robot_name(res, report: dict) -> str:
    """The robot's own name (URDF ``<robot name>``, MJCF ``<mujoco model>``), else the model file's stem."""
    name = str(getattr(getattr(getattr(res.problem, "robot", None), "model", None), "name", "") or "").strip()
    return name or Path(str(report.get("model") or "model")).stem


def render_html(
    res, report: dict, snr: float = 1.0, row_name=None, accuracy=None, figs: dict[str, bytes] | None = None
) -> str:
    """The page as a string (figures embedded); ``snr`` is the fit's ``--snr`` (the truncation line);
    ``row_name`` (`JointLog.where`: 0-based row -> ``log.csv line 52``) names the rows by file and line;
    `figs`: `figures` already drawn (shared with `plot_files`)."""
    if figs is None:
        figs = figures(res, report, snr, accuracy)
    b64 = {k: base64.b64encode(v).decode("ascii") for k, v in figs.items()}
    body = "\n".join(_sections(res, report, snr, row_name))
    for k, v in b64.items():
        body = body.replace("{" + k + "}", v)
    if "accuracy" not in b64:  # no workspace record to draw: no broken image
        body = body.replace("<img alt='predicted accuracy' src='data:image/png;base64,{accuracy}'>", "")
    title = f"{robot_name(res, report)}: closedloop calibration"
    return (
        f"<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'><title>{_e(title)}</title>"
        f"<style>{_CSS}</style></head><body><h1>{_e(title)}</h1>\n{body}\n"
        f"<p class='small'>closedloop {_e(report.get('closedloop_version', ''))}</p></body></html>\n"
    )


def write_html(res, report: dict, path: str | Path, snr: float = 1.0, row_name=None, accuracy=None) -> None:
    """Write `render_html` to `path` whole."""
    atomic_write_text(path, render_html(res, report, snr, row_name, accuracy))
