"""The generated reference pages in docs/ are what the code generates now (run `cell docs` after a change)."""

from __future__ import annotations

from pathlib import Path

import pytest

from cell.docgen import pages

DOCS = Path(__file__).resolve().parent.parent / "docs"


@pytest.mark.parametrize("name", sorted(pages()))
def test_generated_page_is_current(name: str) -> None:
    assert (DOCS / name).read_text() == pages()[name], f"docs/{name} is stale: run `cell docs`"


def test_schema_pages_list_every_field() -> None:
    text = pages()["recipe-schema.md"]
    for field in ("`cad`", "`tolerance`", "`lower`", "`min_coverage`", "`view_budget`", "`T_W_P`"):
        assert field in text
