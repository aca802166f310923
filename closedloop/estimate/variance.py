"""A task-space noise per loop beside the joint noise: variance components.

A ball pressed by hand into a socket has play: its error is in the contact,
not in the joints.  A loop's closure then has the covariance

    W_i = s J_theta,i D^2 J_theta,i^T + C_i + v_l T,

the errors-in-variables term of the joint noise (thesis eq. 3.17 weighted;
`closedloop.estimate.noise`), a known measurement covariance C_i (a tracker's) and the
loop's own task-space variance v_l on its translation rows (T).  A loop's
``sigma_task`` fixes v_l; ``sigma_task=auto`` (the default for point and plane
loops when several share the robot) estimates it with s from the fitted
residuals (`variance_components`), and `solve.solve_staged` re-solves
with the new weights until they settle.  `noise_summary` says per loop which
noise dominates.

A loop's configured noise (its ``sigma_t``, ``sigma_px``, ``sigma_task``) is
set on the loop when it is made (`set_task_noise`); what a calibration
estimates is kept in the problem's noise records (`problem.BlockNoise`), so the
user's loops come out of `calibrate` unchanged.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from closedloop.estimate.noise import joint_variance_scale
from closedloop.loops.settings import task_matrix

if TYPE_CHECKING:
    from closedloop.problem.problem import BlockEval, CalibrationProblem

__all__ = ["task_blocks", "variance_components", "noise_summary", "noise_notes"]


CONTACT_LOOPS = ("PointLoop", "PlaneLoop")


def task_blocks(problem: CalibrationProblem) -> list[int]:
    """Blocks whose task-space noise is estimated.

    Loops with sigma_task=auto, and by default (no sigma_task given) the
    contact loops (point, plane) when at least two of them share the robot:
    a ball with play in its socket is noise in the contact, not in the joints,
    and several loops separate the two.
    """
    out = []
    contact = [
        bi
        for bi, b in enumerate(problem.blocks)
        if type(b.loop).__name__ in CONTACT_LOOPS and getattr(b.loop, "task_noise", None) is None
    ]
    for bi, b in enumerate(problem.blocks):
        mode = getattr(b.loop, "task_noise", None)
        if isinstance(mode, str) or (mode is None and bi in contact and len(contact) >= 2):
            out.append(bi)
    return out


#: a matrix whose |W|_F |W^-1|_F (a bound on its condition number) is below this keeps every eigenvalue
#: under `_wpinv`'s cut (1e-12 of the largest): its pseudo-inverse is its inverse
WELL_CONDITIONED = 1e11


def _wpinv(W: np.ndarray) -> np.ndarray:
    """The pseudo-inverses of the symmetric positive semi-definite W (n, m, m), eigenvalues below 1e-12 of each
    matrix's largest dropped.  Well-conditioned matrices (nearly all) by a batched inverse, a quarter of the
    eigen-decomposition's cost; the others, and any stack with an exactly singular matrix, by eigenvalues."""
    if W.shape[0] and W.shape[1] == 1:
        w = W[:, 0, 0]
        return np.where(w > 0.0, 1.0 / np.where(w > 0.0, w, 1.0), 0.0)[:, None, None]
    try:
        Wi = np.linalg.inv(W)
    except np.linalg.LinAlgError:
        return _eigen_pinv(W)
    bound = np.sqrt(np.sum(W * W, axis=(1, 2)) * np.sum(Wi * Wi, axis=(1, 2)))
    bad = ~(bound < WELL_CONDITIONED)  # NaN too
    if np.any(bad):
        Wi[bad] = _eigen_pinv(W[bad])
    return Wi


def _eigen_pinv(W: np.ndarray) -> np.ndarray:
    lam, V = np.linalg.eigh(W)
    keep = lam > 1e-12 * np.maximum(lam[:, -1:], 1e-300)
    inv = np.where(keep, 1.0 / np.where(keep, lam, 1.0), 0.0)
    return (V * inv[:, None, :]) @ np.swapaxes(V, 1, 2)


