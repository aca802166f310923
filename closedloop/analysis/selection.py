"""Which parameters a calibration estimates, and what the data can move (thesis 3.3, 4.2.2).

Stages of `calibrate` before any solve:

* `initial_values`: the nominal values, with the loops' unknowns started from
  the data (closures, contact points, tool points) and the user's guesses;
  `structure_problem`: where the reduction and gauge are read (a calibrated
  model's own nominal geometry).
* `select_parameters`: the user's patterns and fixes, as one status per
  parameter ('selected', 'fixed', 'not selected').
* `check_motion`: joints that never move (Singularity 5), immobile loops
  (Lemma 4) and joints a loop cannot move (Lemma 6); one scale factor fixed
  when all are free (4.2.2); consecutive parallel D-H axes (Singularity 1).
"""

from __future__ import annotations

import numpy as np

from closedloop.analysis.identifiability import loop_mobility
from closedloop.errors import LogError, NotIdentifiableError, ParameterError
from closedloop.model.parameters import match
from closedloop.problem.problem import CalibrationProblem
from closedloop.records import Dropped, ParamStatus

DEFAULT_IDENTIFY = {
    "urdf": ["placement", "offset", "loop"],
    "mjcf": ["placement", "offset", "loop"],
    "dh": ["theta_off", "s", "a", "alpha", "loop"],
}
MIN_RANGE = 1e-6  # a joint whose readings span less than this never moves
#: configurations per block of a long log the loops' start values and the check of the data read
#: (`CalibrationProblem.sampled`, evenly along the log): thousands place a start well inside the minimum's
#: basin and show a loop the data are not, and a pass over every row costs as much as one of the fit's
START_ROWS = 8192


def initial_values(problem: CalibrationProblem, initial: dict[str, float]) -> np.ndarray:
    """Nominal values; loop unknowns from the data at the nominal robot; then the user's guesses."""
    from closedloop.problem.shared import initial_shared  # shared loop parameters: the mean of the loops' estimates

    x0 = problem.nominal
    inits = [problem.initialize_loop(x0, bi) if cols.size else None for bi, cols in enumerate(problem.loop_columns)]
    x0 = initial_shared(problem, x0, inits)
    for n, v in initial.items():
        if n not in problem.index:
            raise ParameterError(f"initial value for unknown parameter '{n}'")
        x0[problem.index[n]] = v
    return x0


def structure_problem(problem: CalibrationProblem) -> CalibrationProblem:
    """Where the reduction and the length gauge are read (`identifiability.analyse_structure`): the problem
    itself, or for a model calibrated before (`RobotModel.calibrated_from`) the same problem (parameters,
    names, order, loops, log) on the model it was calibrated from.

    A calibrated model's joint frames carry its corrections (offsets folded, millimetre tilts), so slides
    that are exactly redundant at the nominal's geometry (axes parallel or square) are separated there by
    ~1e-4 of their effect: read there, the greedy reduction keeps such a slide in place of a well-determined
    parameter, and another, shorter length holds the size (a Panda weld: panda_joint4.y kept, the size held
    by panda_joint2.y, 0.137 m, not panda_joint3.z, 0.316 m).  Read at the nominal geometry, the reduction
    and the gauge are the first calibration's whatever values it wrote; the fit still starts from the
    calibrated model, and both are re-checked at its solution (`solve.recheck_at_solution`).
    """
    robot = problem.robot.calibrated_from_model()
    return problem if robot is problem.robot else problem.on_robot(robot)


def select_parameters(
    problem: CalibrationProblem, identify: list[str] | None, fix: dict[str, float | None], x0: np.ndarray
) -> list[ParamStatus]:
    """Status per parameter from `identify` patterns and `fix` (x0 takes the fixed values)."""
    names = problem.names
    patterns = identify if identify is not None else DEFAULT_IDENTIFY[problem.robot.kind]
    loop_names = [p.name for p in problem.params if p.kind == "loop"]
    pats = [q for q in patterns if q != "loop"]
    for q in pats:
        if not match(names, [q]):
            raise ParameterError(f"--identify {q}: matches no parameter of this problem")
    selected = set(match(names, pats)) | (set(loop_names) if "loop" in patterns else set())
    status = [ParamStatus.SELECTED if n in selected else ParamStatus.NOT_SELECTED for n in names]
    wants_tau = [n for n in selected if problem.params[problem.index[n]].kind == "compliance"]
    if wants_tau and any(b.tau is None for b in problem.blocks):
        raise LogError(
            f"identifying joint compliance ({wants_tau[0]}, ...) needs the actuator "
            f"torques as columns 'tau:<joint>' for every loop joint"
        )
    for n, v in fix.items():
        if n not in problem.index:
            raise ParameterError(f"--fix {n}: no parameter of this problem has that name")
        k = problem.index[n]
        if v is not None:
            prm = problem.params[k]
            if not np.isfinite(v) or abs(v - prm.nominal) > 1e3 * prm.prior:
                raise ParameterError(
                    f"--fix {n}={v:g}: not a plausible value (nominal {prm.nominal:g} {prm.unit}, "
                    f"expected corrections of about {prm.prior:g} {prm.unit})"
                )
            x0[k] = v
        status[k] = ParamStatus.FIXED
    return status


