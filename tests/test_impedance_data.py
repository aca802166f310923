"""Impedance data I/O, segmentation, exclusion and alignment (thesis 9.5.1)."""

from __future__ import annotations

import numpy as np
import pytest

from closedloop.errors import InputError
from closedloop.impedance.data import (
    Record,
    onsets_from_events,
    onsets_from_peak_velocity,
    onsets_from_times,
    read_record,
    segment,
    write_record,
)
from closedloop.impedance.model import ExperimentConfig
from closedloop.impedance.simulation import simulate


@pytest.fixture(scope="module")
def sim():
    return simulate(ExperimentConfig(n_cycles=20, noise=0.05, seed=3))


@pytest.fixture(scope="module")
def quiet():
    """Weak perturbation: the movement itself, not the perturbation responses, sets the peak velocity."""
    return simulate(ExperimentConfig(n_cycles=20, noise=0.0, seed=3, prbs_amplitude=0.02))


@pytest.mark.parametrize("suffix", [".csv", ".h5"])
def test_round_trip(sim, tmp_path, suffix):
    path = tmp_path / f"d{suffix}"
    write_record(path, sim.record)
    back = read_record(path)
    assert np.allclose(back.angle, sim.record.angle, rtol=1e-8, atol=1e-12)
    assert np.allclose(back.torque, sim.record.torque, rtol=1e-8, atol=1e-12)
    assert np.array_equal(back.event, sim.record.event) and np.array_equal(back.block, sim.record.block)


def test_bad_files(tmp_path):
    p = tmp_path / "bad.csv"
    p.write_text("time,angle\n0,0\n")
    with pytest.raises(InputError, match="missing column 'torque'"):
        read_record(p)
    with pytest.raises(InputError, match="no such file"):
        read_record(tmp_path / "none.csv")
    rows = [f"{i / 600},0,0" for i in range(20)]
    p.write_text("time,angle,torque\n" + "\n".join(rows[:5] + [rows[4]] + rows[5:]))
    with pytest.raises(InputError, match="row 7 repeats the time"):
        read_record(p)
    p.write_text("time,angle,torque\n" + "\n".join(rows[:3] + ["nan,0,0"] + rows[4:]))
    with pytest.raises(InputError, match="'time' row 5 is not finite"):
        read_record(p)
    p.write_text("time,angle,torque\n" + "\n".join(rows[:8] + ["0.02,abc,0"] + rows[9:]))
    with pytest.raises(InputError, match="bad.csv line 10, column 'angle': 'abc' is not a number"):
        read_record(p)  # the file's line (numpy counts data rows from 0) and the column's name


def test_non_finite_rows_leave_out_their_cycles(sim, tmp_path):
    """A block of NaN samples: the file is read, the cycles that touch it are left out, with a note."""
    path = tmp_path / "d.csv"
    write_record(path, sim.record)
    lines = path.read_text().splitlines()
    for k in range(3001, 3061):  # 0.1 s of NaN angle and torque, inside one cycle
        cells = lines[k].split(",")
        cells[1] = cells[2] = "nan"
        lines[k] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    rec = read_record(path)
    assert rec.valid is not None and (~rec.valid).sum() == 60
    assert any("non-finite" in n and "row 3002" in n for n in rec.notes)
    ens = segment(rec, onsets_from_events(rec))
    assert ens.excluded["non-finite samples"] >= 1 and ens.n >= 17
    assert np.all(np.isfinite(ens.angle)) and np.all(np.isfinite(ens.torque))


def test_gaps_split_the_record(sim):
    """Rows deleted from the record: time jumps, the record is split there and no cycle crosses a gap."""
    rec = sim.record
    keep = np.ones(len(rec.time), bool)
    for c in (3, 7, 15):  # 0.1 s deleted in three usable cycles
        keep[c * 1200 + 400 : c * 1200 + 460] = False
    cut = Record(rec.time[keep], rec.angle[keep], rec.torque[keep], rec.command[keep], rec.event[keep], rec.block[keep])
    import tempfile

    from closedloop.impedance.data import record_bytes

    with tempfile.NamedTemporaryFile(suffix=".csv") as fh:
        fh.write(record_bytes(cut))
        fh.flush()
        back = read_record(fh.name)
    assert any("gaps in time" in n for n in back.notes)
    assert len(np.unique(back.block)) == len(np.unique(rec.block)) + 3
    ens = segment(back, onsets_from_events(back))
    full = segment(rec, onsets_from_events(rec))
    assert ens.n <= full.n - 3  # the three cycles with a gap are left out
    # every kept cycle is a real, uncut one: its angle matches the full record's cycle at the same time
    assert np.max(np.abs(ens.angle.mean(0) - full.angle.mean(0))) < 0.01


