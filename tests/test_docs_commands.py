"""Every documented command runs as written.

Each ```bash block of README.md and docs/**/*.md is run with bash (``set -e``, ``pipefail``) in a temporary
folder holding a link to the repository's examples/, the blocks of one page in page order in one folder (as
a reader following the page would).  ``closedloop``, ``python`` and ``python3`` are this test's own
interpreter and checkout, so the code under test is the one installed in the test environment.

Not executed, but checked (`check_install`): ``pip install ...`` (each extra named must exist in
pyproject.toml, the path must be the checkout; no ``closedloop[...]`` from an index in the pages: the
package is not published; the package's own messages may say ``pip install "closedloop[EXTRA]"``, which
works wherever closedloop is installed, pip adding the extra's packages), the virtual environment lines (``python3 -m venv``, ``. .venv/bin/activate``: the test
environment is one) and ``pytest`` (the suite this test belongs to).  Every ``pip install`` written
anywhere in the pages (inline code, comments) and in the package's messages is checked the same way.

A block whose first line is ``# not run: <reason>`` is skipped with that reason: only for commands that
need hardware or a network.  Blocks should each finish within ~20 s.
"""

from __future__ import annotations

import os
import re
import shlex
from pathlib import Path

import pytest

try:
    import tomllib
except ImportError:  # Python 3.10
    from pip._vendor import tomli as tomllib

from docs_blocks import NOT_RUN, PAGES, ROOT, Block, blocks, compare, page_dir, prepare, run_script, shown_outputs

BLOCKS = [b for p in PAGES for b in blocks(p) if b.runnable]


# --------------------------------------------------------------------------- pip install lines
def _extras() -> dict[str, list[str]]:
    with open(ROOT / "pyproject.toml", "rb") as fh:
        return tomllib.load(fh)["project"].get("optional-dependencies", {})


def _declared() -> set[str]:
    """Distribution names the project declares (dependencies and every extra), lower-case."""
    with open(ROOT / "pyproject.toml", "rb") as fh:
        proj = tomllib.load(fh)["project"]
    reqs = list(proj.get("dependencies", [])) + [r for v in proj.get("optional-dependencies", {}).values() for r in v]
    return {re.split(r"[\s<>=!~;\[]", r, 1)[0].lower().replace("_", "-") for r in reqs}


def check_install(args: str, where: str, installed: bool = False) -> list[str]:
    """What is wrong with ``pip install <args>`` run from the checkout's root ([] when it works there);
    `installed`: run where closedloop is installed (a message of the package), so that
    ``"closedloop[EXTRA]"`` works too (pip keeps the installed closedloop, adds the extra's packages)."""
    try:
        words = shlex.split(args)
    except ValueError as exc:
        return [f"{where}: pip install {args}: {exc}"]
    problems, extras, declared = [], _extras(), _declared()
    k = 0
    while k < len(words):
        w = words[k]
        k += 1
        if w in ("-r", "--requirement", "-c", "--constraint"):
            if k >= len(words) or not (ROOT / words[k]).is_file():
                problems.append(f"{where}: pip install {args}: {w} names no file of the checkout")
            k += 1
            continue
        if w.startswith("-"):  # -e, -U, --upgrade, --no-deps ...
            continue
        m = re.fullmatch(r"([^\[\]]+?)(?:\[([^\]]*)\])?", w)
        if not m:
            problems.append(f"{where}: pip install {args}: '{w}' is not a requirement pip reads")
            continue
        target, wanted = m.group(1), [e.strip() for e in (m.group(2) or "").split(",") if e.strip()]
        if target.endswith(".whl") or target.startswith((".", "/")) or os.sep in target:
            if target.endswith(".whl"):  # a wheel built from the checkout (python -m build): its extras
                if not re.fullmatch(r"(.*/)?closedloop-[^-]+-py3-none-any\.whl", target):
                    problems.append(f"{where}: pip install {args}: '{target}' is not a closedloop wheel's name")
            elif not (ROOT / target / "pyproject.toml").is_file():
                problems.append(f"{where}: pip install {args}: '{target}' is not the checkout (run from its root)")
            missing = [e for e in wanted if e not in extras]
            if missing:
                problems.append(
                    f"{where}: pip install {args}: no extra {', '.join(missing)} in pyproject.toml "
                    f"(extras: {', '.join(sorted(extras))})"
                )
            if "[" in w and not re.search(r"""["']""", args):
                problems.append(f"{where}: pip install {args}: quote '{w}' (zsh and others expand [...])")
        else:
            name = re.split(r"[\s<>=!~;]", target, 1)[0].lower().replace("_", "-")
            if name == "closedloop" and installed and wanted:
                missing = [e for e in wanted if e not in extras]
                if missing:
                    problems.append(f"{where}: pip install {args}: no extra {', '.join(missing)} in pyproject.toml")
                if not re.search(r"""["']""", args):
                    problems.append(f"{where}: pip install {args}: quote '{w}' (zsh and others expand [...])")
            elif name == "closedloop":
                problems.append(
                    f"{where}: pip install {args}: closedloop is not published on an index; "
                    f'install from the checkout (pip install ".[{",".join(wanted)}]")'
                    if wanted
                    else f"{where}: pip install {args}: closedloop is not published; pip install . (checkout)"
                )
            elif name not in declared:
                problems.append(f"{where}: pip install {args}: '{name}' is no dependency of pyproject.toml")
    return problems


