"""How many configurations for a given accuracy, with and without pose selection (7-DOF weld).

Pool: ~1000 exact self-motion configurations of the Panda welded at the hand.
For N random configurations (median over draws) the trace of the covariance
of the estimated parameters (from the information matrix at the current
estimate, prior-scaled units and physical units); then the smallest K of a
greedy D-optimal selection (and DETMAX at that K) reaching the same trace;
and, calibrating noisy readings of both sets, the held-out closure error of
the calibrated model on 200 exact configurations (calibrate needs >= 10
configurations here: 55 parameters are selected before the reduction) of the true closure
manifold (the truth's own closure error there is 0) and the parameter error
against the truth in units of the CRB standard errors.

    python benchmarks/bench_pose_selection.py
"""

import time

import numpy as np

from closedloop import CalibrationOptions, calibrate
from closedloop.calibration import residual_stats
from closedloop.montecarlo import unwrap, weld_scenario
from closedloop.poses import detmax, greedy_d_optimal, pool_blocks, trace_covariance

NOISE = 1e-4
t0 = time.time()
sc = weld_scenario(n=200, seed=0, n_pool=1000)  # theta: held-out set; pool: candidates
rng = np.random.default_rng(1)
pool, held = sc.pool, sc.theta
# current estimate: a calibration on 60 random pool configurations
first = rng.choice(len(pool), 60, replace=False)
res0 = calibrate(sc.robot, sc.log(pool[first] + rng.normal(0, NOISE, (60, 7))), sc.loops,
                 CalibrationOptions(noise=NOISE))
B, est = pool_blocks(res0, None, pool)
prior = np.array([res0.problem.params[k].prior for k in est])
greedy = greedy_d_optimal(B, 200)
prefix_trace = np.array([trace_covariance(B, greedy.indices[:k]) if k >= 5 else np.inf for k in range(201)])
print(f"pool {len(pool)} configurations, {len(est)} estimated parameters, setup {time.time() - t0:.1f} s")

truth = np.array([sc.truth[n] for n in res0.problem.names])


def evaluate(rows):
    th = pool[rows] + rng.normal(0, NOISE, (len(rows), 7))
    r = calibrate(sc.robot, sc.log(th), sc.loops, CalibrationOptions(noise=NOISE))
    ev = r.problem.evaluate(r.values, False, [held])
    st = residual_stats(r.problem, ev)[0]
    v = unwrap(r.problem, r.values, truth)
    return st.rms_m, st.rms_rad, r


print(f"\n{'N':>4} {'tr rand (scaled)':>16} {'tr rand (SI)':>12} {'K greedy':>8} {'tr sel':>9} {'K detmax':>8}"
      f" | {'held-out rand m / rad':>22} {'held-out sel m / rad':>22}")
for N in (10, 15, 20, 30, 40, 60, 80, 120, 160):
    draws = [rng.choice(len(pool), N, replace=False) for _ in range(25)]
    tr = [trace_covariance(B, d) for d in draws]
    med = int(np.argsort(tr)[len(tr) // 2])
    tr_med = tr[med]
    tr_si = trace_covariance(B, draws[med], prior)
    ks = np.flatnonzero(prefix_trace <= tr_med)
    K = int(ks[0]) if ks.size else None
    Kd = None
    if K is not None:  # DETMAX at decreasing K while it still reaches the target
        Kd = K
        while Kd > 5 and trace_covariance(B, detmax(B, Kd - 1).indices) <= tr_med:
            Kd -= 1
    rm, rr, _ = evaluate(draws[med])
    if K is not None and K >= 10:
        sm, sr, _ = evaluate(greedy.indices[:K])
        sel = f"{sm:.2e} / {sr:.2e}"
    else:  # calibrate needs at least as many equations as selected parameters (55 here: 10 configurations)
        sel = "- (K < 10)" if K is not None else "-"
    print(f"{N:4d} {tr_med:16.4g} {tr_si:12.3e} {K if K else '>200':>8} "
          f"{prefix_trace[K] if K else float('nan'):9.4g} {Kd if Kd else '-':>8} | {rm:.2e} / {rr:.2e}   {sel}")
print(f"\n({time.time() - t0:.0f} s)")
