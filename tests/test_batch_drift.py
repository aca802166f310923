"""Drift between calibrations in one gauge (closedloop.fleet.drift): a gauge change alone (another
length fixed for the scale, hence another reduction) is not flagged; a drifting joint offset is
flagged only when larger than its uncertainty, whichever gauge each calibration used."""

from __future__ import annotations

import numpy as np
import pytest

from closedloop import CalibrationOptions, calibrate
from closedloop.calibration.pipeline import build_problem
from closedloop.fleet.drift import compare, gauge_record, in_gauge_of
from closedloop.model.parameters import parse_fix

NOISE = 1e-5  # a good encoder: the standard errors are small beside a gauge change
JOINT = "panda_joint4"


@pytest.fixture(scope="module", autouse=True)
def one_blas_thread():
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        yield


@pytest.fixture(scope="module")
def sc(panda_manifold_weld):
    """A Panda welded to a fixture, 40 configurations spread over the whole self-motion (conftest's, shared
    with the other module of this xdist group)."""
    return panda_manifold_weld


def calibrated(sc, offset_drift: float, seed: int, fix: str | list[str] | None) -> dict:
    """The gauge record of a calibration of logs where joint 4's offset grew by `offset_drift` rad,
    holding the length `fix` at its nominal value (the length that sets the scale, thesis 3.3;
    None: calibrate's own choice, panda_joint4.y)."""
    rng = np.random.default_rng(seed)
    k, scale = sc.joints.index(JOINT), sc.truth[f"{JOINT}.scale"]
    th = sc.pool.copy()
    th[:, k] -= offset_drift / scale
    th += rng.normal(0.0, NOISE, th.shape)
    lg = sc.log(th)
    names = build_problem(sc.robot, lg, sc.loops).names
    res = calibrate(
        sc.robot,
        lg,
        sc.loops,
        CalibrationOptions(noise=NOISE, fix=parse_fix([fix] if isinstance(fix, str) else fix or [], names)),
    )
    assert res.converged
    return gauge_record(res)


def estimated(g: dict) -> set[str]:
    return {g["names"][k] for k in g["estimated"]}


def naive_max_z(a: dict, b: dict) -> float:
    """Plain differences of the parameters both estimated, ignoring the gauge (what not to do)."""
    ia, ib = {g: i for i, g in enumerate(a["estimated"])}, {g: i for i, g in enumerate(b["estimated"])}
    ca, cb = np.asarray(a["covariance"]), np.asarray(b["covariance"])
    z = [
        (b["values"][k] - a["values"][k]) / np.sqrt(ca[ia[k], ia[k]] + cb[ib[k], ib[k]])
        for k in ia
        if k in ib and a["kinds"][k] != "loop"
    ]
    return float(np.max(np.abs(z)))


def test_gauge_change_alone_is_not_drift(sc):
    a = calibrated(sc, 0.0, 1, None)  # the scale held by panda_joint4.y (0.316 m)
    b = calibrated(sc, 0.0, 2, f"{JOINT}.x")  # the same robot, the scale held by joint 4's x (0.0825 m, 1.6 % off)
    assert estimated(a) != estimated(b)  # another gauge: another parameter set
    assert naive_max_z(a, b) > 10.0  # plain differences would flag the gauge change
    rows = compare("arm", "a", "b", a, b, 3.0)
    assert len(rows) >= 20 and not any(r.note for r in rows)
    assert max(abs(r.z) for r in rows) < 3.0, [(r.parameter, r.z) for r in rows if abs(r.z) >= 3.0]
    # the move holds A's fixed values: B's vector in A's gauge keeps joint 4's x at A's (nominal) value
    pb, _, cost = in_gauge_of(a, b)
    ky = a["names"].index(f"{JOINT}.y")
    assert abs(pb[ky] - a["values"][ky]) < 1e-12 and cost < 1.0  # a gauge move: the closures barely change
    kx = a["names"].index(f"{JOINT}.x")  # ...and B, re-expressed, finds the length it held (truth -1.36 mm)
    assert abs(pb[kx] - sc.truth[f"{JOINT}.x"]) < 2e-4 and abs(b["values"][kx]) < 1e-12
    # the other way round too
    assert max(abs(r.z) for r in compare("arm", "b", "a", b, a, 3.0)) < 3.0
    # same gauge, same robot: nothing flagged either, and the move is zero
    c = calibrated(sc, 0.0, 2, None)
    rows = compare("arm", "a", "c", a, c, 3.0)
    assert max(abs(r.z) for r in rows) < 3.0
    if estimated(a) == estimated(c):
        assert np.allclose(in_gauge_of(a, c)[0], c["values"], atol=1e-12)


@pytest.mark.parametrize("drift, flagged", [(2.5e-6, False), (6e-5, True)])
def test_offset_drift_flagged_only_above_its_uncertainty(sc, drift, flagged):
    """Joint 4's offset drifts by 0.4x / ~10x the standard error of a change (~6 urad here), and the
    later calibration is also in another gauge."""
    a = calibrated(sc, 0.0, 1, None)
    b = calibrated(sc, drift, 2, f"{JOINT}.x")
    rows = {r.parameter: r for r in compare("arm", "a", "b", a, b, 3.0)}
    off = rows[f"{JOINT}.offset"]
    assert 3e-6 < off.se < 12e-6
    assert abs(off.change - drift) < 4 * off.se  # the change is measured, in A's gauge
    assert off.flagged is flagged
    others = [r for name, r in rows.items() if name != f"{JOINT}.offset" and r.flagged]
    assert not others, [(r.parameter, r.z) for r in others]


def test_a_change_where_the_earlier_calibration_holds_a_value_is_flagged(sc):
    """The earlier calibration also held joint 6's x at nominal, a length the data determine (truly
    0.95 mm): not a gauge but a wrong value.  The later one, which estimates it, cannot be put in that
    gauge without spoiling its closures: the pair gets a flagged row '*' naming the held parameter.
    (Holding joint 4's offset or joint 2's instead is only another gauge of the weld: no row.)"""
    a = calibrated(sc, 0.0, 1, [f"{JOINT}.x", "panda_joint6.x"])
    b = calibrated(sc, 0.0, 2, f"{JOINT}.x")
    rows = compare("arm", "a", "b", a, b, 3.0)
    star = [r for r in rows if r.parameter == "*"]
    assert len(star) == 1 and star[0].flagged and "panda_joint6.x" in star[0].note
    assert in_gauge_of(a, b)[2] > 1e3  # chi^2 of the later closures in that gauge
    for held in (f"{JOINT}.offset", "panda_joint2.offset"):
        c = calibrated(sc, 0.0, 1, [f"{JOINT}.x", held])
        assert in_gauge_of(c, b)[2] < 1.0
        assert not [r for r in compare("arm", "c", "b", c, b, 3.0) if r.flagged]
