"""Eq 2.5 against Tables 2.1-2.3 as printed in the dissertation (the independent truth)."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from cell.cli import app
from cell.sensing.error_model import TABLES, error_table, one_pixel_error

# Copied from the dissertation text (seed 000_19b468d25b1034ee.txt), rows m = 53, 64, 87.
BOOK = {
    "Table 2.1": [
        [0.4535, 0.2590, 0.1792, 0.1335],
        [0.4414, 0.2551, 0.1774, 0.1325],
        [0.4177, 0.2446, 0.1737, 0.1304],
    ],
    "Table 2.2": [
        [0.1681, 0.1530, 0.1335, 0.0702],
        [0.1665, 0.1517, 0.1325, 0.0699],
        [0.1632, 0.1489, 0.1304, 0.0693],
    ],
    "Table 2.3": [
        [0.0805, 0.0775, 0.0750, 0.0702],
        [0.0802, 0.0772, 0.0747, 0.0699],
        [0.0795, 0.0766, 0.0741, 0.0693],
    ],
}
# Table 2.1, d=213.4, m=87 prints 0.2446; eq 2.5 gives 0.2474 (digits transposed in the book: the column's
# steps 0.0039 then 0.0077 follow the 11- and 23-pixel steps of m like every other column, 0.0105 does not).
ERRATUM = ("Table 2.1", 2, 1)


@pytest.mark.parametrize("index", range(3))
def test_tables_match_book_to_4_decimals(index: int) -> None:
    title, varied, values, fixed = TABLES[index]
    key = title.split(".")[0] + "." + title.split(".")[1]
    computed = np.round(error_table(varied, values, fixed), 4)
    book = np.array(BOOK[key])
    mask = np.ones_like(book, dtype=bool)
    if ERRATUM[0] == key:
        mask[ERRATUM[1], ERRATUM[2]] = False
        assert computed[ERRATUM[1], ERRATUM[2]] == pytest.approx(0.2474, abs=5e-5)
    np.testing.assert_allclose(computed[mask], book[mask], atol=1e-9)


def test_eq25_is_the_height_change_of_one_pixel() -> None:
    """Eq 2.5 equals h(m) - h(m-1) from eq 2.4 (independent derivation)."""
    res, S, d, m = 0.151, 393.7, 429.3, np.arange(1, 200)
    h = lambda mm: res * mm * S / (d + res * mm)  # noqa: E731
    np.testing.assert_allclose(one_pixel_error(res, S, d, m), h(m) - h(m - 1), rtol=1e-12)


def test_cli_prints_three_tables() -> None:
    out = CliRunner().invoke(app, ["sensor", "error-table"])
    assert out.exit_code == 0, out.output
    for title, *_ in TABLES:
        assert title in out.output
    assert "m=53pix\t0.4535\t0.2590\t0.1792\t0.1335" in out.output
