"""``cell docs``: regenerate the reference pages that come from the code (schemas, state diagram)."""

from __future__ import annotations

from pathlib import Path

import typer

DOCS = Path(__file__).resolve().parents[2] / "docs"


def register(app: typer.Typer) -> None:
    @app.command("docs")
    def docs_cmd(out: Path = typer.Option(DOCS, "--out", help="folder to write the pages into")) -> None:
        """Write docs/recipe-schema.md, docs/cell-config-schema.md and docs/state-machine.md from the code."""
        typer.echo(f"writing the pages made from the code into {out}")
        from cell.docgen import pages

        out.mkdir(parents=True, exist_ok=True)
        for name, text in pages().items():
            (out / name).write_text(text)
            typer.echo(f"wrote {out / name}")
