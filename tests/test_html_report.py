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
import struct
from html.parser import HTMLParser

import numpy as np
import pytest

from closedloop.assets.catalog import ROBOTS
from closedloop.cli.main import main
from closedloop.io.logs import JointLog
from closedloop.loops import WeldLoop
from closedloop.model.robot import RobotModel
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


def decode(png: bytes) -> np.ndarray | tuple[int, int]:
    """A PNG decoded (matplotlib, else PIL); without either, its header checked and its (height, width)."""
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and png[12:16] == b"IHDR" and png[-8:-4] == b"IEND"
    try:
        from matplotlib import image as mpimg

        return mpimg.imread(io.BytesIO(png), format="png")
    except ImportError:
        pass
    try:
        from PIL import Image

        return np.asarray(Image.open(io.BytesIO(png)).convert("RGBA"), float) / 255.0
    except ImportError:
        w, h = struct.unpack(">II", png[16:24])
        return h, w


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
        "--regions",  # (3 s of the run's 6 s); the page's regions table: test_html_accuracy.py
        "0",
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


@pytest.mark.slow
def test_page_is_self_contained_with_every_section(calibrated):
    html = (calibrated / "report.html").read_text()
    report = json.loads((calibrated / "report.json").read_text())
    page = Page()
    page.feed(html)
    assert page.tags[0] == "html" and "body" in page.tags
    assert page.links == []  # nothing to load, no script
    assert page.h2[:7] == [
        "Closure",
        "Predicted accuracy over the workspace",
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
    log = re.escape(str(calibrated / "log.csv"))
    rows = re.findall(rf"<tr><td class='l'>fixture</td><td>{log} line (\d+)</td><td>([0-9.e+-]+) mm</td>", outl)
    assert len(rows) == 5 and all(2 <= int(r) <= 31 for r, _ in rows)  # the file's lines (header: line 1)
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
    assert len(srcs) == 4  # closure, predicted accuracy over the workspace, corrections, singular values
    for s in srcs:
        img = decode(base64.b64decode(s))
        if isinstance(img, tuple):  # neither matplotlib nor PIL to decode it: its size from the header
            assert img[0] > 200 and img[1] > 500
            continue
        assert img.shape[0] > 200 and img.shape[1] > 500
        assert img[..., :3].std() > 0.05  # drawn, not blank
    files = sorted(p.name for p in (calibrated / "plots").iterdir())
    assert files == ["accuracy.png", "closure.png", "corrections.png", "singular_values.png"]
    for f in files:
        img = decode((calibrated / "plots" / f).read_bytes())
        assert (img[0] if isinstance(img, tuple) else img.shape[0]) > 200


def test_title_is_the_robots_name_and_the_verdict_comes_before_any_figure(calibrated):
    html = (calibrated / "report.html").read_text()
    name = RobotModel.from_file(ROBOTS["panda"].path).model.name
    assert name and name != ROBOTS["panda"].path.name
    assert f"<title>{name}: closedloop calibration</title>" in html
    assert f"<h1>{name}: closedloop calibration</h1>" in html
    assert ROBOTS["panda"].path.name not in html.split("</h1>")[0]
    verdict = html.index("<div class='verdict")
    assert verdict < html.index("<img") and verdict < html.index("<h2>")  # the first screen
    page = Page()
    page.feed(html)
    assert page.tags.index("div") < page.tags.index("img")


def test_every_figure_is_embedded(calibrated):
    html = (calibrated / "report.html").read_text()
    page = Page()
    page.feed(html)
    assert len(page.images) == 4
    assert any(img.get("alt") == "predicted accuracy" for img in page.images)
    for img in page.images:
        src = img["src"]
        assert src.startswith("data:image/png;base64,") and img.get("alt")
        png = base64.b64decode(src.split(",", 1)[1], validate=True)
        w, h = struct.unpack(">II", png[16:24])
        assert w > 500 and h > 200


def test_units_on_every_number_of_the_summary(calibrated):
    html = (calibrated / "report.html").read_text()
    report = json.loads((calibrated / "report.json").read_text())
    assert f"{report['noise']['joint_sigma']:.3g} rad (estimated)" in html
    head = html[html.index("<h2>Closure</h2>") : html.index("<img")]
    assert "RMS before [mm]" in head and "after [mrad]" in head


def test_closure_axis_is_not_stretched_by_one_near_zero_value():
    from closedloop.output.html import closure_axis

    rng = np.random.default_rng(0)
    before = rng.uniform(0.5, 3.0, 200)  # mm
    before[17] = 1e-9  # one configuration that closes by chance
    after = rng.uniform(1e-3, 1e-2, 200)
    lo, hi = closure_axis(np.concatenate([before, after]))
    assert hi == pytest.approx(before.max())
    assert 1e-4 <= lo < 2.5e-4  # a decade below the after closures' low end, not 1e-9
    lo, hi = closure_axis(np.r_[np.full(50, 1e-13), 1.0])  # an exact fit: at most 6 decades below the top
    assert lo == pytest.approx(1e-6) and hi == 1.0
    assert closure_axis(np.array([0.0, np.nan])) == (1e-12, 1.0)


def test_a_joint_that_never_moves_is_named_with_its_range_in_radians(panda):
    from closedloop.analysis.selection import check_motion
    from closedloop.calibration.pipeline import build_problem

    ds = make_dataset(
        panda, WeldLoop("fixture", "panda_hand"), [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8], 20, np.random.default_rng(1)
    )
    theta = np.array(ds.readings, float)
    theta[:, ds.joints.index("panda_joint7")] = 0.8
    prob = build_problem(panda, JointLog(list(ds.joints), theta), [WeldLoop("fixture", "panda_hand")])
    status = ["selected"] * len(prob.names)
    notes, _, _ = check_motion(prob, prob.nominal, status)
    assert any("joint panda_joint7 never moves in the data (range 0.00e+00 rad)" in n for n in notes), notes


def test_the_grasp_configuration_does_not_stretch_the_closure_axis(panda):
    """'Before' is the nominal robot with the fixture fitted to all configurations, so no configuration
    closes by construction (the solver's start places the fixture at the first one, which would show ~1e-9
    mm); the axis spans the closures."""
    from closedloop.calibration.pipeline import calibrate
    from closedloop.output.html import closure_axis, closure_per_configuration, fig_closure

    ds = make_dataset(
        panda,
        WeldLoop("fixture", "panda_hand"),
        [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8],
        30,
        np.random.default_rng(2),
        noise=1e-5,
    )
    res = calibrate(panda, JointLog(list(ds.joints), ds.noisy), [WeldLoop("fixture", "panda_hand")])
    d = closure_per_configuration(res)[0]
    before, after = d["before_m"] * 1e3, d["after_m"] * 1e3  # mm
    assert before.min() > 1e-2 * np.median(before), before[:3]  # none closes by construction
    lo, hi = closure_axis(np.concatenate([before, after]))
    assert hi == pytest.approx(before.max())
    assert lo < after.min()  # every 'after' point on the axis
    img = decode(fig_closure(res, {}))
    if not isinstance(img, tuple):
        assert img.shape[0] > 200 and img[..., :3].std() > 0.05
