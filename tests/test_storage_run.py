"""A real (small) inspection run's storage: the raw images it keeps decode again to the very points it stored,
a passed run under the default retention drops them when it finishes, and a pruned run's report rebuilds."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from cell.inspection import Captured, LambertianInspection
from cell.inspection_run import inspect, load_run_inputs, rebuild_report
from cell.mesh import load_mesh
from cell.retention import RetentionConfig, prune
from cell.run_data import Checkpoint
from cell.view_files import load_eval_points, load_raw_stack, load_view_points
from tests.box_part import small_cell, write_box_recipe, write_dented_box_recipe


def _cell_file(folder: Path, retention: dict | None) -> Path:
    data = small_cell().model_dump(mode="json")
    if retention is not None:
        data["retention"] = retention
    path = folder / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture(scope="module")
def kept_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A box run (passes) whose cell keeps passed runs' raw images a week."""
    folder = tmp_path_factory.mktemp("storage")
    recipe = write_box_recipe(folder)
    cell = _cell_file(folder, {"raw_images_passed_days": 7})
    outcome = inspect(recipe, cell, folder / "run", say=lambda _: None)
    assert outcome.state == "done" and outcome.summary["verdict"] == "pass"
    assert not list((folder / "run").glob("views/*/planes.npz"))  # the resume's cache, dropped when done
    # the last view's raw images are written after the verdict, with the report's page
    journal = [e for e in outcome.run.journal() if e["event"] in ("verdict", "report_written")]
    assert [e["event"] for e in journal] == ["verdict", "report_written"]
    raw = outcome.run.view_dir(outcome.run.completed_views()[-1]) / "raw"
    assert journal[1]["raw_images_bytes"] == sum(f.stat().st_size for f in raw.rglob("*") if f.is_file())
    # a feedback round followed the first plan: its last view's raw images, kept back by its decode, were
    # written beside the next view's decode (cell.inspection, _write_raw_later), and decode again below too
    iterations = [v.iteration for v in Checkpoint.from_json(outcome.run.load_checkpoint()).views]
    assert iterations[0] == 0 and 1 in iterations, iterations
    return folder / "run"


@pytest.mark.parametrize("in_order", [False, True], ids=["side_by_side", "in_order"])
def test_the_raw_images_decode_again_to_the_stored_points(
    kept_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, in_order: bool
) -> None:
    """Lossless, and enough: each view's raw stack, decoded again by the job with the run's own inputs,
    gives exactly the points, flags, u and evaluation subset the run stored; also when the decode runs its
    steps one after the other, as a camera of more than SIDE_BY_SIDE_MAX_PIXELS does."""
    import cell.inspection
    from cell.runs import RunFolder

    if in_order:
        monkeypatch.setattr(cell.inspection, "SIDE_BY_SIDE_MAX_PIXELS", 0)

    run = RunFolder.open(kept_run)
    recipe, cfg, _ = load_run_inputs(run)
    nominal_W = load_mesh(recipe.part.cad).apply_transform(recipe.part.T_W_P.matrix())
    job = LambertianInspection(recipe, cfg, nominal_W)
    views = Checkpoint.from_json(run.load_checkpoint()).views
    done = run.completed_views()
    assert len(done) >= 3
    for i in done:
        stack = load_raw_stack(run.view_dir(i))
        assert stack is not None and stack.shape == (len(job.patterns), 120, 160)
        meta = json.loads((run.view_dir(i) / "view.json").read_text())
        captured = Captured(list(stack), np.asarray(meta["T_B_T"]), np.asarray(meta["joints_rad"]), "camera")
        again = tmp_path / f"{i:03d}"
        again.mkdir()
        assert job.decode(views[i], captured, again)["points"] == meta["points"]
        a, b = load_view_points(run.view_dir(i)), load_view_points(again)
        assert np.array_equal(a.points_W, b.points_W) and np.array_equal(a.quality, b.quality)
        assert np.array_equal(a.oblique, b.oblique)
        assert (a.uncertainty is None) == (b.uncertainty is None)
        assert a.uncertainty is None or np.array_equal(a.uncertainty, b.uncertainty)
        assert np.array_equal(load_eval_points(run.view_dir(i)), load_eval_points(again))


def test_a_pruned_run_keeps_its_report_and_rebuilds_it(kept_run: Path) -> None:
    before = json.loads((kept_run / "results" / "report.json").read_text())
    drop = RetentionConfig(raw_images_passed_days=0)
    assert prune(kept_run.parent, drop, dry_run=True).to_free_bytes > 0
    assert prune(kept_run.parent).freed_bytes == 0  # its own policy: a week, and it is young
    assert list(kept_run.glob("views/*/raw"))
    report = prune(kept_run.parent, drop)
    assert report.freed_bytes > 0 and not list(kept_run.glob("views/*/raw"))
    assert json.loads((kept_run / "results" / "report.json").read_text()) == before
    outcome = rebuild_report(kept_run)
    rebuilt = json.loads((kept_run / "results" / "report.json").read_text())
    assert outcome.summary["verdict"] == before["verdict"] == rebuilt["verdict"]
    assert rebuilt["n_points"] == before["n_points"]
    assert rebuilt["deviation"] == before["deviation"]  # from the same stored cloud


def test_a_passed_run_under_the_default_retention_drops_its_raw_images_at_the_end(tmp_path: Path) -> None:
    recipe = write_box_recipe(tmp_path)
    data = yaml.safe_load(recipe.read_text())
    data["plan"] |= {"view_budget": 2, "max_iterations": 0}  # a short run: two views do
    data["min_coverage"] = 0.2
    recipe.write_text(yaml.safe_dump(data))
    said: list[str] = []
    outcome = inspect(recipe, _cell_file(tmp_path, None), tmp_path / "run", say=said.append)
    assert outcome.summary["verdict"] == "pass"
    assert not list((tmp_path / "run").glob("views/*/raw")) and (tmp_path / "run" / "views" / "000").is_dir()
    prunes = [e for e in outcome.run.journal() if e["event"] == "prune"]
    assert len(prunes) == 1 and prunes[0]["freed_bytes"] > 0
    # the last view's, kept back by its decode, were not written at all: the verdict keeps none
    written = [e for e in outcome.run.journal() if e["event"] == "report_written"]
    assert len(written) == 1 and "raw_images_bytes" not in written[0]
    assert any("raw view images removed" in s for s in said)
    assert not (tmp_path / "run" / "run.lock").exists()  # released by the run, not by the prune


def test_a_failed_run_rebuilt_from_its_cloud_gives_the_same_report(tmp_path: Path) -> None:
    """The run judges its cloud in the registration, with the cloud in memory; `cell report` judges
    results/cloud.ply again (cell.inspection_results): the same report.json but for when and by what it was
    written, on a run with points outside the tolerance, whose link radius and defect regions a passing run
    never computes."""
    recipe = write_dented_box_recipe(tmp_path)
    outcome = inspect(recipe, _cell_file(tmp_path, None), tmp_path / "run", say=lambda _: None)
    assert outcome.state == "done" and outcome.summary["verdict"] == "fail"
    path = tmp_path / "run" / "results" / "report.json"
    before = json.loads(path.read_text())
    assert before["regions"], "the dent is a defect region"
    rebuild_report(tmp_path / "run")
    after = json.loads(path.read_text())
    for doc in (before, after):  # when and by what it was written
        for key in ("created_utc", "software"):
            doc.pop(key, None)
    assert after == before
