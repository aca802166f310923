"""Shared fixtures: the Panda from example-robot-data and pure-kinematic weld datasets."""

from __future__ import annotations

import numpy as np
import pytest

from closedloop.assets.catalog import ROBOTS
from closedloop.loops import WeldLoop
from closedloop.model.robot import RobotModel
from closedloop.studies.truth import make_dataset

PANDA_Q0 = [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8]


@pytest.fixture(scope="session")
def panda() -> RobotModel:
    return RobotModel.from_file(ROBOTS["panda"].path)


@pytest.fixture(scope="session")
def panda_weld(panda):
    """200 exact configurations of the Panda hand welded to an unknown world pose."""
    return make_dataset(panda, WeldLoop("fixture", "panda_hand"), PANDA_Q0, 200, np.random.default_rng(7))
