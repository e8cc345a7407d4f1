"""`cell compare` on clouds from elsewhere: the table and the background are cropped as the inspection crops
its views (counted, not judged), a cloud in another frame is refused, and a tolerance in metres is refused.

The cloud is a box's visible surface with a known dent, standing on a table, with a clamp beside it: which
point is which is known from how the cloud was made."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from cell.analysis.compare import parse_tolerance, run_compare
from cell.errors import ConfigError
from cell.geometry import pose_from_xyz_rpy, transform_points

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> dict:
    """A 100 x 60 x 40 box standing on the table (z = 0): its top and sides sampled (0.8 mm dent on top),
    a ring of table around it, and a clamp 30 mm beside it."""
    folder = tmp_path_factory.mktemp("compare")
    box = trimesh.creation.box(extents=(100.0, 60.0, 40.0))
    box.apply_translation((0.0, 0.0, 20.0))
    box.export(folder / "box.stl")
    rng = np.random.default_rng(5)
    pts, face = trimesh.sample.sample_surface(box, 60000, seed=5)
    up = box.face_normals[face][:, 2] > -0.5  # the bottom face stands on the table: no sensor sees it
    part = np.asarray(pts)[up]
    r = np.hypot(part[:, 0] - 20.0, part[:, 1])
    dent = (part[:, 2] > 39.999) & (r < 5.0)
    part[dent, 2] -= 0.8 * (1 - r[dent] / 5.0)
    part += rng.normal(0, 0.01, part.shape)
    xy = rng.uniform((-120, -90), (120, 90), (20000, 2))
    table_xy = xy[(np.abs(xy[:, 0]) > 52) | (np.abs(xy[:, 1]) > 32)]
    table = np.c_[table_xy, rng.normal(0.0, 0.05, len(table_xy))]
    clamp = rng.uniform((80, -10, 5), (95, 10, 30), (800, 3))
    cloud = np.vstack([part, table, clamp])
    np.savetxt(folder / "cloud.xyz", cloud)
    return {
        "folder": folder,
        "nominal": folder / "box.stl",
        "cloud": cloud,
        "n_part": len(part),
        "n_table": len(table),
        "n_part_low": int((part[:, 2] < 0.5).sum()),  # the sides' lowest half millimetre: cropped as table
        "n_clamp": len(clamp),
        "dent_deep": int((part[dent, 2] < 40.0 - 0.3).sum()),
    }


def test_table_and_background_are_cropped_counted_and_not_judged(scene, tmp_path: Path) -> None:
    doc = run_compare(scene["nominal"], scene["folder"] / "cloud.xyz", tmp_path / "o", pictures=False)
    assert doc["excluded"]["table_points"] == scene["n_table"] + scene["n_part_low"]
    assert doc["excluded"]["background_points"] == scene["n_clamp"]
    assert doc["n_points"] == scene["n_part"] - scene["n_part_low"]
    assert doc["verdict"] == "fail"  # the dent, and only the dent
    assert doc["n_out_of_tolerance"] == pytest.approx(scene["dent_deep"], abs=3)
    assert all(abs(r["centre_mm"][0] - 20) < 3 for r in doc["regions"])
    # without the crop, the clamp alone fails the part (the table lies within the band of the box's
    # bottom face, which is why a box and not a floating part is the honest case for the table crop)
    whole = run_compare(
        scene["nominal"],
        scene["folder"] / "cloud.xyz",
        tmp_path / "w",
        pictures=False,
        table_z="none",
        crop_mm=0,
    )
    assert whole["n_points"] == len(scene["cloud"])
    assert whole["n_out_of_tolerance"] >= scene["n_clamp"] + scene["dent_deep"] - 3


def test_table_z_is_the_part_frame_s_table(scene, tmp_path: Path) -> None:
    """A cloud lifted with its part onto a 10 mm plate (nominal lifted too): 'lowest' follows the nominal."""
    lifted = scene["folder"] / "lifted.stl"
    trimesh.load(scene["nominal"]).apply_translation((0, 0, 10)).export(lifted)
    cloud = tmp_path / "lifted.xyz"
    np.savetxt(cloud, scene["cloud"] + (0, 0, 10))
    doc = run_compare(lifted, cloud, tmp_path / "o", pictures=False)
    assert doc["excluded"]["table_points"] == scene["n_table"] + scene["n_part_low"]
    fixed = run_compare(lifted, cloud, tmp_path / "f", pictures=False, table_z=10.0)
    assert fixed["excluded"] == doc["excluded"]
    with pytest.raises(ConfigError, match="--table-z"):
        run_compare(lifted, cloud, tmp_path / "x", pictures=False, table_z="floor")


@pytest.mark.parametrize(
    ("xyz", "rpy", "says"),
    [
        ((0, 0, 400), (180, 0, 0), "does not overlap the nominal"),  # the camera's frame, 400 mm away
        ((0, 0, 20), (0, 0, 0), "does not overlap the nominal"),  # 20 mm too high
        ((0, 0, 0), (0, 0, 90), "does not overlap the nominal"),  # turned a quarter about z
        ((0, 0, 0), (180, 0, 0), "upside down"),  # everything below the table
    ],
)
def test_a_cloud_in_another_frame_is_refused(scene, tmp_path: Path, xyz, rpy, says: str) -> None:
    moved = tmp_path / "moved.xyz"
    np.savetxt(moved, transform_points(pose_from_xyz_rpy(xyz, np.deg2rad(rpy)), scene["cloud"][::5]))
    with pytest.raises(ConfigError, match=says) as info:
        run_compare(scene["nominal"], moved, tmp_path / "o", pictures=False)
    assert str(moved) in str(info.value)
    assert not (tmp_path / "o").exists()  # refused before anything is written
    with pytest.raises(ConfigError, match=says):  # best fit starts from where the cloud is: refused too
        run_compare(scene["nominal"], moved, tmp_path / "b", pictures=False, align="bestfit")


def test_best_fit_aligns_on_the_part_not_on_the_table(scene, tmp_path: Path) -> None:
    """A cloud 1.5 mm off in x and y: ICP on the cropped part brings it back; the table would hold it."""
    off = tmp_path / "off.xyz"
    np.savetxt(off, scene["cloud"][::3] + (1.5, -1.5, 0.0))
    doc = run_compare(scene["nominal"], off, tmp_path / "o", pictures=False, align="bestfit")
    T = np.asarray(doc["metadata"]["T_P_cloud"])
    assert np.allclose(T[:2, 3], (-1.5, 1.5), atol=0.05)


@pytest.mark.parametrize("text", ["-0.0003,0.0003", "-0.3,0.0002", "-60,0.3"])
def test_a_tolerance_in_metres_or_beyond_belief_is_refused(text: str) -> None:
    with pytest.raises(ConfigError, match="field '--tolerance'"):
        parse_tolerance(text)
    assert parse_tolerance("0,0.2") == (0.0, 0.2)  # one-sided: no removal allowed


def test_cli_refuses_a_tolerance_in_metres_with_exit_code_2(scene, tmp_path: Path) -> None:
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "cell",
            "compare",
            str(scene["nominal"]),
            str(scene["folder"] / "cloud.xyz"),
            "--out",
            str(tmp_path / "o"),
            "--tolerance=-0.0003,0.0003",
        ],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=120,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "--tolerance" in lines[0] and "in metres?" in lines[0], proc.stderr
    assert not (tmp_path / "o").exists()
