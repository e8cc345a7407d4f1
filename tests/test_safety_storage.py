"""A full disk or a read-only folder: one clear error naming the path, never a traceback, never a half-made or
corrupted run. Run folders, calibration folders and the output of compare, on a real tmpfs: a
read-only one (EROFS) and a tiny one that fills up (ENOSPC, and numpy's errno-less short writes); and the
controller's pause on a full disk in process, with the disk simulated at numpy's writer
(np.savez_compressed raising OSError(ENOSPC)) so that it is tested where no tmpfs can be mounted."""

from __future__ import annotations

import errno
import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from cell.runs import RunFolder
from tests.box_part import IN_REACH_MM, small_cell, write_box_recipe
from tests.tmpfs import run_script

REPO = Path(__file__).resolve().parent.parent
PY = f'PYTHONPATH={REPO} "{sys.executable}" -m cell'


@pytest.fixture()
def inputs(tmp_path: Path) -> Path:
    """A 100 x 80 x 5 mm plate that one view measures (a run of seconds), its recipe, the small simulated cell
    as a file, and a cloud of the plate's top."""
    folder = tmp_path / "in"
    folder.mkdir()
    plate = trimesh.creation.box(extents=(100.0, 80.0, 5.0))
    plate.apply_translation((0.0, 0.0, 2.5))
    plate.export(folder / "plate.stl")
    recipe = {
        "name": "plate",
        "part": {"cad": "plate.stl", "T_W_P": {"xyz_mm": list(IN_REACH_MM)}},
        "tolerance": {"lower": -0.3, "upper": 0.3},
        "min_coverage": 0.5,  # the top: the 5 mm sides are left to no view (min_patch_area_mm2)
        "plan": {
            "resolution_mm": 1.5,
            "point_density_per_mm2": 0.2,
            "max_iterations": 0,
            "min_patch_area_mm2": 1000,
        },
    }
    (folder / "plate.yaml").write_text(yaml.safe_dump(recipe))
    (folder / "cell.yaml").write_text(yaml.safe_dump(small_cell().model_dump(mode="json")))
    xy = np.random.default_rng(0).uniform((-50, -40), (50, 40), (500, 2))
    np.savetxt(folder / "cloud.xyz", np.c_[xy, np.full(len(xy), 5.0)])
    return folder


def _outcome(out: Path, name: str) -> tuple[int, str]:
    return int((out / f"{name}.rc").read_text()), (out / f"{name}.err").read_text() + (
        out / f"{name}.out"
    ).read_text()


RUN = 'run() { n=$1; shift; eval "$PY $*" >"$OUT/$n.out" 2>"$OUT/$n.err"; echo $? >"$OUT/$n.rc"; }\n'


