"""The command line's help: every option of every subcommand explained, one spelling per concept."""

from __future__ import annotations

import argparse
import contextlib
import io

import pytest

from closedloop.cli.main import build_parser, main


def _parsers(parser: argparse.ArgumentParser, path: tuple[str, ...] = ("closedloop",)):
    """(command path, parser) of the top-level parser and of every subcommand, nested ones too."""
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _parsers(sub, path + (name,))


def _options(parser: argparse.ArgumentParser):
    return [a for a in parser._actions if not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction))]


def _help_text(argv: list[str]) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(argv) == 0
    return out.getvalue()


def test_every_option_of_every_subcommand_has_help():
    missing = [
        f"{' '.join(path)} {a.option_strings[0] if a.option_strings else a.dest}"
        for path, p in _parsers(build_parser())
        for a in _options(p)
        if not (a.help or "").strip() or a.help == argparse.SUPPRESS
    ]
    assert missing == [], "options without help: " + ", ".join(missing)


def test_the_parser_walk_sees_every_subcommand():
    """The walk above is not vacuous: it reaches the subcommands and nested ones (impedance simulate)."""
    paths = {path for path, _ in _parsers(build_parser())}
    for cmd in ("calibrate", "simulate", "check", "inspect", "evaluate", "batch", "extract", "loops"):
        assert ("closedloop", cmd) in paths
    assert ("closedloop", "impedance", "identify") in paths
    n = sum(len(_options(p)) for _, p in _parsers(build_parser()))
    assert n > 80


# spellings one concept must not take besides its own (the one used across subcommands)
OTHER_SPELLINGS = {
    "--plots": ["--plot", "--figures", "--figs"],
    "--quiet": ["--silent", "-q"],
    "--report": ["--json-report", "--report-json"],
    "--seed": ["--random-seed", "--rng"],
    "--jobs": ["--workers", "--processes", "-j"],
}


@pytest.mark.parametrize("own", sorted(OTHER_SPELLINGS))
def test_one_spelling_per_concept(own):
    seen = {
        f"{' '.join(path)} {s}"
        for path, p in _parsers(build_parser())
        for a in _options(p)
        for s in a.option_strings
        if s in OTHER_SPELLINGS[own]
    }
    assert not seen, f"{sorted(seen)}: spelled {own} elsewhere"


def test_ray_option_names_local_and_both_install_lines():
    for cmd in (["simulate", "--help"], ["batch", "--help"]):
        text = " ".join(_help_text(cmd).split())
        assert "--ray auto|local|ADDRESS" in text
        assert "'local' starts one here" in text
        assert 'pip install "closedloop[ray]"' in text and 'pip install ".[ray]"' in text


def test_calibrate_out_help_names_every_model_format():
    text = " ".join(_help_text(["calibrate", "--help"]).split("options:", 1)[1].split())
    out_help = text.split("--out OUT", 1)[1].split(" --", 1)[0]
    for fmt in ("URDF", "MJCF", "D-H"):
        assert fmt in out_help, out_help


def test_evaluate_help_keeps_the_example_lines():
    text = _help_text(["evaluate", "--help"])
    lines = text.splitlines()
    first = next(i for i, ln in enumerate(lines) if ln.strip().startswith("closedloop evaluate nominal.urdf"))
    assert lines[first].strip().endswith("--loop point:frame=ball,name=a ...")
    assert lines[first + 1].strip().startswith("closedloop evaluate nominal.urdf calibrated.urdf --joints")
    assert lines[first + 1].rstrip().endswith("\\")
    assert lines[first + 2].strip().startswith("--loop point:frame=ball,name=p3a")


@pytest.mark.parametrize(
    "cmd, option, words",
    [
        (["simulate"], "--n N", ["configurations"]),
        (["simulate"], "--seed SEED", ["seed"]),
        (["simulate"], "--out DIR", ["truth.json"]),
        (["calibrate"], "--max-iter N", ["iterations"]),
        (["calibrate"], "--quiet", ["summary"]),
    ],
)
def test_options_that_had_no_help_now_say_what_they_do(cmd, option, words):
    text = " ".join(_help_text(cmd + ["--help"]).split("options:", 1)[1].split())
    after = text.split(option + " ", 1)[1]
    for w in words:
        assert w in after[:200], after[:200]


def test_abbreviated_options_are_refused(capsys):
    """`--degree` must not silently mean `--degrees` (nor `--prefilt` `--prefilter`): one line, exit 2."""
    from closedloop.cli.main import main

    assert main(["calibrate", "m.urdf", "log.csv", "--degree"]) == 2
    assert "unrecognized arguments: --degree" in capsys.readouterr().err
    assert main(["impedance", "identify", "data.csv", "--prefilt", "10"]) == 2
    assert "unrecognized arguments: --prefilt" in capsys.readouterr().err


def test_simulate_quiet_prints_nothing(tmp_path, capsys):
    from closedloop.cli.main import main

    assert main(["simulate", "panda_weld", "--n", "3", "--out", str(tmp_path / "s"), "--quiet"]) == 0
    out = capsys.readouterr()
    assert out.out == "" and (tmp_path / "s" / "log.csv").is_file()


def test_library_note_reads_as_a_note_line():
    """A library's ``note: ...`` warning is printed as the command's own note line; other warnings keep
    their level and module."""
    import logging

    from closedloop.cli.main import _LogFormatter

    fmt = _LogFormatter()
    note = logging.LogRecord("closedloop.sims.robot_scenario", logging.WARNING, __file__, 1, "note: %s", ("x",), None)
    other = logging.LogRecord("closedloop.sims.robot_scenario", logging.WARNING, __file__, 1, "careful", (), None)
    assert fmt.format(note) == "note: x"
    assert fmt.format(other) == "WARNING closedloop.sims.robot_scenario: careful"
