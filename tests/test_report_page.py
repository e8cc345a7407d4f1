"""report.html as a reader sees it: user strings escaped, the run's identity and inputs present, the verdict
with its reason, defects numbered on the maps and in the table, numbers formatted for people, and a 3D view
that keeps the file small (docs/report.md)."""

from __future__ import annotations

import base64
import json
import re
from pathlib import Path

import numpy as np
import pytest

import cell
from cell.analysis.colour_scale import BandedScale
from cell.analysis.regions import Tolerance
from cell.analysis.report import ReportInput, render, summarise, write_report
from cell.analysis.report_html import css_string, verdict_reasons
from cell.analysis.view3d import (
    COORD_STEP_MM,
    DEVIATION_STEP_MM,
    figure,
    figure_json,
    pack_arrays,
    unpack_arrays,
)
from tests.synthetic_report import BUMP_AT, DENT_AT, synthetic_input

XSS = "<script>alert(1)</script>"
CALIBRATION = {
    "required": True,
    "cell_config_sha256": "ef" * 32,
    "files": [
        {
            "field": "hand_eye",
            "file": f"{XSS}.yaml",
            "kind": "hand_eye",
            "created_utc": "2026-11-23T06:00:00+00:00",
            "age_days": 3.25,
            "age_from": "created_utc",
            "made_for_this_config": True,
            "quality": {},
            "problems": [],
        }
    ],
    "incomplete_reasons": [],
}


@pytest.fixture(scope="module")
def hostile(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, str]:
    """A failing report whose part, region, recipe, operator, cloud and calibration file are all named
    ``<script>alert(1)</script>``."""
    inp = synthetic_input(name=XSS, region_name=XSS, n_points=12_000)
    run = inp.metadata["run"]
    run["identity"]["operator"] = XSS
    run["recipe"]["file"] = f"/recipes/{XSS}.yaml"
    inp.metadata["cloud"] = XSS
    inp.calibration = CALIBRATION
    inp.warnings.append(XSS)
    out = tmp_path_factory.mktemp("hostile")
    doc = write_report(out, inp)
    return doc, (out / "report.html").read_text(encoding="utf-8")


def typed(array: dict) -> np.ndarray:
    """A plotly base64 typed array ({dtype, bdata}) as numpy."""
    return np.frombuffer(base64.b64decode(array["bdata"]), dtype=np.dtype(array["dtype"]).newbyteorder("<"))


def visible_text(page: str) -> str:
    """The page's text as a reader sees it: no scripts, styles, tags or embedded images."""
    page = re.sub(r"<(script|style)[^>]*>.*?</\1>", " ", page, flags=re.S)
    return re.sub(r"<[^>]+>", " ", page)


def test_every_user_string_is_escaped(hostile: tuple[dict, str]) -> None:
    _, page = hostile
    assert XSS not in page
    assert page.count("<script") == 4  # the 3D figure (JSON), its packed arrays, plotly.js and its loader
    shown = visible_text(page).count("&lt;script&gt;alert(1)&lt;/script&gt;")
    assert shown >= 6  # part (title, heading), operator, region, recipe, cloud, calibration file, warning
    assert "\\3c script\\3e alert(1)\\3c /script\\3e " in page  # the printed footer's CSS string
    assert css_string('a"b\\c</style>') == '"a\\22 b\\5c c\\3c /style\\3e "'


def test_the_run_is_identified(hostile: tuple[dict, str]) -> None:
    doc, page = hostile
    text = visible_text(page)
    for shown in (
        "SN-0042",  # serial
        "PO-7",  # order
        "2026-11-26 10:15:00 UTC",  # inspected
        f"sha256 {'ab' * 6}",  # the recipe's hash
        "sim-binned",  # cell
        f"config {'ef' * 6}",  # the cell config's fingerprint
        f"inspection-cell {cell.__version__}",  # software
        "3.2 days",  # the calibration file's age
        "2026-11-23 06:00:00 UTC",  # and when it was made
        "box.stl",  # nominal
    ):
        assert shown in text, shown
    assert doc["software"]["version"] == cell.__version__ and doc["created_utc"][:2] == "20"
    assert doc["metadata"]["run"]["identity"]["serial"] == "SN-0042"


