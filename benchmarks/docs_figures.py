"""The documentation site's pictures, drawn from the code and from a fresh run (``make docs-outputs``).

* ``docs/architecture/layers.png``: the package's units in their layers (``tests/test_layout.py``'s
  ``LAYERS``, top to bottom) and the imports between units as read from the source (the same graph the
  layering test checks), each arrow pointing down from the importer to the unit it uses.
* ``docs/images/main-job-closure.png``: the README's main job with 1e-4 rad of simulated joint noise,
  calibrated with ``--plots``: the closure per configuration before and after the fit.

Usage: ``python benchmarks/docs_figures.py`` (needs the ``report`` extra: matplotlib).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def layers_figure(path: Path) -> None:
    """The units stacked by layer, with one arrow per unit-to-unit import (its width: how many modules)."""
    import test_layout as lay

    graph = lay.edges()
    count: Counter = Counter()
    for src, targets in graph.items():
        for t in targets:
            a, b = lay.unit(src), lay.unit(t)
            if a and b and a != b:
                count[(a, b)] += 1
    layers = [list(layer) for layer in lay.LAYERS]
    where: dict[str, tuple[float, float]] = {}
    for i, layer in enumerate(layers):
        for j, u in enumerate(layer):
            where[u] = (j * 2.4 - (len(layer) - 1) * 1.2, -i)
    fig, ax = plt.subplots(figsize=(7.5, 0.42 * len(layers) + 0.6))
    for (a, b), n in sorted(count.items(), key=lambda kv: kv[1]):
        (x0, y0), (x1, y1) = where[a], where[b]
        side = 1.0 if (hash(a) ^ hash(b)) & 1 else -1.0
        rad = side * min(0.9, 0.08 * abs(y1 - y0))
        ax.annotate(
            "",
            xy=(x1 + 1.05 * side, y1),
            xytext=(x0 + 1.05 * side, y0),
            arrowprops={
                "arrowstyle": "-|>",
                "lw": 0.4 + 0.25 * min(n, 8),
                "color": "#5b7db1",
                "alpha": 0.55,
                "connectionstyle": f"arc3,rad={rad}",
                "shrinkA": 2,
                "shrinkB": 2,
            },
        )
    for u, (x, y) in where.items():
        ax.text(
            x,
            y,
            u,
            ha="center",
            va="center",
            fontsize=9,
            bbox={"boxstyle": "round,pad=0.3", "fc": "#f4f1e8", "ec": "#8a7f5c", "lw": 0.8},
        )
    ax.set_xlim(-3.2, 3.2)
    ax.set_ylim(-len(layers) + 0.4, 0.6)
    ax.axis("off")
    ax.set_title("closedloop's units, top layer first; an arrow: the upper unit imports the lower", fontsize=9)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)


def main_job_closure(path: Path) -> None:
    """The main job with realistic joint noise, its closure per configuration before and after (--plots)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT)] + [p for p in [os.environ.get("PYTHONPATH")] if p]))
    cli = [sys.executable, "-m", "closedloop.cli.main"]
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        subprocess.run(
            cli
            + ["simulate", "panda_weld", "--n", "200", "--seed", "1", "--set", "noise=1e-4", "--out", str(t / "sim")],
            check=True,
            env=env,
            capture_output=True,
        )
        subprocess.run(
            cli
            + [
                "calibrate",
                str(t / "sim" / "nominal.urdf"),
                str(t / "sim" / "log.csv"),
                "--loop",
                "weld:frame=panda_hand_tcp,name=fixture",
                "--report",
                str(t / "report.json"),
                "--plots",
                str(t / "plots"),
                "--cv",
                "0",
            ],
            check=True,
            env=env,
            capture_output=True,
        )
        shots = sorted((t / "plots").glob("*closure*.png")) or sorted((t / "plots").glob("*.png"))
        path.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(shots[0], path)


if __name__ == "__main__":
    layers_figure(ROOT / "docs" / "architecture" / "layers.png")
    print("wrote docs/architecture/layers.png")
    main_job_closure(ROOT / "docs" / "images" / "main-job-closure.png")
    print("wrote docs/images/main-job-closure.png")
