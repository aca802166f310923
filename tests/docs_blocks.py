"""The runnable blocks of README.md and docs/, and the outputs they show.

A page's blocks run in page order in one folder (as a reader following the page would), with
``closedloop``, ``python`` and ``python3`` being this interpreter and checkout:

* every ```bash block (install and virtual-environment lines checked, not run: `prepare`);
* a ```python block marked ``<!-- run: NAME -->`` on the line before it.

A block marked ``<!-- run: NAME -->`` has its output (stdout and stderr, interleaved) recorded; a ```text
block marked ``<!-- output: NAME -->`` shows it.  A line ``...`` alone in a shown output stands for any
number of lines.  ``<!-- setup: COMMAND -->`` runs COMMAND (bash) before the next block of the page.

Shown and fresh outputs are compared line by line (`compare`), ignoring only what a machine changes:
timings, the run's own folder, and the last digits of measured figures (numbers agree to 2 %, or both
are below 1e-6 in magnitude, round-off's own level in these outputs).

``python tests/docs_blocks.py --write [PAGE ...]`` (``make docs-outputs``) runs the pages and writes the
fresh outputs into them; ``tests/test_docs_commands.py`` runs the same blocks and fails where a shown
output differs from what runs.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGES = [p for p in [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))] if p.is_file()]
NOT_RUN = re.compile(r"^#\s*not run:\s*(\S.*)$")
RUN = re.compile(r"^\s*<!--\s*run:\s*([\w.-]+)\s*-->\s*$")
OUTPUT = re.compile(r"^\s*<!--\s*output:\s*([\w.-]+)\s*-->\s*$")
SETUP = re.compile(r"^\s*<!--\s*setup:\s*(.*?)\s*-->\s*$")


@dataclass
class Block:
    """A fenced block of a page: its language, the line of its opening fence (1-based), its text, and the
    markers on the lines before it (``run``/``output`` name, ``setup`` commands)."""

    page: Path
    line: int
    lang: str
    text: str
    end: int = 0  # the line of its closing fence
    run: str | None = None
    output: str | None = None
    setup: list[str] = field(default_factory=list)

    @property
    def id(self) -> str:
        return f"{self.page.relative_to(ROOT)}:{self.line}"

    @property
    def runnable(self) -> bool:
        return self.lang in ("bash", "sh", "shell") or (self.lang == "python" and self.run is not None)


def blocks(page: Path) -> list[Block]:
    """The fenced blocks of a Markdown page, with their markers."""
    out, lines = [], page.read_text(encoding="utf-8").splitlines()
    k = 0
    marks: dict = {"setup": []}
    while k < len(lines):
        for rx, key in ((RUN, "run"), (OUTPUT, "output")):
            if m := rx.match(lines[k]):
                marks[key] = m.group(1)
        if m := SETUP.match(lines[k]):
            marks["setup"].append(m.group(1))
        m = re.match(r"^(\s*)(```+|~~~+)\s*(\w+)?", lines[k])
        if not m:
            if lines[k].strip() and not lines[k].lstrip().startswith("<!--"):
                marks = {"setup": marks["setup"]}  # run/output mark only the block right below them
            k += 1
            continue
        fence, lang, start = m.group(2), (m.group(3) or "").lower(), k
        k += 1
        body = []
        while k < len(lines) and not lines[k].strip().startswith(fence):
            body.append(lines[k][len(m.group(1)) :] if lines[k].startswith(m.group(1)) else lines[k])
            k += 1
        out.append(
            Block(
                page,
                start + 1,
                lang,
                "\n".join(body) + "\n",
                k + 1,
                marks.get("run"),
                marks.get("output"),
                marks["setup"],
            )
        )
        marks = {"setup": []}
        k += 1
    return out


# --------------------------------------------------------------------------- preparing and running a block
SETUP_ONLY = [  # lines a reader runs to set up an environment: the test environment is one
    re.compile(r"^python3? -m venv\b"),
    re.compile(r"^(\.|source)\s+\S*bin/activate$"),
]


def prepare(block: Block, check_install: Callable[[str, str], list[str]]) -> tuple[str, list[str]]:
    """The bash script run for a block, and what of it is checked but not run (install, venv, pytest)."""
    if block.lang == "python":
        body = "\n".join(block.setup + [f"python - <<'CLOSEDLOOP_PY'\n{block.text}CLOSEDLOOP_PY"])
        return body + "\n", []
    text = re.sub(r"\\\n", " ", block.text)  # continuation lines joined
    script, held = list(block.setup), []
    for line in text.splitlines():
        kept = []
        for part in re.split(r"\s+&&\s+", line):
            cmd = part.strip()
            inst = re.match(r"^(?:python3? -m )?pip3? install\s+(.*)$", cmd)
            if inst:
                problems = check_install(inst.group(1), block.id)
                assert problems == [], "\n".join(problems)
                held.append(cmd)
            elif any(r.match(cmd) for r in SETUP_ONLY):
                held.append(cmd)
            elif re.match(r"^(python3? -m )?pytest\b", cmd):
                held.append(cmd + "  (the test suite this test is part of)")
            else:
                kept.append(part)
        script.append(" && ".join(kept))
    return "\n".join(script) + "\n", held


def page_dir(parent: Path) -> Path:
    """A folder for one page's blocks: examples/ linked in, and shims for closedloop / python / python3."""
    (parent / "examples").symlink_to(ROOT / "examples")
    bin_dir = parent / ".bin"
    bin_dir.mkdir(exist_ok=True)
    for name, exe in (
        ("closedloop", f'exec "{sys.executable}" -m closedloop.cli.main "$@"'),
        ("python", f'exec "{sys.executable}" "$@"'),
        ("python3", f'exec "{sys.executable}" "$@"'),
    ):
        p = bin_dir / name
        p.write_text(f"#!/bin/sh\n{exe}\n")
        p.chmod(0o755)
    return parent


