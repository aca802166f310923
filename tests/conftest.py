"""Shared fixtures: the Panda from example-robot-data and pure-kinematic weld datasets."""

from __future__ import annotations

import ast
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from closedloop.assets.catalog import ROBOTS
from closedloop.loops import WeldLoop
from closedloop.model.robot import RobotModel
from closedloop.studies.truth import make_dataset

PANDA_Q0 = [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8]


def pytest_configure(config):
    """Compiled bytecode kept for the run's workers and the commands its tests start, where the environment
    turns it off (PYTHONDONTWRITEBYTECODE): without it each pytest worker and each `closedloop` subprocess
    compiles the package again and pytest rewrites every test module again (collection about 12 s of CPU a
    worker, against 3.5 s).  Set before the workers start: they inherit it."""
    os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
    sys.dont_write_bytecode = False


@pytest.fixture(scope="session")
def panda() -> RobotModel:
    return RobotModel.from_file(ROBOTS["panda"].path)


@pytest.fixture(scope="session")
def panda_weld(panda):
    """200 exact configurations of the Panda hand welded to an unknown world pose."""
    return make_dataset(panda, WeldLoop("fixture", "panda_hand"), PANDA_Q0, 200, np.random.default_rng(7))


@pytest.fixture(scope="session")
def panda_manifold_weld():
    """A Panda welded to a fixture, 40 exact configurations spread over the whole self-motion (a walk of 5 s):
    the modules that read it share one xdist group (`SHARED`), so one worker computes it once."""
    from closedloop.studies.montecarlo import weld_scenario

    return weld_scenario(n=1, seed=3, pool="manifold", n_pool=40)


@pytest.fixture(scope="session")
def package_trees() -> dict[Path, ast.Module]:
    """Every module of ``closedloop/`` parsed with `ast` (nothing imported), by path: the checks on the package's
    source read it (1-2 s to parse), in one xdist group (`SHARED`)."""
    package = Path(__file__).resolve().parents[1] / "closedloop"
    return {p: ast.parse(p.read_text(), filename=str(p)) for p in sorted(package.rglob("*.py"))}


# --------------------------------------------------------------------------- one worker per costly fixture
# A fixture scoped to its module (a simulated dataset, a calibration the tests then read) is computed once per
# worker that runs one of its tests, and again whenever that worker ran another module's test in between: a
# module with such a fixture runs whole on one worker (xdist's `loadgroup`), so the fixture is computed once.
# The modules reading one of the session fixtures in `SHARED` run on one worker too, in a group named by it.
SHARED = ("panda_manifold_weld", "package_trees")


@pytest.hookimpl(tryfirst=True)  # before xdist reads the groups
def pytest_collection_modifyitems(config, items):
    def own_module_fixture(item) -> bool:
        info = getattr(item, "_fixtureinfo", None)
        return info is not None and any(
            fd.scope == "module" and str(fd.baseid).endswith(".py")
            for name in info.names_closure
            for fd in info.name2fixturedefs.get(name, ())
        )

    grouped = {item.nodeid.split("::")[0]: item.nodeid.split("::")[0] for item in items if own_module_fixture(item)}
    for item in items:
        for name in SHARED:
            if name in getattr(item, "fixturenames", ()):
                grouped[item.nodeid.split("::")[0]] = name
    for item in items:
        module = item.nodeid.split("::")[0]
        if module in grouped and item.get_closest_marker("xdist_group") is None:
            item.add_marker(pytest.mark.xdist_group(grouped[module]))


# --------------------------------------------------------------------------- what the run left out
# The default run deselects the `slow` tests (pyproject.toml: -m 'not slow'); the summary says how many and how
# to run them.  Under xdist each worker collects the whole suite and deselects the same tests: the workers pass
# their count to the controller (`workeroutput`), which reports it once.
_DESELECTED: dict[str, int] = {"slow": 0}


def pytest_deselected(items):
    _DESELECTED["slow"] += sum(1 for it in items if it.get_closest_marker("slow") is not None)


def pytest_sessionfinish(session):
    out = getattr(session.config, "workeroutput", None)
    if out is not None:  # an xdist worker
        out["slow_deselected"] = _DESELECTED["slow"]


try:
    import xdist  # noqa: F401  (its hook below exists only with it)
except ImportError:
    pass
else:

    def pytest_testnodedown(node, error):
        got = getattr(node, "workeroutput", {}).get("slow_deselected", 0)
        _DESELECTED["slow"] = max(_DESELECTED["slow"], got)


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    n = _DESELECTED["slow"]
    if n and "not slow" in (config.getoption("markexpr") or ""):
        terminalreporter.write_line(f"{n} slow tests not run (the long studies and basins): pytest -m slow")
