"""Option values of the command line, parsed and checked (one `InputError` line for a bad one).

Used by the `closedloop` commands and by `closedloop batch` (whose manifest takes the same options):
``--noise``, ``--bound``, numeric ranges, the numbers inside a ``--loop`` spec, ``--set KEY=VALUE``
simulator settings, argparse number types, and negative numbers given as option values.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from closedloop.errors import InputError

EXIT_INPUT = 2
EXIT_FAILED = 3  # a calibration whose verdict is 'failed' (the report says why)
EXIT_INTERNAL = 70
EXIT_PIPE = 141  # 128 + SIGPIPE: the output's reader closed it (`closedloop ... | head`)


def parse_noise(text: str | float | None):
    """``--noise 1e-4`` or ``--noise j1=1e-4,j2=2e-4``: every value a finite number > 0 (rad or m)."""
    from closedloop.io.schemas import parse_number

    if text is None:
        return None
    if not isinstance(text, str):
        text = repr(text)
    if "=" not in text:
        v = parse_number(text, f"--noise {text}")
        if not 0 < v <= 10:
            raise InputError(f"--noise {text}: the joint noise must be > 0 and <= 10 (a std in rad or m)")
        return v
    out = {}
    for part in text.split(","):
        k, _, v = (t.strip() for t in part.partition("="))
        if not k:
            raise InputError(f"--noise {part}: expected joint=value")
        out[k] = parse_number(v, f"--noise {part}")
        if not 0 < out[k] <= 10:
            raise InputError(f"--noise {part}: the joint noise must be > 0 and <= 10 (a std in rad or m)")
    return out


def parse_bounds(items: list[str]) -> dict[str, tuple[float, float]]:
    """``--bound NAME=LOW:HIGH`` (an empty side is unbounded); LOW <= HIGH."""
    from closedloop.io.schemas import parse_number

    out = {}
    for item in items:
        name, eq, rng = item.partition("=")
        lo, colon, hi = rng.partition(":")
        if not eq or not colon or not name.strip():
            raise InputError(f"--bound {item}: expected NAME=LOW:HIGH")
        lo_v = parse_number(lo, f"--bound {item}", allow_inf=True) if lo.strip() else -np.inf
        hi_v = parse_number(hi, f"--bound {item}", allow_inf=True) if hi.strip() else np.inf
        if lo_v > hi_v:
            raise InputError(f"--bound {item}: the lower bound {lo.strip()} exceeds the upper bound {hi.strip()}")
        out[name.strip()] = (lo_v, hi_v)
    return out


def check_number(opt: str, value, lo: float, hi: float, *, integer: bool = False, lo_open: bool = False):
    """A numeric option in range (``lo < v`` when `lo_open`, else ``lo <= v``; ``v <= hi``), as float/int."""
    from closedloop.io.schemas import is_number, parse_number

    v = parse_number(value, f"{opt} {value}") if isinstance(value, str) else value
    if not is_number(v) or (integer and float(v) != int(v)):
        raise InputError(f"{opt} {value}: expected {'a whole number' if integer else 'a finite number'}")
    if v < lo or (lo_open and v == lo) or v > hi:
        raise InputError(f"{opt} {value}: must be {'>' if lo_open else '>='} {lo:g} and <= {hi:g}")
    return int(v) if integer else float(v)


def check_loop_numbers(spec: str) -> None:
    """Numbers inside a ``--loop`` spec (closure, axis, point, ...) are decimal, finite and within 1e6."""
    import re

    from closedloop.io.schemas import MAX_ABS, parse_number

    for token in re.split(r"[\s,=:\"']+", spec):
        if re.fullmatch(
            r"[-+]?(\d[\d_]*\.?[\d_]*|\.\d[\d_]*)([eE][-+]?\d+)?|[-+]?(nan|inf|infinity)", token, re.IGNORECASE
        ):
            v = parse_number(token, f"--loop {spec}")
            if abs(v) > MAX_ABS:
                raise InputError(f"--loop {spec}: {token} is out of range (|value| <= {MAX_ABS:g})")


def sim_overrides(items: list[str], defaults) -> dict:
    """``--set KEY=VALUE`` items checked against the scenario's settings (type of each default)."""
    import dataclasses

    from closedloop.io.schemas import check_settings, is_number

    kinds = {f.name: type(getattr(defaults, f.name)) for f in dataclasses.fields(defaults)}
    kinds.update(soft=bool, stiff=bool)  # presets
    out: dict = {}
    for item in items:
        key, eq, text = (t.strip() for t in item.partition("="))
        if not eq or not key:
            raise InputError(f"--set {item}: expected KEY=VALUE")
        if key not in kinds:
            raise InputError(f"--set {item}: unknown setting '{key}' (known: {', '.join(sorted(kinds))})")
        kind, default = kinds[key], getattr(defaults, key, False)
        if kind is bool:
            if text.lower() not in ("true", "false", "1", "0"):
                raise InputError(f"--set {item}: '{key}' takes true or false")
            out[key] = text.lower() in ("true", "1")
        elif kind in (str, type(None)):  # a name (None: off by default)
            out[key] = None if kind is type(None) and text.lower() in ("", "none", "off") else text
        else:
            try:
                value = json.loads(text)
            except json.JSONDecodeError:
                value = None
            n = len(default) if kind is tuple else 1
            nums = value if isinstance(value, list) else [value]
            if len(nums) != n or not all(is_number(v) for v in nums):
                want = f"a list of {n} numbers, e.g. {json.dumps(list(default))}" if kind is tuple else "a number"
                raise InputError(f"--set {item}: '{key}' takes {want}")
            if kind is int and not float(nums[0]).is_integer():
                raise InputError(f"--set {item}: '{key}' takes a whole number")
            out[key] = tuple(nums) if kind is tuple else kind(nums[0])
        v = out[key]
        check_settings({key: list(v) if isinstance(v, tuple) else v}, f"--set {item}")
    merged = {k: list(v) if isinstance(v, tuple) else v for k, v in {**defaults.as_dict(), **out}.items()}
    check_settings(merged, "--set")  # types and ranges (kp > 0, timestep > 0, noise >= 0, select a method...)
    return out


class ArgTypeError(argparse.ArgumentTypeError, ValueError):
    """A bad option value: argparse reports it in one line; a --config loader catches the ValueError."""


def float_arg(text: str) -> float:
    from closedloop.io.schemas import parse_number

    try:
        return parse_number(text, text)
    except InputError as exc:
        raise ArgTypeError(str(exc)) from None


def int_arg(text: str) -> int:
    v = float_arg(text)
    if v != int(v):
        raise ArgTypeError(f"{text}: expected a whole number")
    return int(v)


def join_negative_numbers(argv: list[str]) -> list[str]:
    """``--noise -1e-4`` -> ``--noise=-1e-4``: argparse takes '-1e-4' for an option (and prints usage)."""
    import re

    neg = re.compile(r"^-(\d|\.\d|inf|nan)", re.IGNORECASE)
    out: list[str] = []
    for a in argv:
        if out and neg.match(a) and out[-1].startswith("--") and "=" not in out[-1]:
            out[-1] = f"{out[-1]}={a}"
        else:
            out.append(a)
    return out
