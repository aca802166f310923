"""Joint torques in a log (``tau:<joint>`` columns): a missing or non-finite one is named by its file,
line and column."""

from __future__ import annotations

import pytest

from closedloop.errors import LogError
from closedloop.io.logs import read_log


@pytest.mark.parametrize("cell", ["", "nan", "inf"])
def test_a_torque_that_is_not_a_number_names_its_line_and_column(tmp_path, cell):
    path = tmp_path / "log.csv"
    path.write_text(f"a,b,tau:a,tau:b\n0.1,0.2,1.5,2.5\n0.3,0.4,1.0,{cell}\n")
    log = read_log(path, ["a", "b"])
    with pytest.raises(LogError) as err:
        log.torques(["a", "b"])
    assert str(err.value).startswith(f"{path} line 3, column 'tau:b': ")
    assert "not a finite torque" in str(err.value)


def test_finite_torques_are_read_in_the_order_asked(tmp_path):
    path = tmp_path / "log.csv"
    path.write_text("a,b,tau:b,tau:a\n0.1,0.2,2.5,1.5\n0.3,0.4,2.0,1.0\n")
    tau = read_log(path, ["a", "b"]).torques(["a", "b"])
    assert tau is not None and tau.tolist() == [[1.5, 2.5], [1.0, 2.0]]