def run_script(script: str, cwd: Path, merged: bool) -> subprocess.CompletedProcess:
    """Run a prepared script in a page's folder, with this checkout's package; `merged`: stderr into stdout
    (the order a terminal shows)."""
    env = dict(os.environ)
    env["PATH"] = f"{cwd / '.bin'}{os.pathsep}{env.get('PATH', '')}"
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in [env.get("PYTHONPATH")] if p])
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    env.setdefault("MPLBACKEND", "Agg")
    env["COLUMNS"] = "120"
    return subprocess.run(
        ["bash", "-e", "-o", "pipefail", "-c", ("exec 2>&1\n" if merged else "") + script],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,  # a hang guard, not a timing
    )


# --------------------------------------------------------------------------- comparing outputs
_TIME = re.compile(r"\b\d+(?:\.\d+)?(?:e[-+]?\d+)?\s?(?:s|ms|min)\b")
_NUMBER = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")


def _normal(line: str, cwd: str | None) -> str:
    if cwd:
        line = line.replace(cwd + "/", "").replace(cwd, ".")
    return _TIME.sub("<time>", line.rstrip())


def _same_line(shown: str, fresh: str) -> bool:
    a, b = _NUMBER.split(shown), _NUMBER.split(fresh)
    if a != b:
        return False
    for x, y in zip(_NUMBER.findall(shown), _NUMBER.findall(fresh)):
        u, v = float(x), float(y)
        if abs(u - v) > 0.02 * max(abs(u), abs(v)) and not (abs(u) < 1e-6 and abs(v) < 1e-6):
            return False
    return True


def _segments(lines: list[str]) -> list[list[str]]:
    """The runs of lines between the ``...`` lines of a shown output (empty runs where it starts or ends so)."""
    segments: list[list[str]] = [[]]
    for line in lines:
        if line.strip() == "...":
            segments.append([])
        else:
            segments[-1].append(line)
    return segments


def compare(shown: str, fresh: str, cwd: str | None = None) -> list[str]:
    """Where a shown output differs from a fresh run ([] when it matches); ``...`` lines match any lines."""
    want = [_normal(s, None) for s in shown.rstrip("\n").splitlines()]
    got = [_normal(s, cwd) for s in fresh.rstrip("\n").splitlines()]
    segments = _segments(want)
    at = 0
    for n, seg in enumerate(segments):
        if not seg:
            continue
        first, last = n == 0, n == len(segments) - 1
        starts = [at] if first else range(at, len(got) - len(seg) + 1)
        if last and not first:
            starts = [len(got) - len(seg)] if len(got) - len(seg) >= at else []
        hit = next((s for s in starts if all(_same_line(w, g) for w, g in zip(seg, got[s : s + len(seg)]))), None)
        if hit is None or hit + len(seg) > len(got):
            return [f"shown lines from {seg[0]!r} do not match the fresh output:\n" + "\n".join(got)]
        at = hit + len(seg)
    if segments[-1] and at != len(got):
        return ["the fresh output has more lines than shown (end the shown block with '...'):\n" + "\n".join(got)]
    return []


