"""Option values of the command line, parsed and checked (one `InputError` line for a bad one).

Used by the `closedloop` commands and by `closedloop batch` (whose manifest takes the same options):
``--noise``, ``--bound``, numeric ranges, the numbers inside a ``--loop`` spec, ``--set KEY=VALUE``
simulator settings, argparse number types, and negative numbers given as option values.
"""

from __future__ import annotations

import argparse
import json
import math
from typing import Any

from closedloop.errors import InputError


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
        kind = kinds[key]
        default: Any = getattr(defaults, key, False)  # the setting's own default (a tuple for a tuple kind)
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


def parse_box(text: str) -> dict[str, tuple[float, float]]:
    """A joint-space box ``joint=lo:hi,joint=lo:hi`` (rad, or m for a prismatic joint)."""
    out: dict[str, tuple[float, float]] = {}
    for part in (p.strip() for p in text.split(",") if p.strip()):
        name, eq, rng = part.partition("=")
        a, colon, b = rng.partition(":")
        try:
            if not eq or not colon:
                raise ValueError
            lo, hi = float(a), float(b)
        except ValueError:
            raise InputError(
                f"--workspace '{part}': expected joint=lo:hi (rad), e.g. panda_joint1=-1:1, or a log file"
            ) from None
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise InputError(f"--workspace '{part}': the bounds must be finite numbers")
        out[name.strip()] = (lo, hi)
    if not out:
        raise InputError("--workspace: give joint=lo:hi ranges or a log file")
    return out


UNITS = {"m": 1.0, "mm": 1e-3, "um": 1e-6, "rad": 1.0, "mrad": 1e-3, "urad": 1e-6, "deg": 0.017453292519943295}


def parse_accuracy(text: str) -> tuple[float | None, float | None]:
    """An accuracy target ``0.2mm``, ``1mrad`` or both (``0.2mm,1mrad``): (metres or None, radians or None)."""
    import re

    m: float | None = None
    rad: float | None = None
    for part in (p.strip() for p in text.split(",") if p.strip()):
        hit = re.fullmatch(r"([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*(m|mm|um|rad|mrad|urad|deg)", part)
        if not hit:
            raise InputError(
                f"--accuracy '{part}': expected a number and a unit, e.g. 0.2mm or 1mrad (m, mm, um, rad, mrad, urad, deg)"
            )
        value = float(hit.group(1)) * UNITS[hit.group(2)]
        if not (value > 0 and value < 1e3):
            raise InputError(f"--accuracy '{part}': the target must be > 0")
        if hit.group(2) in ("m", "mm", "um"):
            m = value
        else:
            rad = value
    if m is None and rad is None:
        raise InputError("--accuracy: give a position target, an angle target or both, e.g. 0.2mm,1mrad")
    return m, rad
