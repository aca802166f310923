"""MkDocs hook: the pages generated from the code at build time.

* ``<!-- generated: cli -->`` becomes the command-line reference, walked from the argparse parser of
  `closedloop.cli.main.build_parser` (every subcommand, its arguments, defaults, choices and help).
* ``<!-- generated: loops -->`` becomes the loop-type reference, read from the loop registry
  (`closedloop.loops.spec.all_loop_types`): each type's keys, syntax, example and docstring, as
  ``closedloop loops`` prints them.
* ``<!-- generated: verdict-rules -->`` becomes the table of the verdict's thresholds, read from the fields of
  `closedloop.calibration.verdict.VerdictRules` (name, default, unit, meaning).

Nothing here is written by hand: a new option, loop type or threshold shows up in the site on the next build.
"""

from __future__ import annotations

import argparse
import html
import inspect
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]  # the repository: document this checkout's code, installed or not
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

MARK_CLI = "<!-- generated: cli -->"
MARK_LOOPS = "<!-- generated: loops -->"
MARK_RULES = "<!-- generated: verdict-rules -->"


def _cell(text: object) -> str:
    """Plain text for a Markdown table cell: nothing in it read as a link, emphasis or HTML."""
    out = str(text).replace("\\", "\\\\")
    for ch in "|[]*_`":
        out = out.replace(ch, "\\" + ch)
    return html.escape(out, quote=False).replace("\n", " ")


def _subparsers(parser: argparse.ArgumentParser) -> list[tuple[str, str, argparse.ArgumentParser]]:
    out = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help or "" for a in action._choices_actions}
            for name, sub in action.choices.items():
                out.append((name, helps.get(name, ""), sub))
    return out


def _arguments(parser: argparse.ArgumentParser) -> list[str]:
    rows = []
    for a in parser._actions:
        if isinstance(a, (argparse._HelpAction, argparse._SubParsersAction)):
            continue
        if a.option_strings:
            name = ", ".join(f"`{s}`" for s in a.option_strings)
            if a.nargs != 0:
                meta = a.metavar or a.dest.upper()
                name += f" `{meta}`"
        else:
            name = f"`{a.metavar or a.dest}`" + (" (optional)" if a.nargs in ("?", "*") else "")
        extra = []
        if a.choices and not isinstance(a, argparse._SubParsersAction):
            extra.append("one of " + ", ".join(f"`{c}`" for c in a.choices))
        if a.option_strings and a.nargs != 0 and a.default not in (None, [], argparse.SUPPRESS):
            extra.append(f"default `{a.default}`")
        if isinstance(a, argparse._AppendAction):
            extra.append("repeatable")
        if a.required and a.option_strings:
            extra.append("required")
        help_text = (a.help or "").replace("%(default)s", str(a.default)).replace("%%", "%")
        rows.append(f"| {name} | {_cell(help_text)} | {'; '.join(extra)} |")
    if not rows:
        return []
    return ["| argument | meaning | notes |", "|---|---|---|", *rows]


def _command(name: str, help_text: str, parser: argparse.ArgumentParser, level: int) -> list[str]:
    lines = [f"{'#' * level} `{name}`", ""]
    if help_text:
        lines += [help_text[0].upper() + help_text[1:] + ".", ""]
    usage = " ".join(parser.format_usage().split())
    lines += ["```text", textwrap.fill(usage, 80, subsequent_indent="    ", break_on_hyphens=False), "```", ""]
    if parser.description:
        lines += [parser.description, ""]
    args = _arguments(parser)
    if args:
        lines += [*args, ""]
    if parser.epilog:
        lines += ["```text", parser.epilog.strip("\n"), "```", ""]
    for sub_name, sub_help, sub in _subparsers(parser):
        lines += _command(f"{name} {sub_name}", sub_help, sub, level + 1)
    return lines


def cli_reference() -> str:
    """The command-line reference in Markdown, from the parser `closedloop` runs."""
    from closedloop.cli.main import build_parser

    parser = build_parser()
    lines = ["## Global options", "", *_arguments(parser), ""]
    for name, help_text, sub in _subparsers(parser):
        lines += _command(f"closedloop {name}", help_text, sub, 2)
    return "\n".join(lines)


def loops_reference() -> str:
    """Every registered loop type: keys, syntax, example and the factory's docstring."""
    from closedloop.cli.loops import LOOP_EXAMPLES
    from closedloop.loops.spec import GENERIC_KEYS, all_loop_types

    lines = []
    for kind, (factory, keys) in sorted(all_loop_types().items()):
        doc = inspect.cleandoc(factory.__doc__ or "")
        first, _, rest = doc.partition("\n")
        lines += [f"### `{kind}`", ""]
        lines += [f"**Keys:** {', '.join(f'`{k}`' for k in sorted(keys))}", ""]
        if first:
            lines += ["**Syntax:**", "", "```text", first.strip(), "```", ""]
        example = LOOP_EXAMPLES.get(kind, kind + ":frame=<tool frame>")
        lines += ["**Example:**", "", "```text", f"--loop {example}", "```", ""]
        if rest.strip():
            lines += ["```text", rest.strip("\n"), "```", ""]
    lines += [
        "### Keys every loop type takes",
        "",
        ", ".join(f"`{k}`" for k in sorted(GENERIC_KEYS)) + ", and `KEY=@GROUP` (an unknown shared by several loops).",
        "",
    ]
    return "\n".join(lines)


def rules_reference() -> str:
    """The verdict's thresholds: one row per field of `VerdictRules`, its default, unit and meaning."""
    import dataclasses

    from closedloop.calibration.verdict import VerdictRules

    lines = ["| rule | default | unit | meaning |", "|---|---|---|---|"]
    for f in dataclasses.fields(VerdictRules):
        unit = f.metadata["unit"]
        lines.append(f"| `{f.name}` | {f.default:g} | {'' if unit == '1' else unit} | {_cell(f.metadata['meaning'])} |")
    return "\n".join(lines)


def on_page_markdown(markdown: str, page, config, files) -> str:
    """Replace the markers of a page by the references generated from the code (MkDocs hook)."""
    if MARK_CLI in markdown:
        markdown = markdown.replace(MARK_CLI, cli_reference())
    if MARK_LOOPS in markdown:
        markdown = markdown.replace(MARK_LOOPS, loops_reference())
    if MARK_RULES in markdown:
        markdown = markdown.replace(MARK_RULES, rules_reference())
    return markdown


def on_config(config):
    """Snippets (the changelog page includes CHANGELOG.md) are read from the repository, wherever mkdocs runs."""
    config.mdx_configs.setdefault("pymdownx.snippets", {})["base_path"] = [str(ROOT)]
    return config
