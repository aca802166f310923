"""`calibrate --html/--plots`: one self-contained page (no script, figures embedded as PNG) and PNG files.

The page is checked structurally here (every section, the numbers of the fit, figures that decode
to non-blank images); `benchmarks/html_screenshot.sh` renders it in headless Chromium
(docs/report-screenshot.png).
"""

from __future__ import annotations

import base64
import io
import json
import re
from html.parser import HTMLParser

import numpy as np
import pytest
from matplotlib import image as mpimg

from closedloop.cli.main import main
from closedloop.io.logs import JointLog
from closedloop.loops import WeldLoop
from closedloop.model.robot import RobotModel
from closedloop.models import ROBOTS
from closedloop.studies.truth import make_dataset


class Page(HTMLParser):
    def __init__(self):
        super().__init__()
        self.tags: list[str] = []
        self.h2: list[str] = []
        self.images: list[dict] = []
        self.links: list[str] = []
        self._in = None
        self.text: list[str] = []

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        a = dict(attrs)
        if tag == "img":
            self.images.append(a)
        if tag in ("link", "script", "iframe") or (tag == "a" and "href" in a):
            self.links.append(tag)
        self._in = tag

    def handle_data(self, data):
        if self._in == "h2":
            self.h2.append(data.strip())
        self.text.append(data)


def decode(png: bytes) -> np.ndarray:
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    return mpimg.imread(io.BytesIO(png), format="png")


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    robot = RobotModel.from_file(ROBOTS["panda"].path)
    ds = make_dataset(
        robot,
        WeldLoop("fixture", "panda_hand"),
        [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8],
        30,
        np.random.default_rng(2),
        noise=1e-5,
    )
    d = tmp_path_factory.mktemp("html")
    log = d / "log.csv"
    JointLog(list(ds.joints), ds.noisy).write_csv(log)
    args = [
        str(ROBOTS["panda"].path),
        str(log),
        "--loop",
        "weld:frame=panda_hand,name=fixture",
        "--cv",
        "2",
        "--identify",
        "placement,offset,scale,loop",
        "--out",
        str(d / "calibrated.urdf"),
        "--report",
        str(d / "report.json"),
        "--html",
        str(d / "report.html"),
        "--plots",
        str(d / "plots"),
        "--quiet",
    ]
    assert main(["calibrate", *args]) == 0
    return d


def test_page_is_self_contained_with_every_section(calibrated):
    html = (calibrated / "report.html").read_text()
    report = json.loads((calibrated / "report.json").read_text())
    page = Page()
    page.feed(html)
    assert page.tags[0] == "html" and "body" in page.tags
    assert page.links == []  # nothing to load, no script
    assert page.h2[:6] == [
        "Closure",
        "Parameter corrections",
        "Singular values",
        "Outliers",
        "Not identified",
        "Which file carries what",
    ]
    assert re.search(r"verdict: <b>(ok|suspect|failed)</b>", html)
    text = " ".join(page.text)
    assert "2-fold validation" in text
    # every estimated parameter in the corrections table, with its standard error
    est = [p for p in report["parameters"] if p["status"] == "estimated"]
    assert len(est) > 20
    for p in est:
        assert p["name"] in text
        assert f"{p['std_error']:.2e}" in text
    # the structurally redundant parameters with the combination that absorbs them
    for d in report["identifiability"]["dropped"]:
        assert d["name"] in text
    assert "its effect equals" in text
    # the truncation line: the SVD threshold of the fit, consistent with the number of kept directions
    m = re.search(r"(\d+) of (\d+) directions kept; truncation at ([0-9.e+-]+)", text)
    sv = report["identifiability"]["singular_values"]
    assert m and int(m.group(2)) == len(sv)
    assert sum(s > float(m.group(3)) for s in sv) == int(m.group(1))
    # the five largest closures after the fit, by log row, largest first
    outl = html[html.index("<h2>Outliers</h2>") : html.index("<h2>Not identified</h2>")]
    rows = re.findall(r"<tr><td class='l'>fixture</td><td>(\d+)</td><td>([0-9.e+-]+)</td>", outl)
    assert len(rows) == 5 and all(1 <= int(r) <= 30 for r, _ in rows)
    sizes = [float(v) for _, v in rows]
    assert sizes == sorted(sizes, reverse=True) and sizes[0] < 1.0  # mm, after a fit to 1e-5 rad noise


def test_sensor_corrections_beside_the_model(calibrated):
    """Scale factors cannot be expressed in URDF: a small YAML beside it carries them, as the report does."""
    import yaml

    report = json.loads((calibrated / "report.json").read_text())
    corr = yaml.safe_load((calibrated / "calibrated.sensors.yaml").read_text())
    scales = {
        n.rsplit(".", 1)[0]: v
        for n, v in report["scale_factors"].items()
        if next(p for p in report["parameters"] if p["name"] == n)["status"] == "estimated"
    }
    assert scales and {j: c["scale"] for j, c in corr["joints"].items()} == pytest.approx(scales, abs=1e-15)
    assert all(abs(v - 1.0) < 0.01 for v in scales.values())  # the truth has no scale error
    assert corr["model"].endswith("calibrated.urdf") and "scale * reading" in corr["note"]


def test_figures_decode(calibrated):
    html = (calibrated / "report.html").read_text()
    srcs = re.findall(r"src='data:image/png;base64,([A-Za-z0-9+/=]+)'", html)
    assert len(srcs) == 3
    for s in srcs:
        img = decode(base64.b64decode(s))
        assert img.shape[0] > 200 and img.shape[1] > 500
        assert img[..., :3].std() > 0.05  # drawn, not blank
    files = sorted(p.name for p in (calibrated / "plots").iterdir())
    assert files == ["closure.png", "corrections.png", "singular_values.png"]
    for f in files:
        assert decode((calibrated / "plots" / f).read_bytes()).shape[0] > 200
