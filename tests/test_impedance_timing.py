"""Cycle-onset timing: jittered onsets found by the model's split-half test and re-aligned, with the errors
back at the aligned values; no alarm on aligned records (elbow truths and the thesis forearm)."""

from __future__ import annotations

import numpy as np
import pytest

from closedloop.impedance.data import onsets_from_events, recut, segment
from closedloop.impedance.elbow import ElbowConfig, simulate_elbow
from closedloop.impedance.estimate import EstimateOptions, estimate
from closedloop.impedance.metrics import rel_errors
from closedloop.impedance.model import ExperimentConfig
from closedloop.impedance.simulation import simulate
from closedloop.impedance.timing import Z_ALARM, check_onsets, check_timing


def jittered(onsets, fs, ms, seed):
    """The onsets moved by uniform +-ms (whole samples) and the moves."""
    d = np.round(np.random.default_rng(seed).uniform(-ms, ms, len(onsets)) * 1e-3 * fs).astype(int)
    return [(b, i + k) for (b, i), k in zip(onsets, d)], d


def identify(rec, onsets):
    """`identify`'s path with the defaults: segment, estimate, check the onsets (re-align when off)."""
    opt = EstimateOptions()
    ens = segment(rec, onsets, period=2.0)
    est = estimate(ens, options=opt, warn=False)
    return ens, est, check_timing(rec, ens, est, opt)


@pytest.fixture(scope="module")
def forearm():
    sim = simulate(ExperimentConfig(seed=3))
    return sim.record, sim.truth


def test_forearm_jitter_found_and_realigned(forearm):
    rec, truth = forearm
    on = onsets_from_events(rec)
    ens, est, out = identify(rec, on)
    assert not out.summary["misaligned"] and abs(out.summary["z"]) < Z_ALARM and not out.notes and not out.warnings
    base = rel_errors(est, truth)
    assert max(base.values()) < 1.2, base

    jon, d = jittered(on, rec.fs, 10, seed=4)
    jens, jest, out = identify(rec, jon)
    before = rel_errors(jest, truth)
    assert max(before.values()) > 2.0, before  # the harm: 2-4 % on I, B, K
    s = out.summary
    assert s["misaligned"] and s["realigned"] and s["z"] > 8 and 4.5 < s["timing_error_std_ms"] < 7.0, s
    assert any("re-aligned by the model" in n for n in out.notes) and not out.warnings
    # the onsets found again up to a common offset: within one sample (1.7 ms) for every cycle
    moved = out.ensemble.onsets[:, 1] - np.array([i for _, i in on])
    assert np.max(np.abs(moved - np.median(moved))) <= 1, moved
    after = rel_errors(out.estimate, truth)
    for k in "IBK":
        assert after[k] <= base[k] + 0.15 and after[k] < 1.2, (k, after, base)


def test_forearm_voluntary_no_alarm():
    sim = simulate(ExperimentConfig(seed=3, voluntary_rms=0.5))
    rec = sim.record
    ens, est, out = identify(rec, onsets_from_events(rec))
    assert est.options.method == "iv"
    assert not out.summary["misaligned"] and not out.notes and not out.warnings, out.summary


def test_elbow_jitter_found_and_realigned():
    """The independent elbow on a coarser grid (short blocks, 2 RK4 substeps: fast), constant K."""
    rec, truth = simulate_elbow(ElbowConfig(seed=1, cycles_per_block=3, substeps=2))
    on = onsets_from_events(rec)
    ens, est, out = identify(rec, on)
    assert not out.summary["misaligned"]
    base = rel_errors(est, truth)
    jon, _ = jittered(on, rec.fs, 10, seed=5)
    _, jest, out = identify(rec, jon)
    assert out.summary["misaligned"] and out.summary["realigned"]
    after, before = rel_errors(out.estimate, truth), rel_errors(jest, truth)
    for k in "IBK":
        assert before[k] > base[k] + 1.0 and after[k] <= base[k] + 0.2 and after[k] < 1.2, (k, before, after, base)


def test_none_warns_with_the_remedy(forearm):
    rec, _ = forearm
    jon, _ = jittered(onsets_from_events(rec), rec.fs, 10, seed=4)
    ens = segment(rec, jon, period=2.0)
    est = estimate(ens, warn=False)
    out = check_timing(rec, ens, est, allow_realign=False)
    assert out.ensemble is ens and out.estimate is est and not out.notes
    assert len(out.warnings) == 1 and "misaligned" in out.warnings[0] and "--align auto" in out.warnings[0]


