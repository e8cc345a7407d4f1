"""What a plan tells the recipe author: the surfaces no planned viewpoint sees, and whether the predicted
coverage reaches the recipe's ``min_coverage``.

An unseen surface is a planner patch (faces within a cone of normals, eqs 3.1-3.2) with inspectable samples
that no viewpoint of the plan is predicted to measure, over at least ``min_patch_area_mm2``: the planner
tried viewpoints for it (rolls, then tilts up to 45 degrees, then the hole fill) and found none the robot
reaches or that sees it. Faces are indices into the CAD mesh as loaded (as for regions), listed when most of
their samples are unseen; positions and normals are in the part frame {P} (mm).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from cell.config import Recipe
from cell.geometry import Pose, invert, transform_points
from cell.planning.planner import Plan

AXES = {
    "+x": (1, 0, 0),
    "-x": (-1, 0, 0),
    "+y": (0, 1, 0),
    "-y": (0, -1, 0),
    "+z": (0, 0, 1),
    "-z": (0, 0, -1),
}


@dataclass(frozen=True)
class UnseenSurface:
    """A surface no planned viewpoint sees: its planner patch, unseen area (mm^2), mean outward normal and
    centre in the part frame, and the CAD faces most of whose samples are unseen."""

    patch: str
    area_mm2: float
    normal: tuple[float, float, float]
    centre_mm: tuple[float, float, float]
    faces: tuple[int, ...]

    def facing(self) -> str:
        """'+y' when the normal is within 10 degrees of an axis of the part frame, else the vector."""
        n = np.asarray(self.normal)
        for name, axis in AXES.items():
            if float(n @ np.asarray(axis, dtype=float)) > np.cos(np.deg2rad(10.0)):
                return name
        return "(" + ", ".join(f"{v:.2f}" for v in self.normal) + ")"

    def describe(self, max_ranges: int = 12) -> str:
        """One line: 'P3: 4739 mm^2 facing +y around (0, 45, 20) mm, faces 7, 9'."""
        centre = ", ".join(f"{v:.0f}" for v in self.centre_mm)
        return (
            f"{self.patch}: {self.area_mm2:.0f} mm^2 facing {self.facing()} around ({centre}) mm, "
            f"faces {face_ranges(self.faces, max_ranges)}"
        )

    def to_json(self) -> dict[str, Any]:
        return {
            "patch": self.patch,
            "area_mm2": round(self.area_mm2, 1),
            "facing": self.facing(),
            "normal": [round(v, 4) for v in self.normal],
            "centre_mm": [round(v, 2) for v in self.centre_mm],
            "faces": list(self.faces),
        }


def face_ranges(faces: tuple[int, ...] | list[int], max_ranges: int = 12) -> str:
    """'3, 7-9, 12' (consecutive faces as ranges), the first ``max_ranges`` ranges and a count of the rest."""
    runs: list[list[int]] = []
    for f in sorted(faces):
        if runs and f == runs[-1][1] + 1:
            runs[-1][1] = f
        else:
            runs.append([f, f])
    text = ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in runs[:max_ranges])
    rest = len(runs) - max_ranges
    return text + (f" and {rest} more range(s)" if rest > 0 else "")


def unseen_surfaces(plan: Plan, T_W_P: Pose, min_area_mm2: float | None = None) -> list[UnseenSurface]:
    """The surfaces ``plan`` leaves unseen (largest first), each over ``min_area_mm2`` (default the plan's
    ``min_patch_area_mm2``: the planner leaves smaller holes to the feedback loop too)."""
    s = plan.surface
    seen = plan.predicted.any(axis=0) if len(plan.predicted) else np.zeros(len(s.points), dtype=bool)
    unseen = s.inspectable & ~seen
    least = plan.sensor.settings.min_patch_area_mm2 if min_area_mm2 is None else min_area_mm2
    n_faces = len(s.mesh.faces)
    per_face_inspectable = np.bincount(s.face[s.inspectable], minlength=n_faces)
    per_face_unseen = np.bincount(s.face[unseen], minlength=n_faces)
    mostly_unseen = per_face_unseen * 2 >= np.maximum(per_face_inspectable, 1)
    patch = plan.face_patch[s.face] if len(plan.face_patch) else np.zeros(len(s.face), dtype=np.int64)
    T_P_W = invert(T_W_P)
    out = []
    for label in np.unique(patch[unseen]):
        idx = unseen & (patch == label)
        area = float(s.area[idx].sum())
        if area < least:
            continue
        normal = T_P_W[:3, :3] @ (s.normals[idx] * s.area[idx, None]).sum(axis=0)
        normal /= max(float(np.linalg.norm(normal)), 1e-12)
        centre = transform_points(T_P_W, s.points[idx].mean(axis=0, keepdims=True))[0]
        faces = np.unique(s.face[idx])
        out.append(
            UnseenSurface(
                f"P{int(label)}",
                area,
                (float(normal[0]), float(normal[1]), float(normal[2])),
                (float(centre[0]), float(centre[1]), float(centre[2])),
                tuple(int(f) for f in faces[mostly_unseen[faces]]),
            )
        )
    return sorted(out, key=lambda u: -u.area_mm2)


def coverage_warnings(plan: Plan, min_coverage: float, unseen: list[UnseenSurface]) -> list[str]:
    """Warnings for the recipe author: the predicted coverage below ``min_coverage`` (the verdict would be
    incomplete), with the unseen surfaces and what to do about them."""
    if plan.coverage >= min_coverage:
        return []
    text = (
        f"the plan predicts {100 * plan.coverage:.1f}% coverage of the inspectable surface, below the "
        f"recipe's min_coverage of {100 * min_coverage:.1f}%: the verdict would be 'incomplete'"
    )
    if unseen:
        faces = sorted({f for u in unseen for f in u.faces})
        listed = f"[{', '.join(map(str, faces))}]" if len(faces) <= 24 else "the faces of unseen_surfaces"
        text += (
            f"; no reachable viewpoint sees {'; '.join(u.describe(4) for u in unseen)}. Place the part where "
            "the robot reaches them (part.T_W_P), or leave them out of coverage if they need no measurement "
            f"(exclude_from_coverage: {listed})"
        )
    return [text]


@dataclass(frozen=True)
class PlanFeedback:
    """What ``cell plan`` and the report say about a recipe's plan: the unseen surfaces and the warnings."""

    predicted_coverage: float
    min_coverage: float
    unseen: list[UnseenSurface]
    warnings: list[str]

    def to_json(self) -> dict[str, Any]:
        return {
            "predicted_coverage": self.predicted_coverage,
            "min_coverage": self.min_coverage,
            "unseen_surfaces": [u.to_json() for u in self.unseen],
            "warnings": list(self.warnings),
        }


def plan_feedback(plan: Plan, recipe: Recipe) -> PlanFeedback:
    """The feedback on ``plan``, made for ``recipe`` (its placement and ``min_coverage``)."""
    unseen = unseen_surfaces(plan, recipe.part.T_W_P.matrix())
    return PlanFeedback(
        plan.coverage, recipe.min_coverage, unseen, coverage_warnings(plan, recipe.min_coverage, unseen)
    )