_TOKEN = re.compile(r"""\s+(-[\w-]+|"[^"\n]*"|'[^'\n]*'|[\w.\-/]+(?:\[[\w,\s-]*\])?(?:[<>=!~]=?[\w.*]+)?)""")
_PROSE = {"in", "from", "or", "and", "the", "to", "with", "for", "then", "if", "as", "is"}


def _install_args(text: str) -> list[str]:
    """The arguments of every ``pip install`` in a text: the requirement and option words that follow it,
    up to the end of the command or the first word of prose (``pip install ".[ros]" in the checkout``)."""
    text = text.replace('\\"', '"')  # quotes escaped inside Python strings
    out = []
    for m in re.finditer(r"\bpip3? install\b", text):
        pos, words = m.end(), []
        while (t := _TOKEN.match(text, pos)) and t.group(1) not in _PROSE:
            words.append(t.group(1))
            pos = t.end()
        out.append(" ".join(words))
    return out


def test_every_pip_install_written_in_the_pages_works_from_a_checkout():
    seen, problems = 0, []
    for page in PAGES:
        for n, line in enumerate(page.read_text(encoding="utf-8").splitlines(), start=1):
            for args in _install_args(line):
                seen += 1  # a line quoting what a command printed ("error: ...") runs where closedloop is installed
                problems += check_install(args, f"{page.relative_to(ROOT)}:{n}", installed="error: " in line)
    assert seen > 0, "the pages name no install command at all"
    assert problems == [], "\n".join(problems)


def test_every_install_hint_in_the_package_works_from_a_checkout():
    problems, seen = [], 0
    for src in sorted((ROOT / "closedloop").rglob("*.py")):
        text = src.read_text(encoding="utf-8")
        for args in _install_args(text):
            seen += 1
            if "{" not in args:  # a template (`closedloop.errors.require`): its extras are checked below
                problems += check_install(args, str(src.relative_to(ROOT)), installed=True)
        for extra in re.findall(r'(?:require\(\s*"[^"]+",|MissingExtraError\().+?,\s*"(\w+)"\s*\)', text):
            seen += 1
            problems += check_install(f'".[{extra}]"', f"{src.relative_to(ROOT)} (require ... {extra!r})")
    assert seen >= 3, "the ray, report and ros hints were not found"
    assert problems == [], "\n".join(problems)


@pytest.mark.parametrize(
    "args, ok",
    [
        (".", True),
        ('".[ros]"', True),
        ('".[ros,report]"', True),
        ("-e '.[test]'", True),
        ('".[rviz]"', False),  # no such extra
        ('"closedloop[ros,report]"', False),  # not on an index
        ("closedloop", False),
        (".[ros]", False),  # unquoted brackets
        ("matplotlib", True),  # a declared dependency
        ("numpy-quaternion", False),  # not one
        ("-r benchmarks/requirements-handeye.txt", True),
        ("-r no/such/requirements.txt", False),
        ('"dist/closedloop-0.1.0-py3-none-any.whl[ros]"', True),  # from a wheel
        ('"dist/closedloop-0.1.0-py3-none-any.whl[rviz]"', False),
    ],
)
def test_check_install_tells_working_lines_from_broken_ones(args, ok):
    assert (check_install(args, "x") == []) is ok


@pytest.mark.parametrize(
    "args, ok",
    [
        ('"closedloop[ros,report]"', True),
        ('"closedloop[rviz]"', False),
        ("closedloop[ros]", False),
        ("closedloop", False),
    ],
)
def test_an_installed_closedloop_may_name_its_extras(args, ok):
    assert (check_install(args, "x", installed=True) == []) is ok


# --------------------------------------------------------------------------- running the blocks
_PAGE_DIRS: dict[Path, Path] = {}
_RAN: dict[Path, set[str]] = {}  # per page, the blocks run in its folder by this process


