"""Every option of a calibration run through its four entry points: the command line (`calibrate`'s
parser), a ``--config`` file, a batch manifest's job and the Python API (`CalibrateOptions`), and the
JSON schema derived from the same fields: the same names, bounds and defaults, and an out-of-range
value refused by each with the same words (one line, exit 2 on the command line)."""

from __future__ import annotations

import argparse

import pytest

from closedloop.assets.catalog import ROBOTS
from closedloop.cli.calibrate import options_from_args
from closedloop.cli.main import build_parser, main
from closedloop.errors import InputError
from closedloop.fleet.manifest import read_manifest
from closedloop.run.options import (
    CLI,
    MANIFEST,
    MAX_JOINT_NOISE,
    OPTIONS,
    CalibrateOptions,
    default,
    flag,
    json_schema,
)

URDF = str(ROBOTS["panda"].path)
NUMERIC = [f for f in OPTIONS if f.metadata["kind"] in ("float", "int")]
CHOICES = [f for f in OPTIONS if f.metadata["kind"] == "choice"]


def _calibrate_parser() -> argparse.ArgumentParser:
    sub = next(a for a in build_parser("calibrate")._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices["calibrate"]


def _too_big(f):
    """A value just beyond the option's upper bound, and how it is written."""
    hi = f.metadata["hi"]
    return (hi + 1, str(hi + 1)) if f.metadata["kind"] == "int" else (hi * 2, repr(hi * 2))


def test_every_entry_point_takes_the_same_names():
    cli = {f.name for f in OPTIONS if CLI in f.metadata["where"]}
    manifest = {f.name for f in OPTIONS if MANIFEST in f.metadata["where"]}
    actions = _calibrate_parser()._actions
    dests = {a.dest for a in actions if not isinstance(a, argparse._HelpAction)}
    assert dests == cli | {"config", "quiet"}, dests ^ (cli | {"config", "quiet"})
    for a in actions:  # spelled --max-iter for max_iter
        if a.option_strings and a.dest in cli:
            assert a.option_strings == [flag(a.dest)]
    assert set(json_schema(MANIFEST)["properties"]) == manifest
    assert set(json_schema(CLI)["properties"]) == cli
    api = {f for f in CalibrateOptions.__dataclass_fields__}
    assert api == {f.name for f in OPTIONS} | {"rules"}
    # the manifest takes every option of a run but the job folder's own outputs
    assert cli - manifest == {"out", "report", "html", "plots", "force", "suggest"}


def test_defaults_and_bounds_are_the_same_everywhere(tmp_path):
    """The parser's defaults give the API's defaults; the schema states the fields' bounds and defaults."""
    args = _calibrate_parser().parse_args([URDF, "log.csv"])
    from_cli = options_from_args(args)
    from_api = CalibrateOptions(model=URDF, log="log.csv")
    assert from_cli == from_api
    (tmp_path / "m.yaml").write_text(f"jobs:\n  - {{name: a, model: {URDF}, log: log.csv, out: o}}\n")
    (job,) = read_manifest(tmp_path / "m.yaml")
    from_manifest = job.run_options()
    for f in OPTIONS:
        if f.name in ("model", "log", "out", "report"):
            continue
        assert getattr(from_manifest, f.name) == getattr(from_api, f.name) == default(f), f.name
    for entry in (CLI, MANIFEST):
        props = json_schema(entry)["properties"]
        for f in NUMERIC:
            s = props[f.name]
            lo_key = "exclusiveMinimum" if f.metadata["lo_open"] else "minimum"
            assert (s[lo_key], s["maximum"]) == (f.metadata["lo"], f.metadata["hi"]), f.name
            assert s.get("default") == default(f), f.name
        for f in CHOICES:
            assert props[f.name]["enum"] == list(f.metadata["choices"]), f.name
        assert props["noise"]["anyOf"][0]["maximum"] == MAX_JOINT_NOISE
    parser = {a.dest: a for a in _calibrate_parser()._actions}
    for f in NUMERIC + CHOICES:
        assert parser[f.name].default == default(f), f.name
        assert parser[f.name].help == f.metadata["help"], f.name
    for f in CHOICES:
        assert list(parser[f.name].choices) == list(f.metadata["choices"]), f.name


def _refusals(tmp_path, capsys, f, text: str, value) -> dict[str, str]:
    """The one line each entry point prints or raises for `f` = `value` (`text` on a command line)."""
    out = {}
    rc = main(["calibrate", URDF, "log.csv", "--loop", "weld:frame=panda_hand", f"{flag(f.name)}={text}"])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1, err
    out["parser"] = err.strip()
    (tmp_path / "c.yaml").write_text(f"{f.name}: {text}\n")
    rc = main(["calibrate", URDF, "log.csv", "--loop", "weld:frame=panda_hand", "--config", str(tmp_path / "c.yaml")])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1, err
    out["config"] = err.strip()
    (tmp_path / "m.yaml").write_text(f"jobs:\n  - {{name: a, model: {URDF}, log: log.csv, out: o, {f.name}: {text}}}\n")
    with pytest.raises(InputError) as exc:
        read_manifest(tmp_path / "m.yaml")
    out["manifest"] = str(exc.value)
    with pytest.raises(InputError) as exc:
        CalibrateOptions(model=URDF, log="log.csv", **{f.name: value})
    out["api"] = str(exc.value)
    return out


@pytest.mark.parametrize("f", NUMERIC, ids=[f.name for f in NUMERIC])
def test_a_value_beyond_the_bounds_is_refused_alike(f, tmp_path, capsys):
    value, text = _too_big(f)
    said = _refusals(tmp_path, capsys, f, text, value)
    what = f"must be {'>' if f.metadata['lo_open'] else '>='} {f.metadata['lo']:g} and <= {f.metadata['hi']:g}"
    assert said["parser"] == f"error: {flag(f.name)} {text}: {what}"
    assert said["config"] == said["parser"]  # the config's values go through the command line's check
    assert said["manifest"].endswith(f": option '{f.name}': {f.name} {text}: {what}"), said["manifest"]
    assert said["api"] == f"{f.name} {text}: {what}"


@pytest.mark.parametrize("f", CHOICES, ids=[f.name for f in CHOICES])
def test_a_value_outside_the_choices_is_refused_alike(f, tmp_path, capsys):
    said = _refusals(tmp_path, capsys, f, "maybe", "maybe")
    choices = ", ".join(f.metadata["choices"])
    assert "invalid choice: 'maybe'" in said["parser"] and flag(f.name) in said["parser"]  # argparse's own check
    assert f"option '{f.name}' takes one of {choices}" in said["config"]
    assert said["manifest"].endswith(f": option '{f.name}': {f.name} 'maybe': expected one of {choices}")
    assert said["api"] == f"{f.name} 'maybe': expected one of {choices}"


def test_noise_beyond_an_encoders_is_refused_alike(tmp_path, capsys):
    """The joint noise's bound (`MAX_JOINT_NOISE`, 0.1 rad) holds for a config and a manifest too (the
    config schema once took up to 10)."""
    f = next(f for f in OPTIONS if f.name == "noise")
    said = _refusals(tmp_path, capsys, f, "0.5", 0.5)
    what = f"the joint noise must be > 0 and <= {MAX_JOINT_NOISE}"
    assert said["parser"].startswith(f"error: --noise 0.5: {what}")
    assert said["config"] == said["parser"]
    assert f"option 'noise': noise 0.5: {what}" in said["manifest"]
    assert said["api"].startswith(f"noise 0.5: {what}")


def test_older_manifest_spellings_mean_the_same_options(tmp_path):
    (tmp_path / "m.yaml").write_text(
        f"jobs:\n  - {{name: a, model: {URDF}, log: log.csv, out: o, loops: 'weld:frame=panda_hand',"
        " bounds: {fixture.x: [-1, 1]}, threads: 2}\n"
        f"  - {{name: b, model: {URDF}, log: log.csv, out: p, loop: ['weld:frame=panda_hand'],"
        " bound: ['fixture.x=-1:1'], threads: 2}\n"
    )
    a, b = (j.run_options() for j in read_manifest(tmp_path / "m.yaml"))
    assert a.loop == b.loop == ["weld:frame=panda_hand"]
    assert a.bound == b.bound == {"fixture.x": (-1.0, 1.0)}
    assert a.threads == b.threads == 2  # a job's threads reach its run
