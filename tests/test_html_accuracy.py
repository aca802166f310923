"""The HTML report's accuracy section says where to measure next when ``--suggest`` chose configurations,
with the figures the summary prints, and the closure of each region of joint space held out."""

from __future__ import annotations

from closedloop.output.html import _accuracy

FRAME = {"loop": "socket", "frame": "tool", "predicted_rms_m": 6.19e-5, "predicted_max_m": 1.49e-4}
WORKSPACE = {"source": "200 random readings", "error_bars": "the noise model", "frames": [FRAME]}


def test_the_suggested_configurations_are_on_the_page():
    nxt = {
        "file": "out/next.csv",
        "loop": "socket",
        "configurations": 10,
        "predicted_rms_before_m": 6.19e-5,
        "predicted_rms_after_m": [3e-5, 1.2e-5, 8.61e-6],
    }
    page = _accuracy({"accuracy": {"workspace": WORKSPACE, "next_poses": nxt}})
    assert (
        "where to measure next: 10 configurations of loop socket in out/next.csv: predicted RMS 0.0619 mm -&gt; "
        "0.00861 mm once recorded and calibrated again" in page
    )


def test_no_suggestion_no_line():
    assert "where to measure next" not in _accuracy({"accuracy": {"workspace": WORKSPACE}})


def test_held_out_regions_are_a_table_in_millimetres_and_milliradians():
    regions = {"k": 3, "test": [{"loop": "socket", "rms_m": 2.5e-4, "rms_rad": 1.25e-3}]}
    page = _accuracy({"accuracy": {"workspace": WORKSPACE, "regions": regions}})
    assert "3 regions of joint space held out in turn" in page
    table = page[page.index("3 regions of joint space") :]
    assert "held-out [mm]" in table and "held-out [mrad]" in table
    assert "socket" in table and "0.25" in table and "1.25" in table
    assert "regions of joint space" not in _accuracy({"accuracy": {"workspace": WORKSPACE}})
