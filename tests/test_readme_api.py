"""The README's Python example runs as written, importing from `closedloop` alone."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def _api_example() -> str:
    text = README.read_text()
    section = text[text.index("## Python API") :]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_readme_python_example_runs(tmp_path, monkeypatch, panda_weld):
    from closedloop.assets.catalog import ROBOTS

    code = _api_example()
    imports = [ln for ln in code.splitlines() if ln.startswith(("from ", "import "))]
    assert imports and all(ln.startswith("from closedloop import") for ln in imports), imports
    shutil.copy(ROBOTS["panda"].path, tmp_path / "panda.urdf")
    panda_weld.log().write_csv(tmp_path / "log.csv")
    monkeypatch.chdir(tmp_path)
    env: dict = {}
    exec(compile(code, "README.md", "exec"), env)
    assert env["res"].verdict.status == "ok"
    shown = README.read_text().split("its first lines:", 1)[1]
    first = re.search(r"```text\n(.*?)\n", shown).group(1)
    assert first == env["res"].verdict.describe(), first  # the README shows the line the example prints
    assert (tmp_path / "calibrated.urdf").exists() and (tmp_path / "report.json").exists()