def test_the_verdict_says_why(hostile: tuple[dict, str]) -> None:
    doc, page = hostile
    assert page.index("FAIL") < page.index("Serial")  # the verdict first
    reasons = verdict_reasons(doc)
    worst = doc["regions"][0]
    assert worst["kind"] == "dent" and np.linalg.norm(np.subtract(worst["extreme_at_mm"], DENT_AT)) < 3
    assert worst["limit_mm"] == -0.3 and worst["beyond_mm"] == pytest.approx(worst["extreme_mm"] + 0.3)
    assert (
        f"\u2212{abs(worst['extreme_mm']):.3f} mm" in reasons[0]
        and "beyond the limit \u22120.300" in reasons[0]
    )
    assert any("fails" in r for r in reasons)  # the top-face region fails too
    # a pass and an incomplete give their reasons
    plate = np.c_[np.random.default_rng(0).uniform(-20, 20, (400, 2)), np.zeros(400)]
    passing = ReportInput(plate, np.full(400, 0.01), Tolerance(-0.3, 0.3), 400)
    assert verdict_reasons(summarise(passing))[0].startswith("All 400 points lie within \u22120.300 / +0.300")
    passing.incomplete_reasons = ["the hand-eye calibration is stale"]
    doc = summarise(passing)
    assert doc["verdict"] == "incomplete" and verdict_reasons(doc)[0] == "the hand-eye calibration is stale"
    assert "INCOMPLETE" in render(doc, passing, pictures=False)


def test_defects_are_numbered_on_the_maps_and_in_the_table(hostile: tuple[dict, str]) -> None:
    doc, page = hostile
    regions = doc["regions"]
    assert len(regions) >= 2 and {r["kind"] for r in regions} == {"dent", "excess"}
    bump = next(r for r in regions if r["kind"] == "excess")
    assert np.linalg.norm(np.subtract(bump["extreme_at_mm"], BUMP_AT)) < 3
    rows = re.findall(r'<td class="num"><span class="flag">(\d+)</span></td><td>([^<]+)</td>', page)
    assert [int(n) for n, _ in rows] == list(range(1, len(regions) + 1))
    assert [k.split()[0] for _, k in rows] == [r["kind"] for r in regions]
    fig = json.loads(re.search(r'<script id="fig3d" type="application/json">(.*?)</script>', page, re.S)[1])
    flags = next(t for t in fig["data"] if t["name"] == "out-of-tolerance regions")
    assert flags["text"] == [str(i + 1) for i in range(len(regions))]
    callouts = fig["layout"]["scene"]["annotations"]  # the numbered flags over the 3D view
    assert [c["text"] for c in callouts] == [f"<b>{i + 1}</b>" for i in range(len(regions))]
    at = np.array([[c["x"], c["y"], c["z"]] for c in callouts])
    assert np.allclose(at, [r["extreme_at_mm"] for r in regions])
    assert len(re.findall(r'src="data:image/png;base64,', page)) == 4  # the views, flags drawn in


def test_numbers_are_formatted_for_people(hostile: tuple[dict, str]) -> None:
    _, page = hostile
    text = visible_text(page)
    assert not re.search(r"\d\.\d{5,}", text)  # no 16-digit floats
    assert '"metadata"' not in page and "{" not in text  # no JSON dump
    assert re.search(r"\d\u202f\d{3}", text)  # thousands separated by a thin space
    assert "\u22120.300" in text and "-0.300" not in text  # a true minus sign


def test_the_3d_view_is_decimated_and_keeps_every_defect_point() -> None:
    rng = np.random.default_rng(3)
    pts = np.c_[rng.uniform(0, 200, (150_000, 2)), np.zeros(150_000)]
    dev = rng.normal(0, 0.02, len(pts))
    bad = np.zeros(len(pts), bool)
    bad[rng.choice(len(pts), 700, replace=False)] = True
    dev[bad] = -0.5
    fig = figure(pts, dev, BandedScale(-0.3, 0.3), bad, max_points=20_000)
    shown = fig["data"][0]
    assert shown["x"]["dtype"] == "f4"  # plotly's base64 typed arrays, float32
    x, colour = typed(shown["x"]), typed(shown["marker"]["color"])
    assert len(x) == 20_000 and int((colour == np.float32(-0.5)).sum()) == 700


