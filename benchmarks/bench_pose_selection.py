"""How many configurations for a given accuracy, with and without pose selection.

The accuracy of a set of configurations is the trace of the covariance of the
estimated parameters (A-criterion), from the information matrix at the
current estimate (a calibration on 60 random pool configurations; prior-scaled
units, and physical units for reference).  For N random configurations of the
pool it is the median over 200 draws (the mean is dominated by rare bad
draws); for each selection method, the smallest K whose selection from the
SAME pool reaches that trace.  The selection never sees the truth.

7-DOF Panda welded to a fixture at the hand (one-dimensional self-motion).
Pool (--pool manifold, the default): 3,000 configurations evenly spaced along
the whole self-motion, joint limit to joint limit (every configuration the
robot can reach while holding the fixture on that branch;
``montecarlo.self_motion_manifold``).  --pool walk: the 1,000-configuration
self-motion walk of earlier versions (it bounces between the joint limits and
revisits the same arc about 20 times at 0.12 rad spacing).

Methods: greedy D-optimal and greedy A-optimal (forward selection; K from the
prefix of one 200-point run), DETMAX (D; K searched downwards from the greedy
K) and the A-optimal exchange (``exchange_a``; K searched from N/2 with warm
starts).  'poses': how many distinct poses (more than 0.1 rad apart) the
exchange-A set visits: the A-optimal design on a one-dimensional self-motion
repeats measurements at a few poses (its support), so K of them are mostly
near-replicates, as good as independent readings only if the reading errors
are independent from one visit to the next.  'I ratio': the expected squared
closure error of the calibrated model averaged over the pool (I-criterion,
tr(Cov mean_i B_i^T B_i)) of the exchange-A set over the median of the N
random ones: the A-criterion weights every parameter by its prior, this one
by how much the closure along the self-motion sees it, so a ratio near
N / K = 2 means selection gains nothing for predicting closures along that
same motion.  For random and exchange-A sets (K >= 10: calibrate needs 55
equations for the parameters it selects before the reduction) noisy readings
are calibrated and the held-out closure error on 200 exact configurations of
the true closure manifold is reported (the truth's own is 0).

The ratio c_uniform / c_optimal of the traces of the uniform design over the
pool and of the optimal continuous (approximate) A-design (multiplicative
algorithm, Silvey, Titterington & Torsney 1978; Frank-Wolfe lower bound)
is the most selection can gain for large N: as N grows, N random
configurations are matched by no fewer than N / ratio selected ones.

Then UR5 stylus in a ball socket (point contact, three-dimensional
self-motion), pool of 500 readings, the same comparison.

    python benchmarks/bench_pose_selection.py [--pool manifold|walk] [--n-pool 3000] [--no-calibrate] [--no-point]
"""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # 6 x 27 blocks: BLAS threads only contend
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from closedloop import CalibrationOptions, calibrate  # noqa: E402
from closedloop.calibration.pipeline import residual_stats  # noqa: E402
from closedloop.design.poses import detmax, exchange_a, greedy_d_optimal, information, pool_blocks, trace_covariance  # noqa: E402
from closedloop.studies.montecarlo import weld_scenario  # noqa: E402

ap = argparse.ArgumentParser()
ap.add_argument("--pool", choices=("manifold", "walk"), default="manifold")
ap.add_argument("--n-pool", type=int, default=None, help="default 3000 (manifold), 1000 (walk)")
ap.add_argument("--no-calibrate", action="store_true", help="skip the held-out calibrations")
ap.add_argument("--no-point", action="store_true", help="skip the point-contact part")
args = ap.parse_args()
n_pool = args.n_pool or (3000 if args.pool == "manifold" else 1000)

NOISE = 1e-4
DRAWS = 200
W_FINAL = 0.01  # exchange_a's last prior weight (prior_weight 1, continuation (0.1, 0.01))
t0 = time.time()


