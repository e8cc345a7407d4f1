"""``cell compare NOMINAL CLOUD``: error map and report of any cloud against any nominal mesh."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command()
    def compare(
        nominal: Path = typer.Argument(..., help="nominal mesh (STL/PLY/OBJ, mm)"),
        cloud: Path = typer.Argument(..., help="measured cloud (PLY/XYZ/CSV, mm)"),
        out: Path = typer.Option(
            ..., "--out", help="folder for report.json, report.html and cloud.ply (deviation field)"
        ),
        align: str = typer.Option("none", help="none | datums | bestfit (best-fit hides global deviations)"),
        tolerance: str = typer.Option("-0.3,0.3", help="tolerance band LOWER,UPPER in mm"),
        datums: Path = typer.Option(None, help="csv of datum pairs for --align datums"),
        regions: Path = typer.Option(
            None, help="YAML of user regions (face sets or boxes) judged one by one"
        ),
        density: float = typer.Option(None, help="coverage: required points per mm^2 of nominal surface"),
        radius: float = typer.Option(None, help="coverage: search radius in mm (alone: one point covers)"),
        min_coverage: float = typer.Option(None, help="required covered fraction 0..1 (else 'incomplete')"),
        min_defect_points: int = typer.Option(
            1,
            help="out-of-tolerance clusters smaller than this are isolated outliers, excluded and counted "
            "(cell inspect uses 10; 1 keeps every point)",
        ),
        csv: bool = typer.Option(False, "--csv", help="also write deviations.csv (x,y,z,deviation in mm)"),
        table_z: str = typer.Option(
            "lowest",
            help="the table top's z in the nominal's frame: points less than 0.5 mm above it are the table "
            "and left out, as cell inspect does; 'lowest' (the nominal's lowest point), a z in mm, or 'none'",
        ),
        crop_mm: float = typer.Option(
            5.0, help="points farther than this from the nominal are background and left out (0: keep them)"
        ),
        pdf: bool = typer.Option(False, "--pdf", help="also print report.pdf (headless Chromium)"),
    ) -> None:
        """Error map of CLOUD against NOMINAL: signed deviations (+ outside the material) and a report. Exits
        0 on pass, 4 on fail, 5 when incomplete (docs/exit-codes.md)."""
        typer.echo(f"comparing {cloud} with {nominal} -> {out}")
        from cell.analysis import kernels
        from cell.analysis.compare import run_compare
        from cell.exit_codes import ExitCode, for_verdict
        from cell.runs import require_empty_output

        require_empty_output(out)
        kernels.prefer_aot()  # the kernels compiled ahead of time when built (make venv): numba never starts
        if pdf:
            from cell.chromium import require_chromium

            require_chromium()
        doc = run_compare(
            nominal,
            cloud,
            out,
            align=align,
            tolerance=tolerance,
            datums=datums,
            regions=regions,
            density_per_mm2=density,
            radius_mm=radius,
            min_coverage=min_coverage,
            min_defect_points=min_defect_points,
            csv=csv,
            table_z=table_z,
            crop_mm=crop_mm,
        )
        if pdf:
            from cell.analysis.report import print_report_pdf

            print_report_pdf(out)
        typer.echo(
            f"{doc['verdict']}: {doc['n_points']} points, {doc['n_out_of_tolerance']} out of tolerance "
            f"-> {out}"
        )
        code = for_verdict(doc["verdict"])
        if code is not ExitCode.PASS:
            raise typer.Exit(int(code))
