"""The report in a real browser (headless Chromium): the 3D view drawn with the banded colours, and the
printout at most three pages even with everything a report can hold. The screenshot is the one in
docs/report.md: ``CELL_DOCS_SCREENSHOTS=1`` writes it to docs/img/report.png."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy.spatial import cKDTree

from cell.analysis.regions import Region, Tolerance
from cell.analysis.report import ReportInput, print_report_pdf, write_report
from cell.analysis.view3d import READY
from cell.chromium import Browser
from tests.browser import require_chromium
from tests.synthetic_report import synthetic_input

DOCS_IMG = Path(__file__).resolve().parents[1] / "docs" / "img"
pytestmark = pytest.mark.chromium


def test_the_3d_view_draws_the_banded_map(tmp_path: Path) -> None:
    require_chromium()
    inp = synthetic_input(n_points=12_000)
    write_report(tmp_path, inp)
    shot = DOCS_IMG / "report.png" if os.environ.get("CELL_DOCS_SCREENSHOTS") else tmp_path / "report.png"
    with Browser() as browser:
        browser.open(tmp_path / "report.html", 1200, 1500)
        browser.wait_for(READY)
        assert browser.evaluate("document.getElementById('view3d').dataset.ready") == "1"  # plotly drew it
        assert browser.evaluate("document.querySelectorAll('#view3d canvas').length") > 0
        # the page's packed arrays, unpacked by the browser, are the cloud it was given (every point: fewer
        # than the view's 60 000), within half a step (1 um coordinates, 0.1 um deviations)
        drawn = np.array(
            browser.evaluate(
                "(() => { const t = document.getElementById('view3d').data[0]; "
                "return [t.x, t.y, t.z, t.marker.color].map((a) => Array.from(a)); })()"
            )
        )
        box = browser.evaluate(
            "(() => { const r = document.getElementById('view3d').getBoundingClientRect(); "
            "return [r.left, r.top, r.right, r.bottom].map(Math.round); })()"
        )
        badge = browser.evaluate(
            "(() => { const r = document.querySelector('.badge').getBoundingClientRect(); "
            "return [r.left, r.top, r.right, r.bottom].map(Math.round); })()"
        )
        browser.screenshot(shot)
    assert drawn.shape == (4, len(inp.points_mm))
    dist, at = cKDTree(inp.points_mm).query(drawn[:3].T)
    assert len(np.unique(at)) == len(at) and dist.max() < 0.9e-3  # each point once, within 0.5 um per axis
    assert np.abs(drawn[3] - inp.deviation_mm[at]).max() < 0.51e-4
    img = np.asarray(Image.open(shot).convert("RGB")).astype(int)
    view = img[box[1] : box[3], box[0] : box[2]]
    r, g, b = view[..., 0], view[..., 1], view[..., 2]
    assert ((b > 150) & (r < 90) & (g < 140)).sum() > 30  # the dent, saturated blue, drawn by WebGL
    assert ((r > 170) & (g < 90) & (b < 90)).sum() > 10  # the bump, saturated red
    assert ((abs(r - g) < 12) & (abs(g - b) < 12) & (r > 150) & (r < 235)).sum() > 2000  # grey: in tolerance
    top = img[badge[1] : badge[3], badge[0] : badge[2]]
    assert (np.abs(top - [0xC0, 0x17, 0x2B]).sum(-1) < 30).mean() > 0.5  # the FAIL badge


def crowded_input() -> ReportInput:
    """A plate with 30 dents (the report lists 20), six recipe regions, four calibration files with
    problems, an alignment on six datums, warnings and incomplete reasons: the most a report holds."""
    g = np.stack(np.meshgrid(np.arange(0, 300, 0.6), np.arange(0, 120, 0.6)), -1).reshape(-1, 2)
    pts = np.c_[g, np.zeros(len(g))]
    dev = np.random.default_rng(5).normal(0, 0.02, len(pts))
    for k in range(30):
        centre = [10 + 9.5 * k, 20 + 80 * (k % 2)]
        dev -= 0.6 * np.exp(-np.sum((g - centre) ** 2, axis=1) / 8.0)
    regions = [
        Region(
            f"pad {k} with a long descriptive name",
            box_mm=((50.0 * k, 0, -1), (50.0 * k + 40, 120, 1)),
            tolerance=Tolerance(-0.2, 0.2),
        )
        for k in range(6)
    ]
    problems = [
        "hand_eye: handeye.yaml is stale: it was made for another version of the cell config "
        "(robot, sensor or scene changed since); recalibrate"
    ]
    files = [
        {
            "field": f,
            "file": f"{f}.yaml",
            "kind": f,
            "created_utc": "2026-10-01T08:00:00+00:00",
            "age_days": 56.3,
            "age_from": "created_utc",
            "made_for_this_config": False,
            "quality": {},
            "problems": problems,
        }
        for f in ("intrinsics", "projector", "hand_eye", "kinematics")
    ]
    residuals = [
        {"name": f"D{k}", "before_mm": -0.25, "after_mm": 0.0, "spread_mm": 0.003, "n_points": 2900}
        for k in range(6)
    ]
    return ReportInput(
        pts,
        dev,
        Tolerance(-0.3, 0.3),
        len(pts),
        regions=regions,
        excluded={"table_points": 1_800_000, "background_points": 12, "isolated_out_of_tolerance_points": 40},
        warnings=["best-fit alignment hides global deviations", "the nominal mesh is not closed"],
        incomplete_reasons=[p for f in files for p in f["problems"]],
        alignment={
            "method": "datums",
            "correction": {"max_mm": 3.0, "translation_mm": 1.3, "rotation_deg": 0.46},
            "residuals": residuals,
            "rms_mm": 0.0,
            "uncertainty_mm": {"rms": 0.0002, "max": 0.0015},
            "warnings": ["datum C1 is measured on 514 points only"],
        },
        calibration={
            "required": True,
            "cell_config_sha256": "ab" * 32,
            "files": files,
            "incomplete_reasons": [],
        },
        metadata={"part": "a part with a rather long name, revision C", "cad": "part-rev-C.step"},
    )


def test_the_printout_is_at_most_three_pages(tmp_path: Path) -> None:
    require_chromium()
    from pypdf import PdfReader

    doc = write_report(tmp_path, crowded_input())
    assert len(doc["regions"]) == 20 and len(doc["region_verdicts"]) == 6
    pdf = print_report_pdf(tmp_path)
    pages = PdfReader(pdf).pages
    assert 2 <= len(pages) <= 3, len(pages)
    first = pages[0].extract_text()
    assert "INCOMPLETE" in first and "Deviation map" in first  # verdict and maps on page 1
    assert "Beyond tolerance" in pages[1].extract_text()