def median_random(B, N, rng):
    """The median trace of N random pool configurations over DRAWS draws, a draw that has it, and the
    median closure variance over the same draws."""
    draws = [rng.choice(len(B), N, replace=False) for _ in range(DRAWS)]
    tr = [trace_covariance(B, d) for d in draws]
    med = int(np.argsort(tr)[len(tr) // 2])
    return tr[med], draws[med], float(np.median([closure_variance(B, d) for d in draws]))


def closure_variance(B, rows):
    """Expected squared (whitened) closure error of the calibrated model, averaged over the pool:
    tr(Cov mean_i B_i^T B_i), Cov = (sum_{rows} B_i^T B_i)^-1 (the I-criterion over the pool)."""
    return float(np.sum(np.linalg.inv(information(B, rows)) * information(B)) / len(B))


def fmt(k):
    return str(k) if k is not None else "-"


def prefix_k(B, order, target, kmin):
    """Smallest K whose first K points of `order` reach `target` (None if none)."""
    for k in range(kmin, len(order) + 1):
        if trace_covariance(B, order[:k]) <= target:
            return k
    return None


def drop_cheapest(B, design):
    """`design` without the point whose removal raises the trace least (a warm start for K - 1)."""
    design = list(design)
    costs = [trace_covariance(B, np.array(design[:t] + design[t + 1 :])) for t in range(len(design))]
    t = int(np.argmin(costs))
    return design[:t] + design[t + 1 :]


def add_best(B, design):
    """`design` and the point that lowers the trace most (a warm start for K + 1)."""
    return list(greedy_d_optimal(B, len(design) + 1, W_FINAL, start=list(design), criterion="A").indices)


def search_exchange(B, target, k0, kmin):
    """Smallest K at which exchange_a reaches `target`: from k0 (greedy start, continuation), then
    one K at a time with warm starts exchanged at the final prior weight."""
    sel = exchange_a(B, k0)
    K = k0
    if trace_covariance(B, sel.indices) <= target:
        while K > kmin:
            s = exchange_a(B, K - 1, W_FINAL, start=drop_cheapest(B, sel.indices), continuation=())
            if trace_covariance(B, s.indices) > target:
                break
            K, sel = K - 1, s
    else:
        while trace_covariance(B, sel.indices) > target:
            if K >= len(B) // 2:
                return None, sel
            K += 1
            sel = exchange_a(B, K, W_FINAL, start=add_best(B, sel.indices), continuation=())
    return K, sel


def clusters(pool, rows, gap=0.1):
    """Number of distinct poses (joint-space gaps > `gap` rad between them) among `rows`."""
    th = pool[np.asarray(rows)]
    remaining = list(range(len(th)))
    n = 0
    while remaining:
        n += 1
        near = np.linalg.norm(th[remaining] - th[remaining[0]], axis=1) <= gap
        remaining = [r for r, x in zip(remaining, near) if not x]
    return n


def efficiency_ratio(B, iters=2000):
    """tr M(uniform)^-1 / tr M(w*)^-1, w* the A-optimal continuous design on the pool.

    Multiplicative algorithm w_i <- w_i tr(M^-1 M_i M^-1) / tr(M^-1); returns the ratio and an
    upper bound on it from the Frank-Wolfe gap (tr M^-1 - (max_i d_i - sum_i w_i d_i) <= optimum).
    """
    n = len(B)
    Mi = np.einsum("nki,nkj->nij", B, B)
    c_unif = float(np.trace(np.linalg.inv(Mi.mean(axis=0))))
    w = np.full(n, 1.0 / n)
    for _ in range(iters):
        Minv = np.linalg.inv(np.einsum("n,nij->ij", w, Mi))
        T = B @ Minv
        d = np.einsum("nkl,nkl->n", T, T)
        w = w * d / (w @ d)
    c = float(np.trace(Minv))
    lower = c - (float(d.max()) - float(w @ d))
    return c_unif / c, c_unif / lower


# --------------------------------------------------------------------------- weld
sc = weld_scenario(n=200, seed=0, n_pool=n_pool, pool=args.pool)  # theta: held-out set; pool: candidates
rng = np.random.default_rng(1)
pool, held = sc.pool, sc.theta
first = rng.choice(len(pool), 60, replace=False)  # the current estimate
res0 = calibrate(
    sc.robot, sc.log(pool[first] + rng.normal(0, NOISE, (60, 7))), sc.loops, CalibrationOptions(noise=NOISE)
)
B, est = pool_blocks(res0, None, pool)
prior = np.array([res0.problem.params[k].prior for k in est])
L = len(est)
kmin = int(np.ceil(L / B.shape[1]))
greedy = greedy_d_optimal(B, 200).indices
greedy_a = greedy_d_optimal(B, 200, criterion="A").indices
ratio, ratio_hi = efficiency_ratio(B)
print(
    f"7-DOF weld, pool '{args.pool}': {len(pool)} configurations, {L} estimated parameters "
    f"(K >= {kmin}), setup {time.time() - t0:.0f} s"
)
print(f"uniform / optimal continuous A-design: {ratio:.3f} (<= {ratio_hi:.3f})")


def evaluate(rows):
    th = pool[rows] + rng.normal(0, NOISE, (len(rows), 7))
    r = calibrate(sc.robot, sc.log(th), sc.loops, CalibrationOptions(noise=NOISE))
    st = residual_stats(r.problem, r.problem.evaluate(r.fit.values, False, [held]))[0]
    return st.rms_m, st.rms_rad


print(
    f"\n{'N':>4} {'tr rand':>9} {'tr rand SI':>10} | {'K greedy':>8} {'K detmax':>8} {'K greedy-a':>10}"
    f" {'K exch-a':>8} {'tr sel':>9} {'K/N':>5} {'poses':>5} {'I ratio':>7} | {'held-out rand m / rad':>21}"
    f"  {'held-out sel m / rad':>21}"
)
rows = []
for N in (10, 15, 20, 30, 40, 60, 80, 120, 160, 200):
    tr_med, draw, cv_med = median_random(B, N, rng)
    tr_si = trace_covariance(B, draw, prior)
    Kg = prefix_k(B, greedy, tr_med, kmin)
    Kga = prefix_k(B, greedy_a, tr_med, kmin)
    Kd = Kg
    if Kd is not None:  # DETMAX at decreasing K while it still reaches the target
        while Kd > kmin and trace_covariance(B, detmax(B, Kd - 1).indices) <= tr_med:
            Kd -= 1
    Ke, sel = search_exchange(B, tr_med, max(N // 2, kmin), kmin)
    cal = ""
    if not args.no_calibrate:
        rm, rr = evaluate(draw)
        cal = f"{rm:.2e} / {rr:.2e}  "
        if Ke is not None and Ke >= 10:
            sm, sr = evaluate(sel.indices)
            cal += f"{sm:.2e} / {sr:.2e}"
        else:
            cal += "- (K < 10)"
    print(
        f"{N:4d} {tr_med:9.4g} {tr_si:10.3e} | {fmt(Kg):>8} {fmt(Kd):>8} {fmt(Kga):>10} {fmt(Ke):>8} "
        f"{trace_covariance(B, sel.indices):9.4g} {(Ke or np.nan) / N:5.2f} {clusters(pool, sel.indices):5d} "
        f"{closure_variance(B, sel.indices) / cv_med:7.2f} | {cal}",
        flush=True,
    )
    rows.append((N, Ke))
print(
    f"weld: K <= N/2 with exchange-a for N = {', '.join(str(n) for n, k in rows if k is not None and k <= n // 2)}"
    f" ({time.time() - t0:.0f} s)"
)

# --------------------------------------------------------------------------- point contact
if not args.no_point:
    from closedloop.assets.catalog import ROBOTS
    from closedloop.io.logs import JointLog
    from closedloop.loops import PointLoop
    from closedloop.model.robot import RobotModel
    from closedloop.studies.truth import make_dataset

    t1 = time.time()
    robot = RobotModel.from_file(ROBOTS["ur5"].path)
    rng = np.random.default_rng(4)
    loop = PointLoop("socket", "tool0", tip=np.array([0.0, 0.05, 0.1]))
    ds = make_dataset(robot, loop, [0.3, -1.3, 1.7, -1.9, -1.57, 0.2], 500, rng, stride=1, noise=NOISE)
    res = calibrate(
        robot, JointLog(ds.joints, ds.noisy[:150]), [PointLoop("socket", "tool0", tip=np.array([0.0, 0.05, 0.1]))]
    )
    Bp, estp = pool_blocks(res, None, ds.noisy)
    kminp = int(np.ceil(len(estp) / Bp.shape[1]))
    gp = greedy_d_optimal(Bp, 250).indices
    gpa = greedy_d_optimal(Bp, 250, criterion="A").indices
    ratio, ratio_hi = efficiency_ratio(Bp)
    print(
        f"\nUR5 point contact: pool {len(Bp)} readings (3-DOF self-motion walk), {len(estp)} estimated parameters "
        f"(K >= {kminp}); uniform / optimal continuous A-design {ratio:.3f} (<= {ratio_hi:.3f})"
    )
    print(f"{'N':>4} {'tr rand':>9} | {'K greedy':>8} {'K greedy-a':>10} {'K exch-a':>8} {'K/N':>5} {'I ratio':>7}")
    for N in (20, 30, 40, 60, 80, 120, 160, 200):
        tr_med, _, cv_med = median_random(Bp, N, rng)
        Ke, selp = search_exchange(Bp, tr_med, max(N // 2, kminp), kminp)
        Kg, Kga = prefix_k(Bp, gp, tr_med, kminp), prefix_k(Bp, gpa, tr_med, kminp)
        print(
            f"{N:4d} {tr_med:9.4g} | {fmt(Kg):>8} {fmt(Kga):>10} {fmt(Ke):>8} {(Ke or np.nan) / N:5.2f} "
            f"{closure_variance(Bp, selp.indices) / cv_med:7.2f}",
            flush=True,
        )
    print(f"({time.time() - t1:.0f} s)")
print(f"\n({time.time() - t0:.0f} s)")
