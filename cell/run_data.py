"""What a run carries between the controller and its job, typed: views, evaluations and the checkpoint.

The checkpoint (``checkpoint.json`` in the run folder) is what a killed run resumes from; its JSON layout is
the one runs have always written, so older run folders load and resume. Each type reads and writes its own
JSON (``to_json`` / ``from_json``): the controller journals and saves only these.
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass, field
from enum import StrEnum
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.errors import ConfigError

_VIEW_KEYS = ("T_W_C", "T_B_T", "patch", "source", "iteration")
# a part serial or an order number: what a barcode carries and a folder name can hold on every file system
_CODE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+#-]{0,63}")
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")


@dataclass(frozen=True)
class RunIdentity:
    """Who and what a run inspects: the part's serial, the operator, the production order. All optional (a
    development run has none); recorded in the run's inputs, the report and the results database."""

    serial: str | None = None
    operator: str | None = None
    order: str | None = None

    def __post_init__(self) -> None:
        for name in ("serial", "order"):
            value = getattr(self, name)
            if value is not None and not _CODE.fullmatch(value):
                raise ConfigError(
                    f"{value!r} is not a valid {name}: 1-64 letters, digits and . _ + # -, starting with a "
                    "letter or digit (a barcode reader may have added a prefix or a tab: scan it again)",
                    field=f"--{name}",
                )
        if self.operator is not None and (
            not self.operator.strip() or len(self.operator) > 64 or _CONTROL.search(self.operator)
        ):
            raise ConfigError(
                f"{self.operator!r} is not a valid operator name: 1-64 printable characters",
                field="--operator",
            )

    def to_json(self) -> dict[str, str | None]:
        return asdict(self)

    @classmethod
    def from_json(cls, doc: dict[str, Any] | None) -> RunIdentity:
        doc = doc or {}
        return cls(doc.get("serial"), doc.get("operator"), doc.get("order"))


class Phase(StrEnum):
    """Where a run stands, as the checkpoint records it: a resumed run continues from here."""

    NEW = "new"
    SCANNING = "scanning"
    EVALUATING = "evaluating"
    REPLANNING = "replanning"
    REGISTERING = "registering"
    REPORTING = "reporting"
    RENDERING = "rendering"  # the verdict is published; the rest of the report (its page) is being written
    DONE = "done"


@dataclass
class View:
    """A planned view: the robot target, where it puts the camera and why, and what else the job needs there
    (``data``: a calibration board and its pose, an artefact, ...; saved beside the named fields)."""

    T_B_T: NDArray[np.float64]  # the flange target in the robot base frame (mm): where the controller moves
    T_W_C: NDArray[np.float64] | None = None  # the camera pose the planner chose, in the world (mm)
    patch: str | None = None  # the surface patch the view was planned for
    source: str | None = None  # the planner step that proposed it (f0, g_kS, g_kR, g_kA)
    iteration: int | None = None  # the feedback iteration that added it (0: the initial plan)
    data: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        named = {
            "T_W_C": None if self.T_W_C is None else self.T_W_C.tolist(),
            "T_B_T": self.T_B_T.tolist(),
            "patch": self.patch,
            "source": self.source,
            "iteration": self.iteration,
        }
        return {**{k: v for k, v in named.items() if v is not None}, **self.data}

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> View:
        T_W_C = doc.get("T_W_C")
        return cls(
            T_B_T=np.asarray(doc["T_B_T"], dtype=np.float64),
            T_W_C=None if T_W_C is None else np.asarray(T_W_C, dtype=np.float64),
            patch=doc.get("patch"),
            source=doc.get("source"),
            iteration=doc.get("iteration"),
            data={k: v for k, v in doc.items() if k not in _VIEW_KEYS},
        )


@dataclass
class Evaluation:
    """A job's judgement of the views measured so far: qualified (enough) or not, at which cost.

    ``state`` is the job's in-memory result behind the figures (arrays the JSON drops), so that a replan right
    after the evaluation reuses it instead of computing it again; it is not saved, so after a resume it is
    None and the job computes it anew."""

    qualified: bool
    q: float | None  # the cost Q (eq 3.22) when the job has one
    iteration: int
    figures: dict[str, Any] = field(default_factory=dict)  # the job's further key figures, for the report
    state: Any = field(default=None, repr=False, compare=False)

    def to_json(self) -> dict[str, Any]:
        return {"qualified": self.qualified, "Q": self.q, "iteration": self.iteration, **self.figures}

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> Evaluation:
        figures = {k: v for k, v in doc.items() if k not in ("qualified", "Q", "iteration")}
        return cls(bool(doc.get("qualified")), doc.get("Q"), int(doc.get("iteration", 0)), figures)


@dataclass
class Checkpoint:
    """The run's durable state: the phase, the planned views, the feedback iteration and what the finished
    steps returned (``registration`` and ``summary`` are the job's JSON documents)."""

    phase: Phase = Phase.NEW
    views: list[View] = field(default_factory=list)
    iteration: int = 0
    skipped: list[int] = field(default_factory=list)  # views no collision-free path reached
    evaluation: Evaluation | None = None
    registration: dict[str, Any] | None = None
    summary: dict[str, Any] | None = None

    def to_json(self) -> dict[str, Any]:
        doc: dict[str, Any] = {
            "phase": self.phase.value,
            "views": [v.to_json() for v in self.views],
            "iteration": self.iteration,
        }
        if self.skipped:
            doc["skipped"] = self.skipped
        if self.evaluation is not None:
            doc["evaluation"] = self.evaluation.to_json()
        if self.registration is not None:
            doc["registration"] = self.registration
        if self.summary is not None:
            doc["summary"] = self.summary
        return doc

    @classmethod
    def from_json(cls, doc: dict[str, Any] | None) -> Checkpoint:
        """The checkpoint a run folder holds (``RunFolder.load_checkpoint``); a new one for None."""
        if doc is None:
            return cls()
        evaluation = doc.get("evaluation")
        return cls(
            phase=Phase(doc.get("phase", Phase.NEW)),
            views=[View.from_json(v) for v in doc.get("views", [])],
            iteration=int(doc.get("iteration", 0)),
            skipped=[int(i) for i in doc.get("skipped", [])],
            evaluation=None if evaluation is None else Evaluation.from_json(evaluation),
            registration=doc.get("registration"),
            summary=doc.get("summary"),
        )