def test_timing_errors_are_the_shifts(forearm):
    """Per-cycle timing errors (s) against known whole-sample shifts, in one pass (the model fitted to the
    jittered cycles): slope near 1, scatter under 1 ms; `realign` iterates from there."""
    rec, _ = forearm
    on = onsets_from_events(rec)
    jon, d = jittered(on, rec.fs, 10, seed=6)
    ens = segment(rec, jon, period=2.0)
    chk = check_onsets(ens, estimate(ens, warn=False).options)
    true = (d - d.mean()) / rec.fs
    slope = np.polyfit(true, chk.errors, 1)[0]
    assert 0.85 < slope < 1.05 and np.std(chk.errors - slope * true) < 1e-3, slope
    assert chk.misaligned and chk.noise < 1.5e-3


def test_recut_moves_onsets_and_keeps_the_impossible(forearm):
    rec, _ = forearm
    ens = segment(rec, onsets_from_events(rec), period=2.0)
    shifts = np.zeros(ens.n, int)
    shifts[0], shifts[1] = 5, -(10**6)  # a move out of its block keeps the onset
    new = recut(rec, ens, shifts)
    assert new.onsets[0, 1] == ens.onsets[0, 1] + 5 and new.onsets[1, 1] == ens.onsets[1, 1]
    assert np.array_equal(new.alignment.shifts[:2], [5, 0])
    assert np.allclose(new.angle[0, :-5], ens.angle[0, 5:]) and np.array_equal(new.angle[2:], ens.angle[2:])


@pytest.mark.slow
@pytest.mark.parametrize(
    "kw",
    [{}, {"stiffness": "dip"}, {"stiffness": "ramp-b"}, {"stiffness": "square"}, {"voluntary_rms": 0.5}],
    ids=["constant", "dip", "ramp-b", "square", "voluntary"],
)
def test_elbow_truths(kw):
    """The five elbow truths at the full setting: no alarm on aligned onsets; +-10 ms jitter found and
    re-aligned to the aligned errors (voluntary torque: the jitter is below the detector's reach there,
    and does not measurably change the IV estimate)."""
    rec, truth = simulate_elbow(ElbowConfig(seed=2, **kw))
    on = onsets_from_events(rec)
    _, est, out = identify(rec, on)
    assert not out.summary["misaligned"] and not out.notes and not out.warnings, out.summary
    base = rel_errors(est, truth)
    jon, _ = jittered(on, rec.fs, 10, seed=7)
    _, jest, out = identify(rec, jon)
    after = rel_errors(out.estimate, truth)
    if "voluntary_rms" in kw:
        assert max(after.values()) <= 10.0, after
        return
    assert out.summary["misaligned"] and out.summary["realigned"], out.summary
    for k in "IBK":
        assert after[k] <= base[k] + 0.35, (k, after, base)


def test_identify_notes_the_realignment(tmp_path, capsys):
    """`identify --segment onsets:FILE` with onsets jittered by +-10 ms: a note, errors at the aligned
    values; with the true onsets, no note; `--align none`: the warning, and the biased estimate."""
    import json

    from closedloop.cli.main import main
    from closedloop.impedance.data import write_record
    from closedloop.impedance.results import write_truth

    sim = simulate(ExperimentConfig(n_cycles=40, seed=3))
    rec = sim.record
    write_record(tmp_path / "data.csv", rec)
    write_truth(tmp_path / "truth.csv", sim.truth)
    times = np.array([rec.time[rec.block == b][i] for b, i in onsets_from_events(rec)])
    wrong = times + np.random.default_rng(8).uniform(-0.01, 0.01, times.size)
    np.savetxt(tmp_path / "true.txt", times, fmt="%.6f")
    np.savetxt(tmp_path / "wrong.txt", wrong, fmt="%.6f")
    base = ["impedance", "identify", str(tmp_path / "data.csv"), "--truth", str(tmp_path / "truth.csv")]
    base += ["--bootstrap", "0", "--folds", "0"]
    errs = {}
    for name, extra in (("true", []), ("wrong", []), ("none", ["--align", "none"])):
        onsets = tmp_path / ("true.txt" if name == "true" else "wrong.txt")
        res = tmp_path / f"{name}.json"
        assert main(base + ["--segment", f"onsets:{onsets}", "--out", str(res)] + extra) == 0
        std = capsys.readouterr()
        s = json.loads(res.read_text())["summary"]
        errs[name] = s["errors_vs_truth_percent"]
        if name == "true":
            assert not s["onset_check"]["misaligned"] and "misaligned" not in std.out + std.err
        elif name == "wrong":
            assert s["onset_check"]["realigned"] and "note: the cycle onsets are misaligned" in std.out
            assert "misaligned" not in std.err
        else:
            assert not s["onset_check"]["realigned"] and "--align auto" in std.err
    for k in "IBK":
        assert errs["wrong"][k] <= errs["true"][k] + 0.15 < errs["none"][k], errs
