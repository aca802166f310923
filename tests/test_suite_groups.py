"""The suite's own distribution: under xdist (`-n 2 --dist loadgroup`, pyproject.toml) a module with a fixture
of its own runs whole on one worker (`conftest.pytest_collection_modifyitems`), so the fixture is computed once."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module")
def computed_once():
    return object()


def test_a_module_with_its_own_fixture_runs_on_one_worker(request, computed_once):
    if not getattr(request.config.option, "loadgroup", False):
        pytest.skip("checks the xdist workers' grouping: run under `-n 2 --dist loadgroup` (the default)")
    assert request.node.nodeid.endswith("@tests/test_suite_groups.py"), (
        f"{request.node.nodeid}: the xdist group did not reach the scheduler (a pytest release that drops "
        "pytest-xdist's loadgroup suffix: see the pin in pyproject.toml)"
    )
