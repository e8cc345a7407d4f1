"""The kinds of YAML file a person gives the cell, known by their top-level keys.

Each kind names its schema (``module:Class``), the top-level keys that schema requires and those it allows;
tests/test_safety_config.py checks every entry against its schema, so the table cannot drift. It is data
only (no schema imports) so that :func:`cell.config.validate` can tell a glass rig config from a cell config
without importing the glass package.
"""

from __future__ import annotations

from collections.abc import Set
from dataclasses import dataclass


@dataclass(frozen=True)
class FileKind:
    """One kind of file: ``required`` top-level keys, ``allowed`` ones (None: any more), and ``use``: where
    such a file belongs, said to a person who gave it somewhere else."""

    name: str
    schema: str | None
    required: frozenset[str]
    allowed: frozenset[str] | None
    use: str


def _kind(name: str, schema: str | None, required: str, allowed: str | None, use: str) -> FileKind:
    req = frozenset(required.split())
    return FileKind(name, schema, req, None if allowed is None else req | frozenset(allowed.split()), use)


FILE_KINDS: tuple[FileKind, ...] = (
    _kind(
        "cell config",
        "cell.config:CellConfig",
        "name robot sensor",
        "description sim world calibration verification results_db retention",
        "give it with --cell (recipes/cells/ holds the shipped ones)",
    ),
    _kind(
        "recipe",
        "cell.config:Recipe",
        "part tolerance",
        "name min_coverage exclude_from_coverage plan alignment requires_calibration regions decision_rule "
        "guard_band",
        "give it as the RECIPE of `cell inspect` or `cell plan` (docs/recipes.md)",
    ),
    _kind(
        "glass recipe",
        "cell.glass.config:GlassRecipe",
        "rig part tolerance",
        "name calibration_dir search",
        "run it with `cell glass` (docs/glass.md)",
    ),
    _kind(
        "glass rig config",
        "cell.glass.config:GlassRigConfig",
        "name cameras screen board",
        "description driver options glass ambient_e_per_ms seed noise",
        "a glass recipe names it under 'rig:'; run the recipe with `cell glass` (docs/glass.md)",
    ),
    _kind(
        "artefact certificate",
        "cell.verification.certificate:Certificate",
        "sphere ball_bar plane",
        "ball_bar_long material",
        "give it to `cell verify ... --certificate` or name it in the cell config's verification.certificate",
    ),
    _kind(
        "gauge certificate",
        "cell.calibration.validation:GaugeCertificate",
        "name serial mesh top_z_mm slots",
        "laboratory date",
        "give it to `cell calibrate validate --gauge`",
    ),
    _kind(
        "region file",
        "cell.analysis.region_file:RegionFile",
        "regions",
        "",
        "give it to `cell compare --regions`, or copy its entries under a recipe's 'regions:'",
    ),
    _kind(
        "capture manifest",
        "cell.calibration.capture_folder:CaptureManifest",
        "camera projector code",
        "version order images board poses",
        "it describes a capture folder: give the folder with --from (docs/capture-folders.md)",
    ),
    _kind(
        "projector profile",
        "drivers.projector_profile:ProjectorProfile",
        "name format prompt terminator error_reply commands sources power_states powered_states",
        "encoding error_codes serial timing warming_states",
        "a serial projector's sensor.projector.options.profile names it",
    ),
    _kind(
        "calibration file",
        None,  # written by cell/calibration/store.py, read by load_calibration (no pydantic schema)
        "format_version kind arrays",
        None,
        "`cell calibrate` wrote it; a cell config names it under calibration:",
    ),
)


def kind_of_schema(schema: str) -> FileKind | None:
    """The kind whose schema is ``schema`` (``module:Class``), if it is a file kind."""
    return next((k for k in FILE_KINDS if k.schema == schema), None)


def explained_keys(kind: FileKind, keys: Set[str]) -> int:
    """How many of ``keys`` ``kind`` allows at the top level."""
    return len(keys) if kind.allowed is None else len(keys & kind.allowed)


def identify(keys: Set[str]) -> FileKind | None:
    """The kind whose required keys ``keys`` all hold and that allows most of them (ties: the kind that
    requires more); None when no kind's required keys are all there."""
    found = [k for k in FILE_KINDS if k.required <= keys]
    return max(found, key=lambda k: (explained_keys(k, keys), len(k.required)), default=None)
