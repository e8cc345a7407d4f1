"""The technician's calibration routines as controller jobs over the device contracts.

Each routine is a :class:`cell.controller.Job`: ``plan`` lists the views (robot flange pose ``T_B_T`` and,
where a target must be placed, the target and its requested pose ``T_W_Bd`` for the :class:`BoardStage`);
``capture`` places the target and grabs the pattern stack through the camera and projector contracts;
``decode`` detects or
decodes one view into its view folder; ``register`` fits the calibration from the view folders and saves it;
``report`` writes ``calibration.json``. The controller gives them what an inspection has: state machine,
journal, checkpoints, pause and resume (a killed routine continues from the last view).

Nothing here knows whether the cell is simulated: a routine sees targets only through camera images and the
robot only through its reported pose. Routines run on simulated cells (a simulated motorised stage), on real
cells (a stage or the operator placing targets), with the same code.

Frames: {W} world, {B} robot base, {T} flange, {C} camera, {P} projector, {Bd} the target (see
:class:`cell.contracts.CalibrationBoard`). mm and rad.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from cell.calibration.active import active_hand_eye, believed_flange
from cell.calibration.intrinsics import CharucoView, detect_charuco
from cell.config import CellConfig, config_fingerprint
from cell.contracts import BoardKind, CalibrationBoard, CameraSettings, PixelFormat, TriggerMode
from cell.devices import DeviceBundle
from cell.errors import CalibrationError, DeviceFault
from cell.geometry import Pose, invert, look_at
from cell.run_data import Evaluation, View
from cell.runs import RunFolder, write_json_atomic
from cell.sensing.patterns import PatternSet, uniform_patterns
from cell.sensing.scan import capture_stack
from cell.sensing.stack import check_stack

REPO = Path(__file__).resolve().parents[2]
GAUGE_STL = REPO / "recipes" / "parts" / "gauge.stl"
GAUGE_CERTIFICATE = REPO / "recipes" / "parts" / "gauge.certificate.yaml"

CHARUCO = CalibrationBoard(
    "charuco 11x8 15 mm", BoardKind.CHARUCO, squares=(11, 8), square_mm=15.0, marker_mm=11.0
)
FLAT = CalibrationBoard("white reference board", BoardKind.FLAT)
GAUGE = CalibrationBoard("gauge", BoardKind.MESH, mesh_path=str(GAUGE_STL))


@dataclass(frozen=True)
class Station:
    """Where the board stage presents targets: ``xyz_W`` (world mm) of the stage centre on the table and the
    height of the flat board's reference plane above the table (mm)."""

    xyz_W: tuple[float, float, float] = (-130.0, 90.0, 0.0)
    board_top_mm: float = 100.0

    def point(self, height_mm: float = 0.0) -> NDArray[np.float64]:
        return np.asarray(self.xyz_W, dtype=np.float64) + (0.0, 0.0, height_mm)


def charuco(board: CalibrationBoard) -> cv2.aruco.CharucoBoard:
    """The OpenCV board of a ChArUco target (lengths in mm)."""
    return cv2.aruco.CharucoBoard(
        board.squares,
        board.square_mm,
        board.marker_mm,
        cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary)),
    )


def flange_for_camera(cfg: CellConfig, T_W_C: Pose) -> Pose:
    """``T_B_T`` that puts the camera at ``T_W_C`` by the active hand-eye (the mounting drawing if none)."""
    return invert(cfg.robot.T_W_B.matrix()) @ T_W_C @ invert(active_hand_eye(cfg))


def camera_over(
    cfg: CellConfig, target_W: NDArray, tilt_deg: float = 0.0, azimuth_deg: float = 0.0, roll_deg: float = 0.0
) -> Pose:
    """``T_W_C`` of a camera at the stand-off from ``target_W``, looking at it, its axis tilted ``tilt_deg``
    from vertical toward ``azimuth_deg`` and rolled ``roll_deg`` about the optical axis."""
    t, a = np.radians(tilt_deg), np.radians(azimuth_deg)
    eye = np.asarray(target_W) + cfg.sensor.standoff_mm * np.array(
        [np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)]
    )
    T = look_at(eye, target_W, up=(0.0, 1.0, 0.0))
    R = np.eye(4)
    R[:3, :3] = Rotation.from_rotvec([0.0, 0.0, np.radians(roll_deg)]).as_matrix()
    return T @ R


def charuco_poses(
    board: CalibrationBoard,
    distance_mm: float,
    n: int,
    rng: np.random.Generator,
    max_tilt_deg: float = 30.0,
    spread_mm: float = 25.0,
) -> list[Pose]:
    """``n`` poses ``T_C_Bd`` of a ChArUco board for intrinsics: centre near the optical axis at
    ``distance_mm``
    (+-10 %), shifted up to ``spread_mm`` sideways, tilted up to ``max_tilt_deg`` about a random in-plane axis
    and turned up to +-20 deg about its normal."""
    nx, ny = board.squares
    centre = np.array([nx * board.square_mm / 2, ny * board.square_mm / 2, 0.0])
    out = []
    for _ in range(n):
        axis = rng.uniform(0, 2 * np.pi)
        tilt = np.radians(rng.uniform(0.3, 1.0) * max_tilt_deg)
        R = (
            Rotation.from_rotvec(tilt * np.array([np.cos(axis), np.sin(axis), 0.0]))
            * Rotation.from_rotvec([0.0, 0.0, np.radians(rng.uniform(-20, 20))])
        ).as_matrix()
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = (
            np.array([*rng.uniform(-spread_mm, spread_mm, 2), distance_mm * rng.uniform(0.9, 1.1)])
            - R @ centre
        )
        out.append(T)
    return out


