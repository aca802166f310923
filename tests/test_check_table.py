"""`closedloop check`'s table keeps its columns under their headings when a loop's row name is long (a weld
between two fingers: 'pinch: frame link_3.0_tip relative to link_15.0_tip position', 59 characters)."""

from __future__ import annotations

from closedloop.cli.main import _print_rows

LONG = "pinch: frame link_3.0_tip relative to link_15.0_tip position"


def _row(name: str, error: float, predicted: float) -> dict:
    return {
        "name": name,
        "true": None,
        "calibrated": None,
        "error": error,
        "predicted": predicted,
        "ratio": error / predicted,
        "tol": 0.001,
        "result": "FAIL" if error > 0.001 else "ok",
    }


def test_long_row_names_keep_the_columns_aligned(capsys):
    rows = [_row(LONG, 0.00677, 0.0129), _row("size (not measured by the data)", 0.0252, 0.0425)]
    _print_rows(rows, "loop / quantity")
    lines = capsys.readouterr().out.splitlines()
    header, body = lines[0], lines[1:3]
    for line, r in zip(body, rows):
        assert line.startswith(r["name"] + " ")  # the name whole, then a space before the numbers
        # each figure ends where its heading ends
        for heading, text in (("error", f"{r['error']:.3g}"), ("ratio", f"{r['ratio']:.2f}"), ("tol", "0.001")):
            assert line.index(text) + len(text) == header.index(heading) + len(heading), (heading, line)
        assert line.index(r["result"]) == header.index("result")


def test_short_names_keep_the_forty_character_column(capsys):
    """The README's main job prints its rows in the 40-character column, as before."""
    _print_rows([_row("fixture: frame panda_hand_tcp position", 5.72e-06, 5.43e-06)], "loop / quantity")
    header, row = capsys.readouterr().out.splitlines()[:2]
    assert header.index("true") + len("true") == 40 + 14
    assert row.index("5.72e-06") + len("5.72e-06") == header.index("error") + len("error")


def test_a_huge_ratio_keeps_its_column(capsys):
    """A prediction 3e7 times below the observed error (a two-finger point loop whose prediction failed)
    printed '31349536.52' into the 8-character ratio column, run together with the predicted error."""
    row = _row("pinch: tool point link_3.0_tip relative to link_15.0_tip position", 0.221, 7.06e-09)
    _print_rows([row], "loop / quantity")
    header, line = capsys.readouterr().out.splitlines()[:2]
    assert line.index("3.1e+07") + len("3.1e+07") == header.index("ratio") + len("ratio")
    assert "7.06e-09 " in line  # the predicted error apart from the ratio
