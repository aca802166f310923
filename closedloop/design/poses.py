"""Choosing the most informative configurations.

From a pool of candidate configurations of one loop (readings, e.g. a dense
self-motion walk) choose K that make the information matrix of the estimated
parameters large,

    A(S) = A_0 + sum_{i in S} B_i^T B_i,

B_i (m, L) the whitened, prior-scaled Jacobian block of configuration i at the
current estimate (``observability.whitened_blocks``) and A_0 = prior_weight * I
the prior information (prior^-2 I in unscaled units), which lets greedy start
from zero configurations.  Two criteria:

* D-optimality: maximise log det A(S) (observability index O1 of Borm & Menq
  1991), the volume of the confidence ellipsoid;
* A-optimality: minimise tr A(S)^-1, the trace of the parameter covariance
  (prior-scaled units), i.e. the sum of the parameters' variances, which is
  how the accuracy of a design is measured here (``trace_covariance``).

Every update is rank m (one configuration), never a refactorisation.  With
M = A^-1, S_i = I_m + B_i M B_i^T and U_j = I_m - B_j M B_j^T:

* adding i:    (A + B_i^T B_i)^-1 = M - M B_i^T S_i^-1 B_i M  (Sherman-Morrison-
  Woodbury), log det gains log det S_i (matrix determinant lemma), the trace
  falls by tr(S_i^-1 B_i M^2 B_i^T);
* removing j:  (A - B_j^T B_j)^-1 = M + M B_j^T U_j^-1 B_j M, log det falls by
  -log det U_j, the trace rises by tr(U_j^-1 B_j M^2 B_j^T).

These are evaluated for every candidate at once (batched m x m systems).

Algorithms:

* Greedy (forward selection): add the candidate with the largest gain (log det,
  or trace decrease for criterion 'A').  log det A is carried along as a sum
  of gains.
* DETMAX (Mitchell, "An algorithm for the construction of D-optimal
  experimental designs", Technometrics 16(2):203-210, 1974), D-criterion:
  starting from the greedy design, make excursions: add the l best points,
  then remove the l points whose removal costs least; keep the new design if
  log det rose, otherwise try a longer excursion (l = 1 .. max_excursion).
  Designs already visited (Mitchell's failure set) are not revisited.
* A-optimal exchange (``exchange_a``): Fedorov's exchange (Fedorov, "Theory of
  Optimal Experiments", Academic Press 1972, ch. 3) in the "modified"
  one-point-at-a-time form of Cook & Nachtsheim ("A comparison of algorithms
  for constructing exact D-optimal designs", Technometrics 22(3):315-324,
  1980; Atkinson, Donev & Tobias, "Optimum Experimental Designs, with SAS",
  Oxford 2007, ch. 12), on the trace criterion: starting from the A-optimal
  greedy design, for each design point j (cheapest removal first) downdate
  it out, find the candidate i with the largest trace decrease from the
  downdated design, and swap when tr A^-1 falls, i.e. when
  tr(S_i'^-1 B_i M_j^2 B_i^T) > tr(U_j^-1 B_j M^2 B_j^T), M_j the downdated
  inverse and S_i' its S_i; passes repeat until no swap improves the trace
  (a local optimum for all single exchanges; each swap strictly lowers it,
  so it terminates).  The exchange is then continued with the prior weight
  lowered 10x and 100x, towards the prior-free covariance the estimator has.

A pool of distinct configurations is a design without replicates: a point is
chosen at most once.  The A-optimal design on a one-dimensional self-motion
sits on a few poses (about eight on the Panda weld: both joint-limit ends and
interior poses) with many measurements at each, which a pool can only offer
as neighbouring configurations: a dense pool matters.  And its gain is
bounded: the continuous (approximate) A-optimal design there is only ~2.03x
as efficient as configurations spread uniformly along the motion (general
equivalence theorem, Kiefer & Wolfowitz 1960; Atkinson et al. ch. 9-10), so
K = N/2 selected configurations reach the trace of N random ones up to
N ~ 200 only.  The trace weights each parameter by its prior; the expected
closure error along the same motion (I-criterion) is not what it lowers
(README, "Pose selection"; benchmarks/bench_pose_selection.py).

Layout: the algorithms on blocks are in :mod:`closedloop.design.optimal` (information, greedy,
DETMAX) and :mod:`closedloop.design.exchange` (the A-optimal exchange), re-exported here; this
module builds the blocks from a problem (`pool_blocks`, `select_poses`) and runs studies over many
candidate pools on the executor (`select_pools`: one selection per pool; `random_designs`: the
random-subset baseline, seeded per chunk of draws), with the same results on every engine.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from closedloop.analysis.identifiability import greedy_reduction
from closedloop.analysis.observability import resolve, whitened_blocks
from closedloop.design.exchange import exchange_a
from closedloop.design.optimal import Selection, detmax, greedy_d_optimal, information, trace_covariance
from closedloop.errors import OptionError
from closedloop.io.schemas import POSE_METHODS as METHODS
from closedloop.problem.problem import CalibrationProblem
from closedloop.progress import ProgressReporter
from closedloop.records import CalibrationResult

__all__ = [
    "Selection",
    "greedy_d_optimal",
    "detmax",
    "exchange_a",
    "information",
    "trace_covariance",
    "pool_blocks",
    "select_poses",
    "METHODS",
    "select_pools",
    "random_designs",
    "RandomDesigns",
]


# --------------------------------------------------------------------------- on a problem
def pool_blocks(
    result_or_problem: CalibrationResult | CalibrationProblem,
    values: np.ndarray | None,
    pool_thetas: np.ndarray,
    block: int = 0,
    params=None,
    noise=None,
    weighting: str = "noise",
) -> tuple[np.ndarray, list[int]]:
    """Whitened, prior-scaled Jacobian blocks (Npool, m, L) of the pool and the parameter indices used.

    With a bare problem and no `params`, the parameters are a structural
    reduction of the pool's own Jacobian (``identifiability.greedy_reduction``,
    calibrate's priority order): redundant directions carry no information and
    would only measure the prior.  Pool readings should close the loop (e.g.
    a self-motion walk) for that reduction to be exact.
    """
    problem, vals, idx, sigma_q = resolve(result_or_problem, values, params, noise)
    thetas = [b.theta for b in problem.blocks]
    thetas[block] = np.asarray(pool_thetas, float)
    if params is None and not isinstance(result_or_problem, CalibrationResult):
        _, J = whitened_blocks(problem, vals, idx, sigma_q, weighting, thetas, blocks=[block])[0]
        C = J.reshape(-1, J.shape[2])
        prm = problem.params
        order = sorted(
            range(len(idx)),
            key=lambda i: (
                prm[idx[i]].priority,
                -prm[idx[i]].order if prm[idx[i]].kind in ("placement", "dh") else prm[idx[i]].order,
                idx[i],
            ),
        )
        kept, _ = greedy_reduction(C, [problem.names[k] for k in idx], order)
        idx = sorted(idx[i] for i in kept)
    _, J = whitened_blocks(problem, vals, idx, sigma_q, weighting, thetas, blocks=[block])[0]
    return J, idx


def select_poses(
    result_or_problem: CalibrationResult | CalibrationProblem,
    values: np.ndarray | None,
    pool_thetas: np.ndarray,
    k: int,
    method: str = "greedy",
    block: int = 0,
    params=None,
    noise=None,
    weighting: str = "noise",
    prior_weight: float = 1.0,
    include_existing: bool = False,
    return_selection: bool = False,
):
    """Indices of the k most informative rows of `pool_thetas` (readings of loop `block`).

    result_or_problem: a `CalibrationResult` (its estimated parameters, values
      and noise are the defaults) or a `CalibrationProblem` (pass `values`).
    method: 'greedy' (D-optimal forward selection), 'detmax' (greedy, then
      Mitchell's exchange), 'greedy-a' (forward selection minimising the
      trace of the covariance, A-optimality, with the same Woodbury updates),
      or 'exchange-a' (greedy-a, then Fedorov's exchange on the trace:
      `exchange_a`; the best for the covariance trace, what
      benchmarks/bench_pose_selection.py measures).
    prior_weight: A_0 = prior_weight * I in prior-scaled units.
    include_existing: count the problem's own configurations as already taken
      (choose the k that best complement the data in hand).
    Returns the indices (np.ndarray), or a `Selection` if return_selection.
    """
    B, idx = pool_blocks(result_or_problem, values, pool_thetas, block, params, noise, weighting)
    base = None
    if include_existing:
        problem, vals, _, sigma_q = resolve(result_or_problem, values, idx, noise)
        C = np.vstack([J.reshape(-1, len(idx)) for _, J in whitened_blocks(problem, vals, idx, sigma_q, weighting)])
        base = C.T @ C
    if method == "greedy":
        sel = greedy_d_optimal(B, k, prior_weight, base)
    elif method == "greedy-a":
        sel = greedy_d_optimal(B, k, prior_weight, base, criterion="A")
    elif method == "detmax":
        sel = detmax(B, k, prior_weight, base)
    elif method == "exchange-a":
        sel = exchange_a(B, k, prior_weight, base)
    else:
        raise OptionError(f"method must be one of {', '.join(map(repr, METHODS))}, not '{method}'")
    return sel if return_selection else sel.indices


# --------------------------------------------------------------------------- many pools, on the executor
@dataclass
class RandomDesigns:
    """`draws` random n-subsets of a pool (no replicates) and their covariance traces (prior-scaled units)."""

    indices: np.ndarray  # (draws, n) rows of the pool
    traces: np.ndarray  # (draws,) tr (sum_{i in S} B_i^T B_i)^-1, inf when singular

    @property
    def median(self) -> float:
        """The median trace (the mean is dominated by rare bad draws)."""
        return float(np.median(self.traces))


def _select_job(result_or_problem, values, k: int, method: str, kw: dict, pool: np.ndarray) -> Selection:
    return select_poses(result_or_problem, values, pool, k, method, return_selection=True, **kw)


def select_pools(
    result_or_problem: CalibrationResult | CalibrationProblem,
    values: np.ndarray | None,
    pools: list[np.ndarray],
    k: int,
    method: str = "exchange-a",
    executor=None,
    progress: ProgressReporter | None = None,
    **kw,
) -> list[Selection]:
    """`select_poses` on each candidate pool, one job per pool on `executor` (``closedloop.parallel.executor``).

    The problem (or result), `values` and the options travel once per worker; a pool is a job.  The
    selection is deterministic, so every engine returns the same designs, in pool order.  `kw`:
    the other arguments of `select_poses` (block, params, noise, weighting, prior_weight,
    include_existing).
    """
    from closedloop.parallel.executor import run

    if method not in METHODS:
        raise OptionError(f"method must be one of {', '.join(map(repr, METHODS))}, not '{method}'")
    return run(
        _select_job,
        [np.asarray(p, float) for p in pools],
        executor,
        shared=(result_or_problem, values, int(k), method, kw),
        progress=progress,
        task="selecting poses",
    )


def _random_job(B: np.ndarray, n: int, draws: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    idx = np.stack([rng.choice(len(B), n, replace=False) for _ in range(draws)])
    return idx, np.array([trace_covariance(B, d) for d in idx])


def random_designs(
    B: np.ndarray,
    n: int,
    draws: int = 200,
    seed: int = 0,
    executor=None,
    chunk: int = 25,
    progress: ProgressReporter | None = None,
) -> RandomDesigns:
    """The baseline a selection is compared with: `draws` random n-subsets of the pool's blocks B.

    Draws go in chunks of `chunk` as jobs on `executor`; chunk c draws from
    ``default_rng(SeedSequence(seed).spawn(n_chunks)[c])``, so the designs (and their traces
    tr (sum B_i^T B_i)^-1) are the same on every engine and worker count (for a given chunk).
    """
    from closedloop.parallel.executor import run

    if not 1 <= n <= len(B):
        raise OptionError(f"cannot draw {n} configurations from a pool of {len(B)}")
    sizes = [min(chunk, draws - c) for c in range(0, draws, max(1, chunk))]
    parts = run(
        _random_job,
        sizes,
        executor,
        shared=(np.asarray(B), int(n)),
        seed=seed,
        progress=progress,
        task="drawing designs",
    )
    return RandomDesigns(np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]))