def test_the_3d_figure_is_the_one_plotly_makes_of_it() -> None:
    """The figure is written without plotly's graph_objects (their validators cost 0.2-0.4 s of CPU per
    report): plotly must accept it as it is (an unknown property or a bad value raises) and its own figure
    of it, encoded by plotly, must be the same JSON."""
    import plotly.graph_objects as go
    from plotly.io.json import to_json_plotly

    rng = np.random.default_rng(5)
    pts = rng.uniform(0, 100, (3000, 3))
    dev = rng.normal(0, 0.2, len(pts))
    labels = [("1", pts[0], "1: dent -0.512 mm, 40 points"), ("2", pts[1], f"2: {XSS}")]
    fig = figure(pts, dev, BandedScale(-0.3, 0.3), np.abs(dev) > 0.3, unmeasured_mm=pts[:50], labels=labels)
    plotlys = to_json_plotly(go.Figure(fig).to_plotly_json())
    assert json.loads(figure_json(fig)) == json.loads(plotlys)
    assert "</" not in figure_json(fig) and "<script" not in figure_json(fig)


def test_the_report_stays_small(tmp_path: Path) -> None:
    """300k points: the page holds plotly.js (compressed), 60k points of 3D view and four PNG views."""
    rng = np.random.default_rng(4)
    n = 300_000
    pts = np.c_[rng.uniform(0, 300, (n, 2)), np.zeros(n)]
    inp = ReportInput(pts, rng.normal(0, 0.02, n), Tolerance(-0.3, 0.3), n)
    write_report(tmp_path, inp)
    size = (tmp_path / "report.html").stat().st_size
    assert 2.0e6 < size < 4.5e6, size


def test_the_3d_views_arrays_are_packed_small_and_come_back_within_half_a_step() -> None:
    """The page embeds the figure's point arrays as int32 steps (pack_arrays): each value comes back
    within half a step (1 um coordinates, 0.1 um deviations), at less than half the size of plotly's
    base64 float32, and everything else in the figure is untouched."""
    rng = np.random.default_rng(8)
    pts = np.c_[rng.uniform(-250, 250, (60_000, 2)), rng.uniform(0, 120, 60_000)]
    pts = pts[np.lexsort(pts.T[::-1])]  # a merged cloud comes in voxel order
    dev = rng.normal(0, 0.05, len(pts))
    fig = figure(pts, dev, BandedScale(-0.3, 0.3), np.abs(dev) > 0.3, unmeasured_mm=pts[:500])
    layout, blob = pack_arrays(fig)
    plain = sum(len(v["bdata"]) for t in fig["data"] for v in (t["x"], t["y"], t["z"]))
    plain += len(fig["data"][0]["marker"]["color"]["bdata"])
    assert len(blob) < 0.5 * plain
    back = unpack_arrays(layout, blob)
    for mine, theirs in zip(back["data"], fig["data"], strict=True):
        for axis in "xyz":
            assert mine[axis].dtype == np.float32
            assert np.abs(mine[axis] - typed(theirs[axis]).astype(np.float64)).max() <= COORD_STEP_MM * 0.51
        assert {k: v for k, v in mine.items() if k not in ("x", "y", "z", "marker")} == {
            k: v for k, v in theirs.items() if k not in ("x", "y", "z", "marker")
        }
    colour, truth = back["data"][0]["marker"]["color"], typed(fig["data"][0]["marker"]["color"])
    assert np.abs(colour - truth.astype(np.float64)).max() <= DEVIATION_STEP_MM * 0.51
    assert back["data"][1]["marker"]["color"] == fig["data"][1]["marker"]["color"]  # a CSS colour stays
    assert layout["layout"] == fig["layout"]