def variance_components(
    problem: CalibrationProblem,
    evals: list[BlockEval],
    pattern: np.ndarray,
    n_params: int,
    tasks: list[int],
    joint_fixed: bool = False,
    iters: int = 300,
    tol: float = 1e-6,
) -> tuple[float, bool]:
    """Joint variance scale s and each loop's task variance v_l from fitted residuals (Helmert / Foerstner).

    Each configuration's closure has the covariance (eq. 3.17 weighted, with
    a task-space term per loop)

        W_i = s A_i + C_i + v_l T,     A_i = J_theta,i D^2 J_theta,i^T,

    T the identity on the loop's translation rows, C_i a known measurement
    covariance.  The components theta_k (s and the v_l) solve the likelihood's
    score equations  r^T W^-1 B_k W^-1 r = c tr(W^-1 B_k)  (B_k = A_i or T,
    c = (M - p) / M the REML-like degrees-of-freedom correction of
    `joint_variance_scale`); the iteration theta_k <- theta_k r^T W^-1 B_k W^-1 r
    / (c tr(W^-1 B_k)) (Foerstner 1979; Koch, Parameter Estimation 3.6) keeps
    them positive and converges to that root.  `joint_fixed`: s = 1 (the
    joint noise is given).  The iteration stops when no component moves by
    more than `tol` of its loop's whole variance (the caller re-solves and
    estimates again).  Sets each estimated block's task variance in
    `problem.noise` (`BlockNoise.set_task`; the loops are not touched) and
    returns (s, whether a v_l moved by more than 5 %).
    """
    if not tasks and joint_fixed:
        return 1.0, False
    jq = [e.Jq for e in evals if e.Jq is not None]
    if len(jq) < len(evals):
        raise ValueError("variance_components: the blocks must be evaluated with their reading Jacobians (Jq)")
    if not tasks:  # the joint level beside known measurement covariances: the closed score equation
        covs = [
            nz.measurement_cov if np.any(J) else None  # no joint in it (a known distance): no say
            for nz, J in zip(problem.noise, jq)
        ]
        return joint_variance_scale([e.r for e in evals], jq, covs, pattern, n_params), False
    rows = sum(e.r.size for e in evals)
    c = max(rows - n_params, 1) / max(rows, 1)
    T_of = {bi: task_matrix(problem.blocks[bi].loop) for bi in tasks}  # each task loop's T
    blocks = []
    for bi, ev in enumerate(evals):
        Jd = jq[bi] * pattern[None, None, :]
        A = Jd @ np.swapaxes(Jd, 1, 2)
        base = problem.noise[bi].own if bi in tasks else problem.noise[bi].measurement_cov
        C = np.zeros_like(A) if base is None else np.broadcast_to(base, A.shape)
        if ev.cov is not None:
            C = C + ev.cov
        blocks.append((ev.r, A, C, T_of.get(bi)))
    if joint_fixed:
        s = 1.0
    else:
        s = 0.5 * joint_variance_scale(
            [r for r, *_ in blocks], jq, [None] * len(blocks), pattern, n_params
        )  # a start: every residual read as joint noise
        s = max(s, 1e-300)
    v = {
        bi: max(0.5 * float(np.mean(blocks[bi][0][:, list(problem.blocks[bi].loop.translation_rows)] ** 2)), 1e-300)
        for bi in tasks
    }
    # the joint noise's variance per translation row of each task loop, per unit s
    joint_var = {
        bi: float(np.mean(np.einsum("nij,ij->n", blocks[bi][1], T_of[bi]))) / max(float(np.trace(T_of[bi])), 1.0)
        for bi in tasks
    }
    s, v = _foerstner(blocks, tasks, {bi: bi for bi in tasks}, s, v, c, joint_fixed, joint_var, iters, tol)
    for bi in tasks:
        problem.noise[bi].pooled = False
    if len(tasks) > 1 and homogeneous(problem, blocks, tasks, v, c):  # one play, read off every loop at once
        pooled = sum(v[bi] * _task_dof(problem, blocks, bi, c) for bi in tasks) / sum(
            _task_dof(problem, blocks, bi, c) for bi in tasks
        )
        s, v = _foerstner(
            blocks,
            tasks,
            {bi: 0 for bi in tasks},
            s,
            {bi: pooled for bi in tasks},
            c,
            joint_fixed,
            joint_var,
            iters,
            tol,
        )
        for bi in tasks:
            problem.noise[bi].pooled = True
    moved = False
    for bi in tasks:
        nz = problem.noise[bi]
        old = nz.task_var
        if old is None or abs(float(np.mean(old)) - v[bi]) > 0.05 * max(float(np.mean(old)), v[bi], s * joint_var[bi]):
            moved = True
        nz.set_task(v[bi], estimated=True)
    return float(s), moved