def test_a_read_only_folder_is_refused_before_anything_is_written(inputs: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    script = (
        f"OUT={out}; PY='{PY}'\n{RUN}"
        'mount -t tmpfs -o size=1m tmpfs "$M" && mount -o remount,ro "$M" || exit 99\n'
        'run inspect inspect plate.yaml --cell cell.yaml --out "$M/run"\n'
        'run calibrate calibrate intrinsics --cell cell.yaml --out "$M/cal"\n'
        'run compare compare plate.stl cloud.xyz --out "$M/cmp"\n'
        'ls -A "$M" > "$OUT/left"\n'
    )
    proc = run_script(script, tmp_path / "mnt", inputs)
    assert proc.returncode == 0, proc.stderr
    # plan and scan refuse their --out as compare does (cell.runs.require_empty_output); a verification folder
    # is made as a calibration folder is (cell.calibration.routines)
    for name, target in (("inspect", "run"), ("calibrate", "cal"), ("compare", "cmp")):
        code, text = _outcome(out, name)
        assert code == 2, (name, text)
        assert "Traceback" not in text, text
        error = [line for line in text.splitlines() if line.startswith("error:")]
        assert len(error) == 1, text
        assert f"{tmp_path / 'mnt' / target}" in error[0] and "read-only file system" in error[0], text
    assert (out / "left").read_text() == ""  # nothing was made


def test_a_disk_full_before_the_run_starts_leaves_nothing(inputs: Path, tmp_path: Path) -> None:
    """Room for the write probe but not for the inputs: refused naming the run folder, nothing left."""
    out = tmp_path / "out"
    out.mkdir()
    script = (
        f"OUT={out}; PY='{PY}'\n{RUN}"
        'mount -t tmpfs -o size=8k tmpfs "$M" || exit 99\n'
        'run inspect inspect plate.yaml --cell cell.yaml --out "$M/run"\n'
        'ls -A "$M" > "$OUT/left"\n'
    )
    proc = run_script(script, tmp_path / "mnt", inputs)
    assert proc.returncode == 0, proc.stderr
    code, text = _outcome(out, "inspect")
    assert code == 2 and "Traceback" not in text, text
    assert "".join(f"cannot write {tmp_path / 'mnt' / 'run'}: the disk is full".split()) in "".join(
        text.split()
    )
    # no run folder and no partial one; the runs root's results database (opened to read the verification
    # history before the run folder is made) is not part of a run
    assert (out / "left").read_text().split() in ([], ["results.sqlite"])


def test_a_disk_filling_up_mid_run_pauses_and_the_run_resumes_once_there_is_room(
    inputs: Path, tmp_path: Path
) -> None:
    """A 128 kB tmpfs takes the inputs but not the view (about 470 kB): the run pauses naming the view and
    saying to free space; on the same disk made larger, `cell resume` finishes it (a full disk is not a lost
    run)."""
    out = tmp_path / "out"
    out.mkdir()
    script = (
        f"OUT={out}; PY='{PY}'\n{RUN}"
        'mount -t tmpfs -o size=128k tmpfs "$M" || exit 99\n'
        'run inspect inspect plate.yaml --cell cell.yaml --out "$M/run"\n'
        'cp -a "$M/run" "$OUT/paused"\n'
        'mount -o remount,size=64m "$M"\n'
        'run resume resume "$M/run"\n'
        'cp -a "$M/run" "$OUT/done"\n'
    )
    proc = run_script(script, tmp_path / "mnt", inputs)
    assert proc.returncode == 0, proc.stderr
    code, text = _outcome(out, "inspect")
    flat = "".join(text.split())  # the console wraps long lines
    assert code == 3 and "Traceback" not in text, text
    assert "".join(f"paused: cannot write {tmp_path / 'mnt' / 'run'}: the disk is full".split()) in flat, text
    assert f"{tmp_path / 'mnt' / 'run' / 'views' / '000'}" in flat and "freespaceonit" in flat
    paused = RunFolder.open(out / "paused")
    assert paused.completed_views() == [] and not any((out / "paused" / "views").iterdir())  # no half view
    errors = [e for e in paused.journal() if e["event"] == "error"]
    assert errors[0]["kind"] == "StorageError"  # then the pending decodes of the same full disk
    code, text = _outcome(out, "resume")
    assert code == 0, text
    report = json.loads((out / "done" / "results" / "report.json").read_text())
    assert report["verdict"] == "pass"


def test_the_controller_pauses_on_a_full_disk_keeping_every_whole_view(tmp_path: Path, monkeypatch) -> None:
    """In process, with numpy's writer raising ENOSPC from the third view on: the run pauses with the view
    named, the two views written stay whole and journalled, no half view is left, and the journal says why
    (resuming once there is room: the tmpfs test above)."""
    from tests.test_controller import make_controller

    recipe = write_box_recipe(tmp_path)
    run_dir = tmp_path / "run"
    real_save = np.savez_compressed  # the view files' writer (cell.view_files, defects.npz)
    views: set[str] = set()

    def full_disk_save(file, *args, **kwargs):
        name = getattr(file, "name", file)  # an open file or a path
        views.add(Path(name).parent.name)
        if len(views) > 2:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(name))
        return real_save(file, *args, **kwargs)

    monkeypatch.setattr(np, "savez_compressed", full_disk_save)
    ctl, _ = make_controller(recipe, run_dir, pipelining=False)
    assert ctl.execute() == "paused", ctl.message
    assert ctl.message.startswith(f"cannot write {run_dir}: the disk is full")
    assert f"{run_dir / 'views' / '002'}" in ctl.message
    run = RunFolder.open(run_dir)
    assert run.completed_views() == [0, 1]
    assert sorted(p.name for p in (run_dir / "views").iterdir()) == ["000", "001"]
    assert {e["view"] for e in run.journal() if e["event"] == "view"} == {0, 1}
    assert [e["kind"] for e in run.journal() if e["event"] == "error"][0] == "StorageError"
