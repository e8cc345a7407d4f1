"""The VDI/VDE 2634 procedures as a controller job, run like an inspection or a calibration routine (state
machine, pause and resume, checkpoint after every view, journal, run folder): every view is a sensor pose with
an artefact placed by the artefact stage; the figures come from the saved view points once all are measured.

Part 2 (one view): the sensor stays at the single-view pose and the stage puts the sphere, the ball bar and
the plane at the guideline's positions; points stay in the camera frame {C}, so the figures do not depend on
the robot or the hand-eye. Part 3 (multi-view): the long ball bar in each direction, four sensor poses per
position; the points go to the world with the cell's believed flange pose and the active hand-eye, as an
inspection merges its views, so SD contains the robot's and the hand-eye's errors.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from cell.analysis.linkfilter import unreliable_pixels
from cell.calibration import active_hand_eye, active_sensor_config, active_triangulator, calibration_source
from cell.calibration.active import active_measuring_patterns
from cell.calibration.procedures import CalibrationJob, _view, flange_for_camera
from cell.config import CellConfig
from cell.devices import DeviceBundle, build_artefact_stage
from cell.errors import ConfigError
from cell.geometry import invert, look_at, make_pose, transform_points
from cell.run_data import View
from cell.runs import RunFolder
from cell.sensing.decode import decode
from cell.sensing.patterns import PatternSet
from cell.verification.certificate import Certificate
from cell.verification.figures import FitError
from cell.verification.multiview import BAR_DIRECTIONS_DEG, bar_pose, view_targets
from cell.verification.positions import Position, Volume
from cell.verification.procedure import (
    AcceptanceResult,
    PositionResult,
    acceptance_positions,
    evaluate_ball_bar,
    evaluate_plane,
    evaluate_sphere,
    single_view_pose,
)
from cell.verification.report import write_html, write_json


class VerificationJob(CalibrationJob):
    """``part`` 2: the single-view acceptance test at ``positions`` (default: every Part 2 position; the
    interim check passes two). ``part`` 3: the long ball bar in ``directions`` (default: along x, along y,
    diagonal), each across four views. ``note`` heads the report (after what kind of cell measured);
    ``interim``: the start-of-shift check (the report says so)."""

    kind, file_stem, result_file = "verification", "verification", "verification.json"
    view_key = 1000  # begin_view's keys apart from the inspection's
    part_name = "verification"
    rerun_finished = False  # a finished test is a record: a new one goes into a new folder

    def __init__(
        self,
        cfg: CellConfig,
        certificate: Certificate,
        *,
        part: int = 2,
        positions: list[Position] | None = None,
        directions: dict[str, float] | None = None,
        note: str = "",
        interim: bool = False,
        **kw: Any,
    ) -> None:
        super().__init__(cfg, **kw)
        if part not in (2, 3):
            raise ConfigError(f"--part {part}: give 2 (single view) or 3 (multi-view)", field="--part")
        if part == 3 and certificate.ball_bar_long is None:
            raise ConfigError("the certificate has no ball_bar_long (Part 3 needs a bar of about 300 mm)")
        self.certificate, self.part, self.note, self.interim = certificate, part, note, interim
        self.positions = positions if positions is not None else acceptance_positions(cfg, certificate)
        self.directions = directions if directions is not None else BAR_DIRECTIONS_DEG
        self.T_W_B, self.T_T_C = cfg.robot.T_W_B.matrix(), active_hand_eye(cfg)
        self.projector_C = active_sensor_config(cfg).projector.T_C_P.matrix()[:3, 3]
        self.triangulator = active_triangulator(cfg)  # once: a per-pixel model is read from its files
        self._stage: Any = None
        self._placed: tuple[Any, ...] | None = None  # what the stage holds now (artefact, label, pose)

    # ------------------------------------------------------------------ the views
    def plan(self) -> list[View]:
        standoff = self.cfg.sensor.standoff_mm
        if self.part == 3:
            bar = self.certificate.ball_bar_long
            assert bar is not None  # checked in __init__
            out: list[View] = []
            for label, deg in self.directions.items():
                T_W_A = bar_pose(deg)
                for target in view_targets(T_W_A, bar.centre_distance_mm):
                    T_W_C = look_at(target + (0.0, 0.0, standoff), target, up=(0.0, 1.0, 0.0))
                    name = f"long ball bar, {label}"
                    out.append(self._artefact_view(T_W_C, "ball_bar_long", T_W_A, name, len(out)))
            return out
        T_W_C = single_view_pose(self.cfg)
        T_W_V = T_W_C @ make_pose(np.eye(3), (0.0, 0.0, standoff))  # the volume's centre, camera axes
        return [
            self._artefact_view(T_W_C, p.artefact, T_W_V @ p.T_V_A, p.label, k)
            for k, p in enumerate(self.positions)
        ]

    def _artefact_view(self, T_W_C: Any, artefact: str, T_W_A: Any, label: str, index: int) -> View:
        view = _view(flange_for_camera(self.cfg, T_W_C), index=index)
        view.data.update(artefact=artefact, T_W_A=np.asarray(T_W_A).tolist(), label=label, part=self.part)
        return view

    def patterns(self, view: View) -> PatternSet:
        return active_measuring_patterns(self.cfg)  # through the gamma LUT, if any

    def capture(self, devices: DeviceBundle, view: View, index: int, views: Sequence[View]) -> dict[str, Any]:
        """Place the view's artefact (the technician's hand on a real cell) when it differs from the one
        placed for the previous view (the views of one Part 3 position share one placement: placing the bar
        again between them would measure two placements), then grab the stack."""
        held = view.data.get("part", self.part)
        if held != self.part:
            raise ConfigError(
                f"this run folder holds a Part {held} test; run it again with --part {held}", field="--part"
            )
        if self._stage is None:
            self._stage = build_artefact_stage(devices, self.certificate)
        artefact, label, T_W_A = view.data["artefact"], view.data["label"], view.data["T_W_A"]
        placement = (artefact, label, tuple(np.ravel(T_W_A)))
        if placement != self._placed:  # a resumed run places its first view's artefact again
            self._stage.place(artefact, np.asarray(T_W_A, dtype=np.float64), label)
            self._placed = placement
        # Part 2's views share one pose: the robot holds it (and its landing) while the artefact is placed
        return {**super().capture(devices, view, index, views), "simulated": devices.simulated}

    def decode_view(self, view: View, captured: dict[str, Any], out_dir: Path) -> dict[str, Any]:
        """The points the sensor delivers in an inspection too (valid, off the rims, lit within
        ``sensor.max_projector_incidence_deg``), in {C}, and where the cell believes the camera was."""
        cam = self.cfg.sensor.camera
        decoded = decode(captured["images"], self.patterns(view), cam.bit_depth)
        cloud = self.triangulator.triangulate(decoded)
        p, valid = cloud.points_C, cloud.valid
        max_deg = self.cfg.sensor.max_projector_incidence_deg
        rim, oblique = unreliable_pixels(p, valid, self.projector_C, max_deg)
        points_C = p[valid & ~rim & ~oblique]
        T_W_C = self.T_W_B @ np.asarray(captured["T_B_T"]) @ self.T_T_C
        with open(out_dir / "data.npz", "wb") as f:
            np.savez(f, points_C=points_C, T_W_C=T_W_C)
        return {
            "simulated": bool(captured["simulated"]),
            "points": int(len(points_C)),
            "rim_filtered": int((valid & rim).sum()),
            "oblique_filtered": int((valid & ~rim & oblique).sum()),
        }

    # ------------------------------------------------------------------ the figures
    def fit(self, run: RunFolder, views: list[View]) -> tuple[dict[str, Any], Path]:
        if views and views[0].data.get("part", self.part) != self.part:
            raise ConfigError(
                f"this run folder holds a Part {views[0].data['part']} test; run it again with "
                f"--part {views[0].data['part']}",
                field="--part",
            )
        planned: dict[str, list[int]] = {}
        for i, v in enumerate(views):
            planned.setdefault(v.data["label"], []).append(i)
        done = set(run.completed_views())
        summaries = self.view_summaries(run)
        result = self._empty_result(bool(summaries) and all(s.get("simulated") for _, s in summaries))
        for label, indices in planned.items():
            v0 = views[indices[0]]
            missing = [i for i in indices if i not in done]
            if missing:  # a view the robot could not reach (skipped and logged): the position is not measured
                result.positions.append(
                    PositionResult(
                        label, v0.data["artefact"], error=f"view(s) {missing} not measured (see journal)"
                    )
                )
                continue
            T_W_A = np.asarray(v0.data["T_W_A"])
            data = [np.load(run.view_dir(i) / "data.npz") for i in indices]
            try:
                if self.part == 3:
                    points_W = np.vstack([transform_points(d["T_W_C"], d["points_C"]) for d in data])
                    bar = self.certificate.ball_bar_long
                    assert bar is not None  # checked in __init__
                    r = evaluate_ball_bar(points_W, T_W_A, bar)
                else:
                    (d,) = data
                    T_C_A = invert(d["T_W_C"]) @ T_W_A
                    if v0.data["artefact"] == "plane":
                        r = evaluate_plane(d["points_C"], T_C_A, self.certificate.plane)
                    elif v0.data["artefact"] == "sphere":
                        r = evaluate_sphere(d["points_C"], T_C_A, self.certificate.sphere)
                    else:
                        r = evaluate_ball_bar(d["points_C"], T_C_A, self.certificate.ball_bar)
            except FitError as exc:
                r = PositionResult(label, v0.data["artefact"], error=f"too few points on the artefact: {exc}")
            r.label, r.artefact = label, v0.data["artefact"]
            result.positions.append(r)
        result.summarise()
        return result.to_dict(), run.path / self.result_file

    def _empty_result(self, simulated: bool) -> AcceptanceResult:
        vol, v = Volume.of(self.cfg.sensor), self.cfg.verification
        mpe = {"PF": v.mpe_pf_mm, "PS": v.mpe_ps_mm, "SD": v.mpe_sd_mm, "F": v.mpe_f_mm}
        extra: dict[str, Any] = {}
        if self.part == 3:
            mpe["SD"] = v.mpe_sd_multiview_mm
            extra = {
                "kind": "VDI/VDE 2634 Part 3, multi-view (robot-moved sensor)",
                "required": ("PF", "PS", "SD"),
            }
        return AcceptanceResult(
            cell=self.cfg.name,
            geometry_source=calibration_source(self.cfg),
            volume_mm={
                "width": vol.width_mm,
                "height": vol.height_mm,
                "depth": vol.depth_mm,
                "L0": vol.diagonal_mm,
            },
            mpe_mm=mpe,
            positions=[],
            simulated=simulated,
            interim=self.interim,
            **extra,
        )

    def report(self, run: RunFolder, registration: dict[str, Any]) -> dict[str, Any]:
        """verification.json and report.html in the run folder (from the fit saved in results/fit.json, so a
        run resumed after its fit writes the same report)."""
        if self._stage is not None:
            self._stage.clear()
        result = AcceptanceResult.from_dict(self.fitted(run)["summary"])
        where = (
            f"Simulated cell '{self.cfg.name}': its world: section says how the simulated world differs from "
            "the config; where it is 'ideal' these figures are a noise floor."
            if result.simulated
            else f"Cell '{self.cfg.name}'."
        )
        note = f"{self.note} {where}".strip()
        write_json(run.path / self.result_file, result, self.certificate, note)
        write_html(run.path / "report.html", result, self.certificate, note)
        return {"kind": self.kind, "verdict": result.verdict}


# ---------------------------------------------------------------------------------------------- running it
def load_cell_and_certificate(
    cell: Path | None, certificate: Path | None
) -> tuple[Path, CellConfig, Path, Certificate]:
    """(cell config path, cell config, certificate path, certificate): ``cell`` defaults to the simulated
    cell, ``certificate`` to the cell's ``verification.certificate`` (relative to the cell file), else the
    repository's."""
    from cell.config import DEFAULT_CELL, load_cell_config
    from cell.verification.certificate import DEFAULT_CERTIFICATE, load_certificate

    cfg_path = cell or DEFAULT_CELL
    cfg = load_cell_config(cfg_path)
    cert_path = certificate or cfg.verification.certificate or DEFAULT_CERTIFICATE
    if certificate is None and cfg.verification.certificate is not None and not Path(cert_path).is_absolute():
        cert_path = Path(cfg_path).resolve().parent / cert_path
    return cfg_path, cfg, Path(cert_path), load_certificate(cert_path)


