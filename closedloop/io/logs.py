"""Joint logs: CSV with a header naming joints, one row per configuration.

Values are radians (metres for prismatic joints) unless ``degrees=True``.
Extra columns are kept aside (``extra``) and ignored by the calibration; an
optional ``loop`` column assigns each row to a loop by name.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Mapping, Sequence

import numpy as np

from closedloop.errors import LogError
from closedloop.io.schemas import parse_number

if TYPE_CHECKING:
    from closedloop.io.files import OutputSet

#: largest |reading| accepted (rad, m or degrees): beyond it the kinematics overflow
MAX_READING = 1e6


@dataclass
class JointLog:
    """Joint readings of N configurations."""

    joints: list[str]
    angles: np.ndarray  # (N, len(joints))
    source: Path | None = None
    loop: np.ndarray | None = None  # (N,) loop name per row, or None
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    #: where each row was read: the files, and per row (index into `files`, line number in that file, 1-based)
    files: list[str] | None = None
    lines: np.ndarray | None = None  # (N, 2) int

    def __len__(self) -> int:
        return self.angles.shape[0]

    def where(self, i: int) -> str:
        """Row `i` (0-based) named for a message: ``log.csv line 52``, by the file and line it was read
        from; ``<source> row i+1`` for a log made in memory."""
        if self.files is not None and self.lines is not None and 0 <= i < len(self.lines):
            f, line = self.lines[i]
            return f"{self.files[int(f)]} line {int(line)}"
        return f"{self.source if self.source is not None else 'log'} row {i + 1}"

    def columns(self, names: list[str]) -> np.ndarray:
        """Readings of `names` (N, len(names)); a missing name is a LogError."""
        missing = [n for n in names if n not in self.joints]
        if missing:
            where = f"{self.source}: " if self.source else ""
            raise LogError(f"{where}missing column(s) for loop joint(s) {', '.join(missing)}")
        idx = [self.joints.index(n) for n in names]
        return self.angles[:, idx]

    def torques(self, names: list[str]) -> np.ndarray | None:
        """Actuator torques from columns ``tau:<joint>`` (N, len(names)), or None if any is missing."""
        cols = [c for c in (self.extra.get(f"tau:{n}") for n in names) if c is not None]
        if len(cols) < len(names):
            return None
        tau = np.column_stack(cols)
        if not np.all(np.isfinite(tau)):
            row, col = (int(k) for k in np.argwhere(~np.isfinite(tau))[0])
            raise LogError(
                f"{self.where(row)}, column 'tau:{names[col]}': {tau[row, col]} is not a finite torque (an empty "
                "cell reads as nan); every row needs its joint torques where tau:<joint> columns are given"
            )
        return tau

    def write_csv(self, path: str | Path) -> None:
        """Write the log whole, in the format `read_log` reads (`write_log_csv`)."""
        columns: dict[str, np.ndarray | Sequence] = {j: self.angles[:, k] for k, j in enumerate(self.joints)}
        if self.loop is not None:
            columns["loop"] = self.loop
        write_log_csv(path, columns | dict(self.extra))


def log_csv(columns: Mapping[str, np.ndarray | Sequence]) -> str:
    """The text of a CSV log (`read_log`'s format): a header of the column names, then one row per
    configuration; a number as ``repr(float)`` (read back to the same double), a value that is not finite
    as an empty cell (no value: a missed view, an unmeasured column), a string (the ``loop`` column) as is.
    Rows end with a line feed."""
    names = list(columns)
    n = {len(v) for v in columns.values()}
    if len(n) > 1:
        raise ValueError(f"columns of different lengths: {sorted(n)}")
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(names)
    cells = [[_cell(v) for v in columns[c]] for c in names]
    w.writerows(zip(*cells))
    return buf.getvalue()


def _cell(v) -> str:
    if isinstance(v, str):
        return v
    x = float(v)
    return repr(x) if math.isfinite(x) else ""


def write_log_csv(
    path: str | Path, columns: Mapping[str, np.ndarray | Sequence], files: "OutputSet | None" = None
) -> None:
    """The one writer of CSV logs: `log_csv`'s text written whole, staged in `files` (an output set the
    caller publishes) or through `atomic_write_text` (the active output set, or a set of one)."""
    from closedloop.io.files import atomic_write_text

    text = log_csv(columns)
    if files is not None:
        files.add(path, text)
    else:
        atomic_write_text(path, text)


def read_log(
    path: str | Path,
    joint_names: list[str],
    degrees: bool = False,
    linear: list[str] | tuple = (),
    order: list[str] | None = None,
) -> JointLog:
    """Read a CSV log, keeping the columns that name joints of the model.

    A file whose first row is numbers has no header: `order` (``--joints
    j1,j2,...``) names its columns.  Every error names the file and, for bad
    values, the line of the file (1-based, as an editor numbers it) and the column.
    """
    path = Path(path)
    from closedloop.io.files import note_input

    if not degrees and order is None:
        plain = _plain_log(path, set(joint_names))
        if plain is not None:
            note_input(path)
            return plain
    try:
        note_input(path)
        with path.open(newline="", encoding="utf-8-sig") as fh:  # a UTF-8 byte-order mark is dropped
            reader = csv.reader(fh)
            numbered = [(reader.line_num, row) for row in reader]  # the line a row ends on
    except IsADirectoryError:
        raise LogError(f"{path}: is a directory, not a CSV log") from None
    except OSError as exc:
        raise LogError(f"{path}: cannot read log ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise LogError(f"{path}: not a UTF-8 text CSV file (byte {exc.start})") from None
    except csv.Error as exc:
        raise LogError(f"{path}: not a CSV file ({exc})") from None
    numbered = [(n, r) for n, r in numbered if r and any(c.strip() for c in r) and not r[0].lstrip().startswith("#")]
    rows = [r for _, r in numbered]
    line_of = [n for n, _ in numbered]
    if not rows:
        raise LogError(f"{path}: empty log (expected a header row naming joints)")
    if _numbers(rows[0]):  # header-less: the joint order is given
        if not order:
            raise LogError(
                f"{path}: the first row is numbers, not a header naming joints; give the column "
                "order (--joints j1,j2,...)"
            )
        unknown = [j for j in order if j not in set(joint_names) and j != "loop"]
        if unknown:
            raise LogError(f"{path}: --joints names {', '.join(unknown)}, not joint(s) of the model")
        if len(rows[0]) != len(order):
            raise LogError(f"{path}: line {line_of[0]} has {len(rows[0])} fields, --joints names {len(order)} columns")
        rows = [list(order)] + rows
        line_of = [0] + line_of
    header = [h.strip() for h in rows[0]]
    if len(set(header)) != len(header):
        dup = sorted({h for h in header if header.count(h) > 1})
        raise LogError(f"{path}: duplicate column(s) {', '.join(dup)}")
    known = set(joint_names)
    cols = [i for i, h in enumerate(header) if h in known]
    if not cols:
        raise LogError(f"{path}: no column names a joint of the model (header: {', '.join(header[:6])}...)")
    loop_col = header.index("loop") if "loop" in header else None
    extra_cols = [i for i, h in enumerate(header) if h not in known and i != loop_col]
    data = rows[1:]
    if not data:
        raise LogError(f"{path}: no data rows after the header")
    A = np.empty((len(data), len(cols)))
    extra = {header[i]: np.full(len(data), np.nan) for i in extra_cols}
    loops = []
    for r, row in enumerate(data, start=1):
        at = f"{path} line {line_of[r]}"
        if len(row) != len(header):
            raise LogError(f"{at} has {len(row)} fields, the header has {len(header)}")
        for k, c in enumerate(cols):
            v = parse_number(row[c], f"{at}, column '{header[c]}'", LogError)
            if abs(v) > MAX_READING:
                raise LogError(
                    f"{at}, column '{header[c]}': {row[c].strip()} is out of range (|reading| <= {MAX_READING:g})"
                )
            A[r - 1, k] = v
        for c in extra_cols:
            try:  # extra columns are informational: a cell that is not a number is NaN
                extra[header[c]][r - 1] = parse_number(row[c], "", LogError)
            except LogError:
                pass
        if loop_col is not None:
            name = row[loop_col].strip()
            if not name:
                raise LogError(f"{at}, column 'loop': empty (name the loop of this row)")
            loops.append(name)
    names = [header[c] for c in cols]
    if degrees:  # prismatic joints (`linear`) stay in metres
        ang = [k for k, n in enumerate(names) if n not in set(linear)]
        A[:, ang] = np.deg2rad(A[:, ang])
    lines = np.column_stack([np.zeros(len(data), int), np.asarray(line_of[1:], int)])
    return JointLog(names, A, path, np.array(loops) if loop_col is not None else None, extra, [str(path)], lines)


def _plain_log(path: Path, known: set[str]) -> JointLog | None:
    """The common log read at once: a header naming joints (and other columns: torques, measurements; no
    ``loop`` column), then one line per row, every cell a decimal number, a joint's finite and within
    MAX_READING, no blank or comment line.  None for anything else (and for any fault): the line-by-line
    reading of `read_log` then reads it or names the fault.  The other columns are read as that reading
    reads them: a cell that is not a finite number is NaN.

    NumPy's C parser reads 100,000 rows of 7 joints in about 0.1 s; the line-by-line reading, 3 s.
    """
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError):
        return None
    head, _, body = text.partition("\n")
    header = [h.strip() for h in head.split(",")]
    joints = [i for i, h in enumerate(header) if h in known]
    if '"' in head or len(set(header)) != len(header) or not joints or "loop" in header or not body.strip():
        return None
    try:
        A = np.loadtxt(io.StringIO(body), delimiter=",", comments=None, ndmin=2, dtype=float)
    except ValueError:
        return None
    n = body.count("\n") + (not body.endswith("\n"))  # its lines (a blank one, a lone CR: a shape that differs)
    if A.shape != (n, len(header)):  # blank lines
        return None
    Q = A if len(joints) == len(header) else A[:, joints]
    if not np.all(np.abs(Q) <= MAX_READING):  # nan, inf, too large
        return None
    extra = {header[i]: np.where(np.isfinite(A[:, i]), A[:, i], np.nan) for i in range(len(header)) if i not in joints}
    lines = np.column_stack([np.zeros(n, int), np.arange(2, n + 2)])
    return JointLog([header[i] for i in joints], Q, path, None, extra, [str(path)], lines)


def check_loop_column(log: JointLog, loop_names: list[str]) -> None:
    """Every name in the log's ``loop`` column must be a loop of the calibration (no silently dropped rows)."""
    if log.loop is None:
        return
    known = set(loop_names)
    for r, name in enumerate(log.loop):
        if name not in known:
            import difflib

            close = difflib.get_close_matches(str(name), sorted(known), n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else f" (loops: {', '.join(sorted(known))})"
            raise LogError(f"{log.where(r)}, column 'loop': no loop named '{name}'{hint}")


BEYOND_LIMIT = 0.5  # rad past a joint limit from which a reading is no reading of that joint (`check_angle_units`)
RADIANS_AS_DEGREES = 0.05  # rad: with --degrees, no revolute joint moving more is a log in radians


def check_angle_units(log: JointLog, robot, degrees: bool = False) -> None:
    """Refuse a log in which most readings of one of `robot`'s revolute joints lie far beyond its limits.

    A log in degrees read as radians (55.5 against a limit of 2.09) is no calibration problem: the fit
    would run for its whole budget and fail.  More than half of one joint's readings BEYOND_LIMIT past its
    limits make it an input error naming the joint, a row and the value.  A few such rows are left to the
    outlier screen (a corrupted cell); joints without limits (continuous, or a range over 4 pi) are not
    checked.  The opposite mistake, a log in radians given ``degrees``, leaves every revolute joint moving
    less than RADIANS_AS_DEGREES (3 degrees read as radians are 0.05 rad): refused too, naming the joint
    that moves most.
    """
    limits = {n: (j.lower, j.upper) for n, j in robot.joints.items() if j.kind == "revolute"}
    logged = [j for j in limits if j in log.joints]
    if degrees and len(log) > 1 and logged:
        ranges = {j: float(np.ptp(log.angles[:, log.joints.index(j)])) for j in logged}
        widest = max(ranges, key=ranges.__getitem__)
        if ranges[widest] < RADIANS_AS_DEGREES:
            raise LogError(
                f"{log.source}: with --degrees no revolute joint moves more than {ranges[widest]:.3g} rad over the "
                f"log (the most: '{widest}', {np.degrees(ranges[widest]):.3g} degrees as given): a log in radians? "
                "(leave out --degrees)"
            )
    for j, (lo, hi) in limits.items():
        if j not in log.joints or not (np.isfinite(lo) and np.isfinite(hi)) or hi - lo > 4.0 * np.pi:
            continue
        col = log.angles[:, log.joints.index(j)]
        out = (col < lo - BEYOND_LIMIT) | (col > hi + BEYOND_LIMIT)
        if col.size and out.sum() > 0.5 * col.size:
            i = int(np.flatnonzero(out)[0])
            hint = "" if degrees else ": a log in degrees? (give --degrees)"
            raise LogError(
                f"{log.source}: {int(out.sum())} of {col.size} readings of joint '{j}' lie over "
                f"{BEYOND_LIMIT} rad beyond its limits [{lo:.4g}, {hi:.4g}] rad ({log.where(i)}: "
                f"{col[i]:.6g}{' rad' if degrees else ''}){hint}"
            )


def _numbers(row: list[str]) -> bool:
    """Every cell of a row is a number (a data row, not a header)."""
    try:
        for c in row:
            float(c)
    except ValueError:
        return False
    return bool(row)


def read_loop_logs(
    files: list[tuple[str, str | Path]],
    joint_names: list[str],
    degrees: bool = False,
    linear: list[str] | tuple = (),
    order: list[str] | None = None,
) -> JointLog:
    """One log from several files, one per loop: (loop name, path) pairs (``--loop ...,log=FILE``).

    Each file's rows get its loop's name in the ``loop`` column (a file's own
    ``loop`` column must agree); the files must log the same joints.
    """
    parts = []
    for name, path in files:
        lg = read_log(path, joint_names, degrees, linear, order)
        if lg.loop is not None and np.any(lg.loop != name):
            raise LogError(f"{path}: its 'loop' column names other loops than '{name}'")
        parts.append((name, lg))
    first = parts[0][1]
    for _, lg in parts[1:]:
        if set(lg.joints) != set(first.joints):
            raise LogError(
                f"{lg.source}: logs joints {', '.join(lg.joints)}, {first.source} logs "
                f"{', '.join(first.joints)}: the files must log the same joints"
            )
    angles = np.vstack([lg.columns(first.joints) for _, lg in parts])
    loops = np.concatenate([np.full(len(lg), name, dtype=object) for name, lg in parts]).astype(str)
    keys = list(dict.fromkeys(k for _, lg in parts for k in lg.extra))
    extra = {k: np.concatenate([lg.extra.get(k, np.full(len(lg), np.nan)) for _, lg in parts]) for k in keys}
    names = [str(p) for _, p in files]
    lines = np.vstack(
        [
            np.column_stack([np.full(len(lg), k), lg.lines[:, 1]])
            if lg.lines is not None
            else np.column_stack([np.full(len(lg), k), np.arange(2, len(lg) + 2)])
            for k, (_, lg) in enumerate(parts)
        ]
    )
    return JointLog(list(first.joints), angles, Path("+".join(names)), loops, extra, names, lines)