def _pose_text(T: Any) -> str:
    T = np.asarray(T, dtype=np.float64)
    tilt = np.degrees(np.arccos(np.clip(abs(T[2, 2]), -1.0, 1.0)))
    return f"world ({T[0, 3]:.0f}, {T[1, 3]:.0f}, {T[2, 3]:.0f}) mm, tilt {tilt:.0f} deg"


def arrived_for(views: Sequence[View], index: int) -> int:
    """The first of ``views`` up to ``index`` that the robot takes at view ``index``'s flange pose without
    moving in between: consecutive views of one ``T_B_T`` are taken where the robot stands (the controller's
    move to them is a joint move to the joints it holds, JointMotion), e.g. while the stage steps the board or
    places another artefact. From the views the controller runs (the stored ones on a resume), so that a
    resumed run names it as the uninterrupted one did."""
    first = index
    while first > 0 and np.array_equal(views[first - 1].T_B_T, views[index].T_B_T):
        first -= 1
    return first


class CalibrationJob:
    """What every routine shares: placing targets, grabbing stacks, a trivial evaluate/replan, the report.

    Subclasses set ``kind`` and ``file_stem``, build ``views`` in :meth:`plan`, and implement
    :meth:`decode_view` and :meth:`fit`."""

    kind = ""
    file_stem = ""
    view_key = 0  # view i's key for DeviceBundle.begin_view is view_key + i
    result_file = "calibration.json"  # what the routine leaves in its run folder
    rerun_finished = True  # a finished run folder is measured again (the previous views kept aside)
    part_name = "calibration"

    def __init__(
        self, cfg: CellConfig, *, force: bool = False, seed: int = 1, station: Station | None = None
    ):
        self.cfg = cfg
        self.force = force
        self.seed = seed
        self.station = station or Station()
        self.result: dict[str, Any] = {}
        self.made_for = config_fingerprint(cfg)  # recorded in every file the routine writes

    def plan(self) -> list[View]:
        """The routine's views (each subclass builds its own)."""
        raise NotImplementedError

    # ------------------------------------------------------------------ capture
    def patterns(self, view: View) -> PatternSet:
        """The projector frames of a view (the first frame of every set is full white)."""
        return uniform_patterns(self.cfg.sensor.projector, (255, 0))

    def capture(self, devices: DeviceBundle, view: View, index: int, views: Sequence[View]) -> dict[str, Any]:
        """Place the view's target, if any, and grab its stack. A simulated cell restarts its noise from the
        view's key, and the landing error of the pose the robot holds from the key of the view it came there
        for (:func:`arrived_for`): a resumed routine then draws what an uninterrupted one drew."""
        devices.begin_view(self.view_key + index, arrived=self.view_key + arrived_for(views, index))
        if "board" in view.data:
            if devices.stage is None:
                raise DeviceFault(
                    "stage", "this cell has no board stage; the routine needs one to place targets"
                )
            devices.stage.place(_board(view), np.asarray(view.data["T_W_Bd"], dtype=np.float64))
        cam = self.cfg.sensor.camera
        devices.camera.configure(
            CameraSettings(
                cam.exposure_ms,
                cam.gain_db,
                PixelFormat(f"Mono{cam.bit_depth}") if cam.bit_depth != 8 else PixelFormat.MONO8,
                TriggerMode.SOFTWARE,
            )
        )
        ps = self.patterns(view)
        images = capture_stack(devices.camera, devices.projector, ps)
        stack = check_stack(
            images, ps, (cam.width_px, cam.height_px), cam.bit_depth, source=f"camera '{devices.camera.name}'"
        )
        return {
            "images": stack,
            "T_B_T": believed_flange(self.cfg, devices.robot),
            "joints": devices.robot.joints(),
        }

    def decode(self, view: View, captured: dict[str, Any], out_dir: Path) -> dict[str, Any]:
        summary = self.decode_view(view, captured, out_dir)
        summary["T_B_T"] = np.asarray(captured["T_B_T"]).tolist()
        summary["joints"] = np.asarray(captured["joints"]).tolist()
        write_json_atomic(out_dir / "view.json", summary)
        return summary

    def decode_view(self, view: View, captured: dict[str, Any], out_dir: Path) -> dict[str, Any]:
        raise NotImplementedError

    # ------------------------------------------------------------------ no feedback loop
    def evaluate(self, run: RunFolder, views: list[View], iteration: int) -> Evaluation:
        return Evaluation(True, 1.0, iteration, {"views": len(run.completed_views())})

    def replan(self, run: RunFolder, views: list[View], evaluation: Evaluation) -> list[View]:
        return []

    # ------------------------------------------------------------------ results
    def view_summaries(self, run: RunFolder) -> list[tuple[int, dict[str, Any]]]:
        return [(i, json.loads((run.view_dir(i) / "view.json").read_text())) for i in run.completed_views()]

    def register(self, run: RunFolder, views: list[View]) -> dict[str, Any]:
        """Fit the calibration from the view folders and save it (never over a better one without force)."""
        figures, path = self.fit(run, views)
        self.result = {"kind": self.kind, "file": str(path), "summary": figures}
        write_json_atomic(run.results_dir / "fit.json", self.result)
        return {"n_points": int(figures.get("points", figures.get("corners", 1))), "file": str(path)}

    def fit(self, run: RunFolder, views: list[View]) -> tuple[dict[str, Any], Path]:
        raise NotImplementedError

    def fitted(self, run: RunFolder) -> dict[str, Any]:
        """The fit's result: kept from :meth:`register`, or read back from results/fit.json when the run
        resumed after it."""
        return self.result or json.loads((run.results_dir / "fit.json").read_text())

    def report(self, run: RunFolder, registration: dict[str, Any]) -> dict[str, Any]:
        result = self.fitted(run)
        write_json_atomic(run.path / self.result_file, result)
        return {"kind": self.kind, "file": result.get("file")}


