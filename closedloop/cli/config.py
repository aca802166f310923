"""``--config FILE.yaml``: every option of a subcommand in one YAML mapping (keys are the long option
names, ``-`` or ``_``; positionals by name), checked against the subcommand's parser and converted by its
own option types; options given on the command line win.  `calibrate`'s values are then checked as its
command line's (`closedloop.run.options`)."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from closedloop.errors import InputError


def _subcommand(parser: argparse.ArgumentParser, argv: list[str]):
    subs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for tok in argv:
        if tok in subs.choices:
            return tok, subs.choices[tok]
    return None, None


def _config_path(argv: list[str]) -> str | None:
    for k, tok in enumerate(argv):
        if tok == "--config" and k + 1 < len(argv):
            return argv[k + 1]
        if tok.startswith("--config="):
            return tok.split("=", 1)[1]
    return None


def _converted(act: argparse.Action, text: str) -> Any:
    """`text` converted by the option's own ``type=`` (none: the text itself)."""
    return act.type(text) if callable(act.type) else text


def load_config(path: str, sub: argparse.ArgumentParser, command: str) -> dict:
    """The YAML mapping of ``path`` checked against the options of ``sub`` (dest -> value)."""
    from closedloop.io.schemas import load_yaml  # strict YAML: only true/false are booleans, no 1_000

    data = load_yaml(path, "config")
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise InputError(f"{path}: a config is a mapping of option: value")
    actions = {a.dest: a for a in sub._actions if a.dest not in ("help", "config", "func")}
    out = {}
    for key, value in data.items():
        dest = str(key).lstrip("-").replace("-", "_")
        act = actions.get(dest)
        if act is None:
            raise InputError(
                f"{path}: unknown option '{key}' for {command} "
                f"(known: {', '.join(sorted(a.replace('_', '-') for a in actions))})"
            )
        if isinstance(act, argparse._AppendAction):
            value = [_converted(act, str(v)) for v in (value if isinstance(value, list) else [value])]
        elif isinstance(act, (argparse._StoreTrueAction, argparse._StoreFalseAction)):
            if not isinstance(value, bool):
                raise InputError(f"{path}: option '{key}' takes true or false")
        elif value is not None:
            if isinstance(value, (bool, dict)) or (isinstance(value, list) and act.nargs is None and act.type):
                want = "a number" if act.type not in (None, str) else "a text value (a path, a name)"
                raise InputError(f"{path}: option '{key}' takes {want}, got {_shown(value)}")
            if isinstance(value, list):
                value = ",".join(str(v) for v in value)
            try:
                value = _converted(act, str(value))
            except (TypeError, ValueError):
                raise InputError(f"{path}: option '{key}': '{value}' is not valid") from None
            if act.choices is not None and value not in act.choices:
                raise InputError(f"{path}: option '{key}' takes one of {', '.join(map(str, act.choices))}")
        out[dest] = value
    return out


def _shown(value) -> str:
    if isinstance(value, bool):
        return f"{str(value).lower()} (a boolean)"
    return "a mapping" if isinstance(value, dict) else "a list" if isinstance(value, list) else repr(value)


def parse_args(parser: argparse.ArgumentParser, argv: list[str] | None):
    """``parser.parse_args`` with a subcommand's ``--config FILE`` applied first (command line wins)."""
    import logging

    # kinematics only: yourdfpy's warnings about mesh files it cannot resolve (package://...) are noise here
    logging.getLogger("yourdfpy").setLevel(logging.ERROR)
    argv = list(sys.argv[1:] if argv is None else argv)
    command, sub = _subcommand(parser, argv)
    path = _config_path(argv)
    if sub is not None and path is not None:
        try:
            cfg = load_config(path, sub, command)
        except InputError as exc:
            print(f"error: {exc}", file=sys.stderr)
            raise SystemExit(2) from None
        positional = [a.dest for a in sub._actions if not a.option_strings and a.dest in cfg]
        for a in sub._actions:  # what the config gives is no longer required on the command line
            if a.dest in positional:
                a.nargs = "?"
            elif a.dest in cfg:
                a.required = False
        sub.set_defaults(**cfg)
    return parser.parse_args(argv)