def run_verification(
    job: VerificationJob,
    out: Path,
    cfg_path: Path,
    cert_path: Path,
    on_progress: Callable[[Any], None] | None = None,
) -> AcceptanceResult:
    """Run ``job`` into the run folder ``out`` under the controller (an unfinished one is resumed), the
    certificate copied into its inputs; the result."""
    from cell.calibration.routines import run_routine

    doc = run_routine(
        job, Path(out), cfg_path, on_progress=on_progress, inputs={"certificate.yaml": Path(cert_path)}
    )
    return AcceptanceResult.from_dict(doc)


def acceptance_test(
    cell: Path | None,
    certificate: Path | None,
    out: Path,
    part: int = 2,
    on_progress: Callable[[Any], None] | None = None,
) -> AcceptanceResult:
    """``cell verify acceptance``: the Part 2 or Part 3 acceptance test of ``cell`` into ``out``."""
    cfg_path, cfg, cert_path, cert = load_cell_and_certificate(cell, certificate)
    return run_verification(VerificationJob(cfg, cert, part=part), out, cfg_path, cert_path, on_progress)


def interim_check(
    cell: Path | None,
    certificate: Path | None,
    runs: Path,
    on_progress: Callable[[Any], None] | None = None,
) -> tuple[AcceptanceResult, Path, list[str]]:
    """``cell verify check``: one ball-bar and one plane position into a new folder under ``runs``, added to
    the verification history (the cell's results database); returns (the result, its folder, the warnings:
    not recorded, drift of this cell's checks). A paused check is not resumed: RoutinePaused says to start
    a new one."""
    from cell.errors import RoutinePaused
    from cell.results import ResultsError
    from cell.verification.history import VerificationHistory, drift_warnings, local_entries
    from cell.verification.procedure import check_positions

    cfg_path, cfg, cert_path, cert = load_cell_and_certificate(cell, certificate)
    note = "Interim check (one ball-bar and one plane position)."
    job = VerificationJob(cfg, cert, positions=check_positions(cfg, cert), note=note, interim=True)
    folder = Path(runs) / RunFolder.new_name("verify-check")
    try:
        result = run_verification(job, folder, cfg_path, cert_path, on_progress)
    except RoutinePaused as exc:  # a check is short: start a new one rather than resume an old one
        raise RoutinePaused(
            f"interim check paused ({exc}); run `cell verify check` again for a new check"
        ) from exc
    history = VerificationHistory(runs, cfg)
    try:
        history.add(folder, "check", result)
        entries, unrecorded = history.entries(cfg.name), []
    except ResultsError as exc:  # the folder keeps the figures; `cell history --sync` records them later
        history.store.mark_pending(folder, str(exc))
        entries = local_entries(runs, cfg.name)
        unrecorded = [f"not recorded in the results database yet, drift judged from {runs} alone: {exc}"]
    checks = [e for e in entries if e.kind == "check"]
    warnings = drift_warnings(checks, result.mpe_mm, warn_fraction=cfg.verification.warn_fraction)
    return result, folder, [*unrecorded, *warnings]