def _board(view: View) -> CalibrationBoard:
    return {b.name: b for b in (CHARUCO, FLAT, GAUGE)}.get(view.data["board"]) or _mesh_board(view)


def _mesh_board(view: View) -> CalibrationBoard:
    """A target the view names by its mesh (the validation sphere, a gauge from its certificate)."""
    return CalibrationBoard(view.data["board"], BoardKind.MESH, mesh_path=view.data["mesh_path"])


def _view(
    T_B_T: Pose, board: CalibrationBoard | None = None, T_W_Bd: Pose | None = None, **extra: Any
) -> View:
    v = View(np.asarray(T_B_T, dtype=np.float64), data=dict(extra))
    if board is not None:
        v.data["board"] = board.name
        v.data["T_W_Bd"] = np.asarray(T_W_Bd).tolist()
    return v


class JointMotion:
    """Moves between calibration views: up to a safe height above the current flange position (a linear
    move), then a joint move to the IK solution of the target nearest the current joints (a calibration
    station has no part to plan around; linear moves between the views' tilted poses cross wrist
    singularities). The controller asks it through the same ``plan`` call as the inspection's
    MotionPlanner."""

    def __init__(self, kin: Any, lift_to_z_B_mm: float | None = None) -> None:
        self.kin = kin
        self.lift_to_z_B_mm = lift_to_z_B_mm

    def plan(
        self, T_B_T_now: Pose, q_now: NDArray[np.float64], target: Pose, home: NDArray[np.float64] | None
    ) -> tuple[list[Any], list[str]]:
        from cell.errors import PlanningError
        from cell.planning.motion import Move

        sols = self.kin.ik(target, q_now, allow_singular=False)
        if not sols.ok:
            raise PlanningError(f"calibration view unreachable: {sols.reason}")
        q = sols.joints[int(np.argmin(np.abs(sols.joints - np.asarray(q_now)).max(axis=1)))]
        moves = []
        if self.lift_to_z_B_mm is not None and T_B_T_now[2, 3] < self.lift_to_z_B_mm:
            up = np.array(T_B_T_now, dtype=np.float64)
            up[2, 3] = self.lift_to_z_B_mm
            moves.append(Move("linear", up))
        return [*moves, Move("joint", q)], []


# --------------------------------------------------------------------------------------------- view files
def board_not_found(view: View, index: int | str) -> CalibrationError:
    """The error of a view whose board the camera does not see, with where it was asked for."""
    return CalibrationError(
        f"view {index}: the board '{view.data['board']}' was not found in the camera image (requested at "
        f"{_pose_text(view.data['T_W_Bd'])}, robot flange at {_pose_text(view.T_B_T)}); check that the board "
        "is in view, lit and in focus"
    )


def detect_board(view: View, image: Any) -> CharucoView:
    """The ChArUco board of ``view`` in ``image``, or :func:`board_not_found`."""
    found = detect_charuco(image, charuco(CHARUCO))
    if found is None:
        raise board_not_found(view, view.data.get("index", "?"))
    return found


def save_view_arrays(out_dir: Path, **arrays: Any) -> None:
    """A routine's per-view arrays, as ``data.npz`` in the view folder."""
    with open(out_dir / "data.npz", "wb") as f:
        np.savez(f, **arrays)


def load_view_arrays(run: RunFolder, i: int) -> dict[str, Any]:
    """The arrays :func:`save_view_arrays` wrote for view ``i``."""
    with np.load(run.view_dir(i) / "data.npz") as d:
        return {k: d[k] for k in d.files}
