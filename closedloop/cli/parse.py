"""Option values of the command line, parsed and checked (one `InputError` line for a bad one).

Used by the `closedloop` commands:
``--set KEY=VALUE`` simulator settings, argparse number types, and negative numbers given as option
values (calibrate's own options are checked by `closedloop.run.options`).
"""

from __future__ import annotations

import argparse
import json
from typing import Any

from closedloop.errors import InputError


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
