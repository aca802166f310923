"""A feature whose optional package is missing: one line naming the feature and both install lines, exit 2.

Every optional extra of pyproject.toml is refused the same way (`closedloop.errors.require`): the
package is made unimportable here (``sys.modules[name] = None``, so ``import name`` raises ImportError)
and the command that needs it is run in this process.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from closedloop.cli.main import main
from closedloop.errors import MissingExtraError, require

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    from pip._vendor import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]


#: extra -> (the module hidden, the feature named in the line, argv with {tmp} and {panda})
CASES = {
    "ros": (
        "rosbags",
        "{tmp}/run.bag: reading a ROS bag",
        ["extract", "{tmp}/run.bag", "--model", "{panda}", "--out", "{tmp}/o.csv"],
    ),
    "report": (
        "matplotlib",
        "--html",
        ["calibrate", "{panda}", "{tmp}/log.csv", "--loop", "weld:frame=panda_hand", "--html", "{tmp}/r.html"],
    ),
    "ray": (
        "ray",
        "--ray",
        ["simulate", "panda_weld", "--seeds", "0-1", "--n", "5", "--ray", "local", "--out", "{tmp}/s"],
    ),
    "impedance": (
        "h5py",
        "--format h5",
        ["impedance", "simulate", "--out", "{tmp}/h", "--format", "h5", "--cycles", "2"],
    ),
}


def test_every_extra_has_a_case():
    with open(ROOT / "pyproject.toml", "rb") as fh:
        extras = set(tomllib.load(fh)["project"]["optional-dependencies"])
    assert extras - {"test", "docs", "dev"} == set(CASES)


@pytest.mark.parametrize("extra", sorted(CASES))
def test_missing_extra_is_one_line_and_exit_2(extra, tmp_path, monkeypatch, capsys):
    module, feature, argv = CASES[extra]
    (tmp_path / "log.csv").write_text("panda_joint1\n0.0\n")
    monkeypatch.setitem(sys.modules, module, None)  # `import module` raises ImportError
    for sub in [m for m in sys.modules if m.startswith(module + ".")]:
        monkeypatch.setitem(sys.modules, sub, None)
    from closedloop.assets.catalog import ROBOTS

    args = [a.replace("{tmp}", str(tmp_path)).replace("{panda}", str(ROBOTS["panda"].path)) for a in argv]
    rc = main(args)
    out, err = capsys.readouterr()
    assert rc == 2, err
    assert out == ""
    assert err.count("\n") == 1 and "Traceback" not in err, err
    feature = feature.replace("{tmp}", str(tmp_path))
    assert err == (
        f'error: {feature}: needs {module}, which is not installed: pip install "closedloop[{extra}]" '
        f'(from a checkout: pip install ".[{extra}]")\n'
    )
    assert not (tmp_path / "o.csv").exists() and not (tmp_path / "r.html").exists() and not (tmp_path / "h").exists()


def test_require_returns_the_module_and_refuses_with_the_feature(monkeypatch):
    assert require("json", "--anything", "report") is sys.modules["json"]
    monkeypatch.setitem(sys.modules, "h5py", None)
    with pytest.raises(MissingExtraError) as exc:
        require("h5py", "data.h5 (an HDF5 record)", "impedance")
    assert (exc.value.feature, exc.value.module, exc.value.extra) == ("data.h5 (an HDF5 record)", "h5py", "impedance")
    assert str(exc.value).startswith("data.h5 (an HDF5 record): needs h5py, which is not installed")


def test_a_fleet_page_without_matplotlib_is_one_line_and_writes_nothing(tmp_path, monkeypatch, capsys):
    """`fleet-report --html` (the drift figure) refuses a missing matplotlib as `calibrate --html` does, before
    any file of the report is written (the JSON asked beside it included)."""
    summary = tmp_path / "fleet.summary.csv"
    summary.write_text(
        "name,robot,date,status,verdict,verdict_reasons,configurations,estimated,rms_before_mm,rms_after_mm,"
        "rms_before_mrad,rms_after_mrad,cv_test_mm,cv_test_mrad,top_changes,drift_from,drift_max_z,drift_flagged,"
        "seconds,cpu_seconds,resumed,error,out\n"
        "a1,a,2026-01-01,ok,ok,,40,20,1.0,0.01,1.0,0.01,,,,,,,1.0,1.0,False,,a1\n"
    )
    for m in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")] + ["matplotlib"]:
        monkeypatch.setitem(sys.modules, m, None)
    args = ["fleet-report", str(summary), "--html", str(tmp_path / "f.html"), "--json", str(tmp_path / "f.json")]
    rc = main(args)
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert err.startswith("error: --html: needs matplotlib, which is not installed")
    assert not (tmp_path / "f.html").exists() and not (tmp_path / "f.json").exists()