MOBILITY_ROWS = 25  # configurations per loop `identifiability.loop_mobility` reads
SMALL_RANGE = 0.05  # rad: a joint that moves less than this barely excites the geometry around it


def check_motion(
    problem: CalibrationProblem, x0: np.ndarray, status: list[ParamStatus]
) -> tuple[list[str], list[Dropped], list[str]]:
    """Notes and warnings on the data's motion; drops what a never-moving joint cannot reveal. Edits `status`."""
    names, notes, dropped, warnings = problem.names, [], [], []
    theta_all = np.vstack([b.theta for b in problem.blocks])
    ranges = theta_all.max(axis=0) - theta_all.min(axis=0)
    if np.all(ranges < MIN_RANGE):
        raise NotIdentifiableError(
            "no joint moves in the log: every configuration is the same pose, so nothing can be identified"
        )
    for j, name in enumerate(problem.joints):
        if ranges[j] < MIN_RANGE:
            notes.append(
                f"joint {name} never moves in the data (range {ranges[j]:.2e} "
                f"{'m' if problem.robot.joints[name].kind == 'prismatic' else 'rad'}); its scale and "
                "the geometry it would reveal cannot be identified (Singularity 5)"
            )
            k = problem.rp.index[problem.rp.sensor_name(name, "scale")]
            if status[k] == ParamStatus.SELECTED:
                status[k] = ParamStatus.DROPPED
                dropped.append(Dropped(names[k], "its joint never moves, so scale and offset are one"))
    small = [
        f"{n} ({r:.3g})"
        for n, r in zip(problem.joints, ranges)
        if MIN_RANGE <= r < SMALL_RANGE and problem.robot.joint(n).unit == "rad"
    ]
    if small:
        warnings.append(
            f"joint(s) {', '.join(small)} move less than {SMALL_RANGE} rad in the log: the data barely "
            "excite the geometry around them, and the calibrated model is unchecked away from the "
            "logged configurations"
        )
    sample = problem.sampled(MOBILITY_ROWS, first=True)  # `loop_mobility` reads the first configurations
    for b, ev in zip(sample.blocks, sample.evaluate(x0, True, columns=[])):
        if not b.loop.scale_free:  # a measured (open) loop: mobility is not a question
            continue
        assert ev.Jq is not None  # evaluated with the Jacobians
        mob, moves = loop_mobility(ev.Jq)
        if mob == 0:
            notes.append(
                f"loop {b.loop.name} is immobile (Lemma 4: J_theta has full column rank): "
                "the closed chain cannot move, so its configurations carry no new information"
            )
        for j, name in enumerate(problem.joints):
            if not moves[j] and ranges[j] >= MIN_RANGE and np.any(np.abs(ev.Jq[:, :, j]) > 0):
                notes.append(
                    f"joint {name} is structurally immobile in loop {b.loop.name} "
                    "(Lemma 6: no self-motion of the closed chain moves it)"
                )
    robot = problem.robot
    if robot.kind == "dh" and robot.dh is not None:  # a D-H robot always has its table (`RobotModel.from_file`)
        rows = robot.dh.rows
        for r1, r2 in zip(rows, rows[1:]):
            if r1.convention == "dh" and abs(np.sin(r1.alpha)) < 1e-6 and r1.name in problem.joints:
                notes.append(
                    f"D-H rows {r1.name} and {r2.name}: consecutive parallel axes (alpha_{r1.name} = "
                    f"{r1.alpha:.3g} rad); the common normal is not unique, so {r1.name}.s and "
                    f"{r2.name}.s are not separately identifiable (thesis 3.3, Singularity 1; see "
                    "what absorbs them). Write these rows with convention: hayati (eq. 4.2)"
                )
    sc = [problem.rp.index[problem.rp.sensor_name(j, "scale")] for j in problem.joints]
    if sc and all(status[k] == ParamStatus.SELECTED for k in sc):
        k = sc[-1]
        status[k] = ParamStatus.FIXED
        notes.append(f"fixed {names[k]} = {x0[k]:g}: with every scale factor free, k = 0 fits any data (thesis 4.2.2)")
    return notes, dropped, warnings