def test_columns_mapped_and_unknown_reported(sim, tmp_path):
    path = tmp_path / "lab.csv"
    write_record(path, sim.record)
    text = path.read_text().splitlines()
    head = text[0].replace("torque", "tau").replace("command", "perturbation") + ",emg"
    path.write_text("\n".join([head] + [ln + ",0" for ln in text[1:]]) + "\n")
    with pytest.raises(InputError, match="--columns torque=NAME"):
        read_record(path)
    from closedloop.impedance.data import parse_columns

    rec = read_record(path, parse_columns("torque=tau,command=perturbation"))
    assert np.allclose(rec.torque, sim.record.torque, rtol=1e-8, atol=1e-12)
    assert np.allclose(rec.command, sim.record.command, rtol=1e-8, atol=1e-12)
    assert any("ignored columns emg" in n for n in rec.notes)
    with pytest.raises(InputError, match="no column 'force'"):
        read_record(path, parse_columns("torque=force"))
    with pytest.raises(InputError, match="NAME=COLUMN"):
        parse_columns("torque")


def test_csv_named_h5_is_read_as_csv(sim, tmp_path):
    path = tmp_path / "d.h5"
    path.write_bytes(__import__("closedloop.impedance.data", fromlist=["x"]).record_bytes(sim.record))
    assert np.allclose(read_record(path).angle, sim.record.angle, rtol=1e-8, atol=1e-12)


def test_segmentation_methods_agree(quiet):
    rec = quiet.record
    ev = onsets_from_events(rec)
    assert len(ev) == 20
    ens = segment(rec, ev)
    assert ens.n == 20 and ens.length == 1200 and ens.excluded["incomplete padding"] == 0
    t_on = np.array([rec.time[rec.block == b][i] for b, i in ev])
    assert len(onsets_from_times(rec, t_on)) == 20
    pv = onsets_from_peak_velocity(rec, period=2.0, lead=0.5)  # peak velocity of 0.5 - 0.5 cos(pi t) at 0.5 s
    ens_pv = segment(rec, pv, period=2.0)
    assert ens_pv.n >= 18
    assert np.max(np.abs(ens_pv.mean()[0][ens.pad : -ens.pad] - ens.mean()[0][ens.pad : -ens.pad])) < 0.01


def test_exclusion_of_irregular_cycles(sim):
    rec = sim.record
    ev = onsets_from_events(rec)
    ev[5] = (ev[5][0], ev[5][1] + 300)  # a cycle that starts 0.5 s late
    ens = segment(rec, ev, period=2.0)
    assert ens.excluded["irregular length"] >= 1 and ens.n < 20


def test_peak_velocity_alignment_recovers_jitter(quiet):
    rec = quiet.record
    rng = np.random.default_rng(0)
    ev = onsets_from_events(rec)
    jit = rng.integers(-12, 13, len(ev))
    bad = [(b, i + j) for (b, i), j in zip(ev, jit)]
    ens = segment(rec, bad, period=2.0, align="peak-velocity", max_shift_s=0.05)
    err = ens.onsets[:, 1] - np.array([i for _, i in ev])
    assert np.max(np.abs(err - np.median(err))) <= 3  # 5 ms; the common offset is arbitrary
    rep = ens.alignment.summary()
    assert sum(rep["histogram"]["counts"]) == ens.n and rep["max_abs_ms"] <= 50.0 + 1e-9


def test_alignment_invents_shifts_on_periodic_perturbed_data(sim):
    """The alignment trap: perfectly periodic cycles, strong perturbations; peak-velocity + RMS
    re-alignment shifts them anyway, within the limit, and the diagnostics say so."""
    ens = segment(sim.record, onsets_from_events(sim.record), align="peak-velocity+rms", max_shift_s=0.05)
    rep = ens.alignment.summary()
    assert np.all(np.abs(ens.alignment.shifts) <= 30)
    assert rep["std_ms"] > 5.0 and rep["warnings"]
    ens = segment(sim.record, onsets_from_events(sim.record), align="rms", max_shift_s=0.01)
    assert np.all(np.abs(ens.alignment.shifts) <= 6)


def test_too_few_cycles():
    rec = Record(np.arange(100) / 600.0, np.zeros(100), np.zeros(100), event=np.r_[1, np.zeros(99)])
    with pytest.raises(InputError):
        segment(rec, onsets_from_events(rec), period=0.1)


def test_a_period_that_contradicts_the_onsets_is_refused():
    """Events 2 s apart with --period 3: one line naming both, not 90 of 100 cycles dropped in silence."""
    fs, L = 100.0, 200
    n = 12 * L
    ev = np.zeros(n)
    ev[::L] = 1
    rec = Record(np.arange(n) / fs, np.sin(np.arange(n) / 10), np.zeros(n), event=ev)
    with pytest.raises(InputError, match=r"--period 3: the onsets are 2 s apart \(median of 11\)"):
        segment(rec, onsets_from_events(rec), period=3.0)
    assert segment(rec, onsets_from_events(rec), period=2.0, pad_s=0.2).length == L