def regenerate(shown: str, fresh: str, cwd: str | None = None) -> str:
    """The fresh output in the shown block's form: where the shown block elides lines (``...``), each shown
    run of lines is replaced by the fresh lines found where its first line's words (numbers aside) are, in
    order; the first run is the output's first lines, the last its last lines."""
    raw = fresh.rstrip("\n").splitlines()
    if cwd:
        raw = [r.replace(cwd + "/", "").replace(cwd, ".") for r in raw]
    want = shown.rstrip("\n").splitlines()
    if not any(w.strip() == "..." for w in want):
        return "\n".join(raw) + "\n"
    segments = _segments(want)
    out: list[str] = []
    at = 0
    for n, seg in enumerate(segments):
        if n:
            out.append("...")
        if not seg:
            continue
        if n == 0:
            start = 0
        elif n == len(segments) - 1:
            start = max(at, len(raw) - len(seg))
        else:
            words = _NUMBER.split(_normal(seg[0], None))  # the line's text with its numbers taken out
            start = next((k for k in range(at, len(raw)) if _NUMBER.split(_normal(raw[k], None)) == words), at)
        out += raw[start : start + len(seg)]
        at = start + len(seg)
    return "\n".join(out) + "\n"


def shown_outputs(page: Path) -> dict[str, Block]:
    return {b.output: b for b in blocks(page) if b.output}


# --------------------------------------------------------------------------- make docs-outputs
def write_outputs(pages: list[Path], check_install: Callable[[str, str], list[str]]) -> list[str]:
    """Run each page's blocks in order and write the fresh outputs into its marked ```text blocks."""
    done = []
    for page in pages:
        wanted = shown_outputs(page)
        if not wanted:
            continue
        with tempfile.TemporaryDirectory() as tmp:
            cwd = page_dir(Path(tmp))
            fresh: dict[str, str] = {}
            for b in blocks(page):
                if not b.runnable or (b.text.strip() and NOT_RUN.match(b.text.strip().splitlines()[0])):
                    continue
                script, _ = prepare(b, check_install)
                proc = run_script(script, cwd, merged=b.run is not None)
                if proc.returncode != 0:
                    raise SystemExit(f"{b.id}: exit {proc.returncode}\n{proc.stdout[-3000:]}{proc.stderr[-3000:]}")
                if b.run:
                    fresh[b.run] = proc.stdout
            lines = page.read_text(encoding="utf-8").splitlines()
            for name, ob in sorted(wanted.items(), key=lambda kv: -kv[1].line):  # bottom up: line numbers hold
                if name not in fresh:
                    raise SystemExit(f"{ob.id}: no block marked <!-- run: {name} --> before it")
                new = regenerate(ob.text, fresh[name], str(cwd)).rstrip("\n").splitlines()
                indent = lines[ob.line - 1][: len(lines[ob.line - 1]) - len(lines[ob.line - 1].lstrip())]
                lines[ob.line : ob.end - 1] = [indent + n if n else n for n in new]
            page.write_text("\n".join(lines) + "\n", encoding="utf-8")
            done.append(str(page.relative_to(ROOT)))
    return done


if __name__ == "__main__":
    import argparse

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from test_docs_commands import check_install

    ap = argparse.ArgumentParser(description="Write fresh outputs into the docs' marked ```text blocks.")
    ap.add_argument("--write", action="store_true", required=True)
    ap.add_argument("pages", nargs="*", type=Path, help="pages (default: README.md and docs/**/*.md)")
    ns = ap.parse_args()
    for p in write_outputs([p.resolve() for p in ns.pages] or PAGES, check_install):
        print(f"wrote {p}")
