"""The figure users expect: I(t), B(t), K(t) with bands against the truth, movement beneath.

Top three panels: the estimates with their bootstrap bands, the truth when known (dashed) and the
posture (time-invariant) values as horizontal reference lines; bottom three: the mean angle, velocity
and torque of the ensemble.  matplotlib (the `impedance` extra) is imported only here.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from closedloop.impedance.data import Ensemble


def plot_impedance(
    path: str | Path,
    est,
    ens: Ensemble,
    bands=None,
    truth: dict | None = None,
    posture: dict[str, tuple[float, float, float]] | None = None,
    title: str = "",
) -> Path:
    """Write the figure to `path` (format from the suffix: .png, .svg, .pdf)."""
    from closedloop.errors import require

    require("matplotlib", "--plots", "impedance").use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    fig, axes = plt.subplots(
        6, 1, figsize=(7.5, 11), sharex=True, gridspec_kw={"height_ratios": [1, 1, 1, 0.7, 0.7, 0.7]}
    )
    units = {"I": "I (kg m$^2$)", "B": "B (N m s/rad)", "K": "K (N m/rad)"}
    for ax, k in zip(axes[:3], "IBK"):
        y = getattr(est, k)
        ax.plot(est.t, y, color="C0", lw=1.2, label=f"estimate ({est.options.method})")
        if bands is not None:
            ax.fill_between(
                est.t,
                bands.lo[k],
                bands.hi[k],
                color="C0",
                alpha=0.25,
                label=f"{100 * bands.level:.0f} % bootstrap band",
            )
        if truth is not None:
            ax.plot(truth["t"], truth[k], "k--", lw=1.0, label="truth")
        for j, (name, vals) in enumerate((posture or {}).items()):
            ax.axhline(vals["IBK".index(k)], color=f"C{j + 2}", ls=":", lw=1.0, label=name)
        ax.set_ylabel(units[k])
        finite = y[np.isfinite(y)]
        if finite.size:
            lo, hi = np.percentile(finite, [1, 99])
            if bands is not None:  # the band too, but not a few instants where it balloons (steps)
                blo, bhi = bands.lo[k][np.isfinite(bands.lo[k])], bands.hi[k][np.isfinite(bands.hi[k])]
                if blo.size and bhi.size:
                    lo, hi = min(lo, np.percentile(blo, 2)), max(hi, np.percentile(bhi, 98))
            if truth is not None:
                lo, hi = min(lo, truth[k].min()), max(hi, truth[k].max())
            pad = 0.15 * (hi - lo) + 1e-12
            ax.set_ylim(lo - pad, hi + pad)
    axes[0].legend(fontsize=7, loc="upper right", ncol=2)
    th0, tau0 = ens.mean()
    core = slice(ens.pad, ens.pad + ens.length)
    t = ens.t
    from closedloop.impedance.estimate import lowpass

    vel = np.gradient(lowpass(th0, ens.fs, 20.0), 1.0 / ens.fs)[core]
    for ax, y, lab in zip(
        axes[3:],
        (th0[core], vel, lowpass(tau0, ens.fs, 20.0)[core]),
        ("mean angle (rad)", "mean velocity (rad/s)", "mean torque (N m)"),
    ):
        ax.plot(t, y, color="0.3", lw=1.0)
        ax.set_ylabel(lab, fontsize=8)
    axes[-1].set_xlabel("time in cycle (s)")
    fig.suptitle(title or f"time-varying joint impedance, {ens.n} cycles", fontsize=10)
    fig.tight_layout()
    import io

    from closedloop.io.files import atomic_write_text

    buf = io.BytesIO()
    fig.savefig(buf, dpi=120, format=path.suffix.lstrip(".").lower() or "png")
    plt.close(fig)
    atomic_write_text(path, buf.getvalue())  # whole, or inside the command's OutputSet
    return path