def noise_summary(problem: CalibrationProblem, values: np.ndarray, sigma_q: np.ndarray) -> list[dict]:
    """Per loop with translation rows: the task-space noise and what the joint noise makes there (m, RMS per axis).

    joint_m = sqrt(mean_i tr(T J_theta,i Sigma J_theta,i^T) / n_t) at `values`; the larger names what dominates.
    """
    out: list[dict] = []
    if not any(
        b.loop.translation_rows and (hasattr(b.loop, "task_noise") or nz.task_var is not None)
        for b, nz in zip(problem.blocks, problem.noise)
    ):
        return out  # no loop with a task-space noise model: nothing to evaluate
    evals = problem.evaluate(values, True, columns=[])
    for b, ev, nz in zip(problem.blocks, evals, problem.noise):
        lp = b.loop
        rows = list(lp.translation_rows)
        if not rows or ev.Jq is None or not hasattr(lp, "task_noise") and nz.task_var is None:
            continue
        Jt = ev.Jq[:, rows, :] * sigma_q[None, None, :]
        joint = float(np.sqrt(np.mean(np.einsum("nij,nij->n", Jt, Jt)) / len(rows)))
        var = nz.task_var
        task = float(np.sqrt(np.mean(var))) if var is not None else 0.0
        out.append(
            {
                "loop": lp.name,
                "task_sigma_m": task,
                "joint_sigma_m": joint,
                "task_estimated": nz.estimated,
                "task_pooled": nz.pooled,
                "dominant": "task" if task > joint else "joint",
            }
        )
    return out


def noise_notes(summary: list[dict]) -> list[str]:
    """One sentence per noise model: loops whose task-space noise reads the same (one pooled estimate, or
    the same given value) and the same noise dominating share one sentence, their joint-noise figures
    given as a range."""

    def how(d: dict) -> str:
        if not d["task_estimated"]:
            return "given"
        return "estimated, one for the loops whose estimates agree" if d.get("task_pooled") else "estimated"

    groups: dict[tuple, list[dict]] = {}
    for d in summary:
        groups.setdefault((f"{d['task_sigma_m'] * 1e3:.3g}", how(d), d["dominant"]), []).append(d)
    notes = []
    for (task, kind, dominant), ds in groups.items():
        joint = sorted(f"{d['joint_sigma_m'] * 1e3:.3g}" for d in ds)
        lo, hi = min(d["joint_sigma_m"] for d in ds), max(d["joint_sigma_m"] for d in ds)
        span = joint[0] if len(set(joint)) == 1 else f"{lo * 1e3:.3g} to {hi * 1e3:.3g}"
        who = f"loop {ds[0]['loop']}" if len(ds) == 1 else f"loops {', '.join(d['loop'] for d in ds)}"
        notes.append(
            f"{who}: task-space noise {task} mm ({kind}) against {span} mm from the joint noise: "
            f"the {dominant} noise dominates"
        )
    return notes


def measurement_row_weights(problem: CalibrationProblem, values: np.ndarray) -> np.ndarray | None:
    """Row weights for an unweighted fit (``weighting='none'``) beside known measurements, or None without any.

    The closures keep weight 1 (metres, radians); a known distance or length
    (a block without configurations of its own, ``parameter_only``, with its
    covariance sigma^2) gets sigma_c / sigma, sigma_c the RMS of the
    closures' translation rows at `values`: the two-group variance-component
    weighting with the closures' level read off the fit.  Weight 1 in metres
    would make a 10-micrometre distance one row among hundreds of
    0.2-millimetre closures, and least squares would shrink the robot, whose
    closure spread scales with its size.
    """
    only = [
        bi
        for bi, b in enumerate(problem.blocks)
        if getattr(b.loop, "parameter_only", False) and b.loop.measurement_cov is not None
    ]
    if not only:
        return None
    evals = problem.evaluate(values, False)
    parts = [
        ev.r[:, list(b.loop.translation_rows)].ravel()
        for bi, (b, ev) in enumerate(zip(problem.blocks, evals))
        if bi not in only and b.loop.translation_rows
    ]
    t = np.concatenate(parts) if parts else np.zeros(0)
    level = float(np.sqrt(np.mean(t**2))) if t.size else 0.0
    weights = []
    for bi, (b, ev) in enumerate(zip(problem.blocks, evals)):
        w = 1.0
        cov = b.loop.measurement_cov
        if bi in only and level > 0.0 and cov is not None:  # (every loop in `only` has one)
            w = level / float(np.sqrt(np.mean(np.diag(cov))))
        weights.append(np.full(ev.r.size, w))
    return np.concatenate(weights)