def _run_earlier_blocks(block: Block, cwd: Path) -> None:
    """Run the page's runnable blocks above `block` that have not run in `cwd` (a worker that was handed
    this block without the ones before it, whose files it reads), each required to succeed."""
    for b in (b for b in BLOCKS if b.page == block.page and b.line < block.line):
        first = b.text.strip().splitlines()[0] if b.text.strip() else ""
        if b.id in _RAN.get(block.page, set()) or NOT_RUN.match(first):
            continue
        proc = run_script(prepare(b, check_install)[0], cwd, merged=False)
        assert proc.returncode == 0, f"{b.id} (run before {block.id}): exit {proc.returncode}\n{proc.stdout[-2000:]}"
        _RAN.setdefault(block.page, set()).add(b.id)


def _page_dir(page: Path, factory) -> Path:
    """One folder per page, shared by its blocks (run in page order)."""
    if page not in _PAGE_DIRS:
        _PAGE_DIRS[page] = page_dir(factory.mktemp(re.sub(r"\W", "_", str(page.relative_to(ROOT)))))
    return _PAGE_DIRS[page]


def test_the_pages_have_blocks_to_run():
    assert BLOCKS, "no ```bash block found in README.md or docs/"
    assert any("closedloop calibrate" in b.text for b in BLOCKS)


def test_every_shown_output_names_a_block_that_runs():
    """A ```text block marked ``<!-- output: NAME -->`` follows a runnable block of its page marked
    ``<!-- run: NAME -->``, and every block marked to run shows its output somewhere on the page."""
    problems, shown = [], 0
    for page in PAGES:
        runs = {b.run: b for b in blocks(page) if b.run}
        outs = shown_outputs(page)
        shown += len(outs)
        for name, ob in outs.items():
            if name not in runs or not runs[name].runnable or runs[name].line > ob.line:
                problems.append(f"{ob.id}: no runnable block marked <!-- run: {name} --> above it")
        problems += [
            f"{b.id}: marked to run as {n!r}, no <!-- output: {n} --> shows it"
            for n, b in runs.items()
            if n not in outs
        ]
    assert shown >= 3, "the pages show no regenerated output"
    assert problems == [], "\n".join(problems)


def test_compare_ignores_timings_paths_and_last_digits_only():
    assert (
        compare("simulated 200 configurations in 1.7 s -> out/sim", "simulated 200 configurations in 0.4 s -> out/sim")
        == []
    )
    assert compare("closure 1.428e-05 mm", "closure 1.43e-05 mm") == []
    assert compare("in 4 iterations", "in 3 iterations") != []
    assert compare("verdict: suspect", "verdict: ok") != []
    assert compare("a\n...\nz", "a\nb\nc\nz") == []
    assert compare("a\nb", "a\nb\nc") != []
    assert compare("wrote /tmp/x/out/r.json", "wrote out/r.json", None) != []
    assert compare("wrote out/r.json", "wrote /tmp/x/out/r.json", "/tmp/x") == []


@pytest.mark.slow
@pytest.mark.parametrize(
    "block",
    # one page's blocks on one worker, in page order: a later block reads what an earlier one wrote
    [pytest.param(b, marks=pytest.mark.xdist_group(str(b.page.relative_to(ROOT)))) for b in BLOCKS],
    ids=[b.id for b in BLOCKS],
)
def test_documented_block_runs(block: Block, tmp_path_factory):
    """Each block runs as written (exit 0); a block marked to run shows, on its page, what it prints."""
    first = block.text.strip().splitlines()[0] if block.text.strip() else ""
    m = NOT_RUN.match(first)
    if m:
        pytest.skip(f"{block.id}: not run: {m.group(1)}")
    script, held = prepare(block, check_install)
    cwd = _page_dir(block.page, tmp_path_factory)
    for h in held:
        print(f"checked, not run: {h}")
    _run_earlier_blocks(block, cwd)  # what this block reads: the page's earlier blocks, run in this folder
    proc = run_script(script, cwd, merged=block.run is not None)
    _RAN.setdefault(block.page, set()).add(block.id)
    assert proc.returncode == 0, (
        f"{block.id}: exit {proc.returncode}\n--- script\n{script}--- stdout (end)\n{proc.stdout[-3000:]}"
        f"--- stderr (end)\n{proc.stderr[-3000:]}"
    )
    if block.run:
        ob = shown_outputs(block.page).get(block.run)
        assert ob is not None, f"{block.id}: marked to run as {block.run!r}, shown nowhere"
        problems = compare(ob.text, proc.stdout, str(cwd))
        assert problems == [], f"{ob.id}: the shown output is not what runs (make docs-outputs):\n" + "\n".join(
            problems
        )