def _foerstner(
    blocks: list,
    tasks: list[int],
    group: dict[int, int],
    s: float,
    v: dict[int, float],
    c: float,
    joint_fixed: bool,
    joint_var: dict[int, float],
    iters: int,
    tol: float,
) -> tuple[float, dict[int, float]]:
    """Foerstner's iteration of `variance_components`; the task loops of one `group` key share one component:
    v_g <- v_g sum_l e_l^T T e_l / (c sum_l tr(W_l^-1 T)).

    The configurations of every loop with the same number of rows are one stack (`_stacks`): each step is a
    handful of batched operations whatever the number of loops (per loop, they cost a rig of 16 loops
    sixteen times the calls)."""
    stacks = _stacks(blocks)
    for _ in range(iters):
        num_s = den_s = 0.0
        qt = np.zeros(len(blocks))
        tt = np.zeros(len(blocks))
        for r, A, C, T, seg in stacks:
            vrow = np.array([v.get(bi, 0.0) for bi in range(len(blocks))])[seg]
            W = s * A + C + vrow[:, None, None] * T
            Wi = _wpinv(W)
            e = np.einsum("nij,nj->ni", Wi, r)
            num_s += float(np.einsum("ni,nij,nj->", e, A, e))
            den_s += c * float(np.sum(Wi * A))  # tr(W^-1 A), both symmetric
            qt += np.bincount(seg, weights=np.einsum("ni,nij,nj->n", e, T, e), minlength=len(blocks))
            tt += np.bincount(seg, weights=np.sum(Wi * T, axis=(1, 2)), minlength=len(blocks))
        num: dict[int, float] = {}
        den: dict[int, float] = {}
        for bi in tasks:
            g = group[bi]
            num[g] = num.get(g, 0.0) + float(qt[bi])
            den[g] = den.get(g, 0.0) + c * float(tt[bi])
        new_v = {bi: v[bi] * num[group[bi]] / max(den[group[bi]], 1e-300) for bi in tasks}
        s_new = s if joint_fixed else s * num_s / max(den_s, 1e-300)
        change = abs(s_new - s) / max(s, 1e-300)
        for bi in tasks:  # relative to the loop's whole variance: a vanishing component need not settle
            change = max(change, abs(new_v[bi] - v[bi]) / max(v[bi] + s_new * joint_var[bi], 1e-300))
        s, v = s_new, new_v
        if change < tol:
            break
    return s, v


def _stacks(blocks: list) -> list[tuple]:
    """The blocks (r, A, C, T) grouped by their number of rows m: per m, (r, A, C, T, block) over all their
    configurations, T zero where a loop has no task term and `block` each configuration's block index."""
    out = []
    for m in sorted({r.shape[1] for r, *_ in blocks}):
        members = [bi for bi, (r, *_) in enumerate(blocks) if r.shape[1] == m]
        r = np.concatenate([blocks[bi][0] for bi in members])
        A = np.concatenate([blocks[bi][1] for bi in members])
        C = np.concatenate([np.broadcast_to(blocks[bi][2], blocks[bi][1].shape) for bi in members])
        T = np.concatenate(
            [
                np.broadcast_to(blocks[bi][3] if blocks[bi][3] is not None else np.zeros((m, m)), blocks[bi][1].shape)
                for bi in members
            ]
        )
        seg = np.repeat(members, [blocks[bi][0].shape[0] for bi in members])
        out.append((r, A, C, T, seg))
    return out


def _task_dof(problem: CalibrationProblem, blocks: list, bi: int, c: float) -> float:
    """Degrees of freedom of loop bi's task variance: its translation rows, less their share of the parameters."""
    return c * blocks[bi][0].shape[0] * len(problem.blocks[bi].loop.translation_rows)


def homogeneous(
    problem: CalibrationProblem, blocks: list, tasks: list[int], v: dict[int, float], c: float, z: float = 1.645
) -> bool:
    """Whether the loops' task variances agree within their scatter: Bartlett's test at 5 %.

    M = nu ln s_p^2 - sum nu_l ln s_l^2, s_p^2 the dof-weighted mean, divided
    by 1 + (sum 1/nu_l - 1/nu) / (3 (k - 1)), is chi-square with k - 1 dof
    under equal variances; its 95 % point by Wilson-Hilferty,
    k' (1 - 2/(9k') + z sqrt(2/(9k')))^3.  Equal play in every socket is then
    one variance component: per-loop estimates from ~30 configurations each
    scatter by ~25 % in weight, which costs precision for nothing.
    """
    nu = np.array([_task_dof(problem, blocks, bi, c) for bi in tasks])
    var = np.array([max(v[bi], 1e-300) for bi in tasks])
    if np.any(nu < 2):
        return False
    sp = float(np.sum(nu * var) / np.sum(nu))
    k = len(tasks) - 1
    M = float(np.sum(nu) * np.log(sp) - np.sum(nu * np.log(var)))
    C = 1.0 + (float(np.sum(1.0 / nu)) - 1.0 / float(np.sum(nu))) / (3.0 * k)
    q95 = k * (1.0 - 2.0 / (9.0 * k) + z * np.sqrt(2.0 / (9.0 * k))) ** 3
    return M / C <= q95
