"""The pipeline cannot see the simulated world (issue 12) nor a driver (issue 14): nothing under ``cell/``
imports ``fakes`` or ``drivers`` except ``cell/devices.py`` (the one module that builds devices from a config
and records them), and nothing under ``cell/`` touches the simulator's truth (``ground_truth``, the world,
the true camera or flange pose, the part's true placement). Parsed with ``ast``: docstrings and comments may
name them.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

CELL = Path(__file__).resolve().parent.parent / "cell"

# names that reach the simulator's truth: per-pixel truth, the world object and section, true poses
TRUTH_NAMES = {"ground_truth", "world", "camera_pose", "flange_pose", "true_flange", "T_place_W"}

# Modules allowed to import fakes or drivers / touch truth, and why. Only cell/devices.py (builds the devices)
# and cell/config.py (carries the opaque `world:` section to cell.devices.check_world) belong here for good.
IMPORT_ALLOWED = {"cell/devices.py"}
TRUTH_ALLOWED = {"cell/devices.py": {"world"}, "cell/config.py": {"world"}}

# Modules known to reach the world, to be fixed (each reported as an xfail until then). Empty: every module
# under cell/ is guarded. Add one only with the reason, and fix it before it stays.
KNOWN_OFFENDERS_IMPORT: set[str] = set()
KNOWN_OFFENDERS_TRUTH: dict[str, set[str]] = {}


def _modules() -> list[Path]:
    return sorted(CELL.rglob("*.py"))


def _rel(path: Path) -> str:
    return path.relative_to(CELL.parent).as_posix()


def _imports_of(tree: ast.AST, package: str) -> list[int]:
    """Lines that import ``package`` or one of its modules."""
    lines = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import) and any(a.name.split(".")[0] == package for a in node.names):
            lines.append(node.lineno)
        elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == package:
            lines.append(node.lineno)
    return lines


def _truth_uses(tree: ast.AST) -> dict[str, list[int]]:
    uses: dict[str, list[int]] = {}
    for node in ast.walk(tree):
        name = (
            node.attr if isinstance(node, ast.Attribute) else node.id if isinstance(node, ast.Name) else None
        )
        if name in TRUTH_NAMES:
            uses.setdefault(name, []).append(node.lineno)
    return uses


@pytest.mark.parametrize("path", _modules(), ids=_rel)
def test_cell_module_does_not_import_the_simulator(path: Path) -> None:
    rel = _rel(path)
    lines = _imports_of(ast.parse(path.read_text(), str(path)), "fakes")
    if rel in IMPORT_ALLOWED:
        return
    if rel in KNOWN_OFFENDERS_IMPORT:
        if not lines:
            pytest.fail(f"{rel} no longer imports fakes: remove it from KNOWN_OFFENDERS_IMPORT")
        pytest.xfail(f"known offender, to be fixed: {rel} imports fakes at lines {lines}")
    assert not lines, (
        f"{rel} imports fakes at lines {lines}: only cell/devices.py may build simulated devices"
    )


@pytest.mark.parametrize("path", _modules(), ids=_rel)
def test_cell_module_does_not_import_a_driver(path: Path) -> None:
    """Drivers (and their hardware libraries) are reached through the device registry only."""
    rel = _rel(path)
    lines = _imports_of(ast.parse(path.read_text(), str(path)), "drivers")
    assert rel in IMPORT_ALLOWED or not lines, (
        f"{rel} imports drivers at lines {lines}: only cell/devices.py may build or record devices"
    )


@pytest.mark.parametrize("path", _modules(), ids=_rel)
def test_cell_module_does_not_touch_the_world(path: Path) -> None:
    rel = _rel(path)
    uses = _truth_uses(ast.parse(path.read_text(), str(path)))
    for name in TRUTH_ALLOWED.get(rel, set()):
        uses.pop(name, None)
    known = KNOWN_OFFENDERS_TRUTH.get(rel, set())
    if known:
        if not set(uses) & known:
            pytest.fail(f"{rel} no longer uses {sorted(known)}: remove it from KNOWN_OFFENDERS_TRUTH")
        extra = {k: v for k, v in uses.items() if k not in known}
        assert not extra, f"{rel} reaches the simulator's truth: {extra}"
        pytest.xfail(f"known offender, to be fixed: {rel} uses {sorted(known)}")
    assert not uses, f"{rel} reaches the simulator's truth (name: lines): {uses}"


def test_the_checks_catch_an_offender() -> None:
    """The scanner itself: imports of fakes and drivers and a ground_truth call are found, a docstring is
    not."""
    tree = ast.parse(
        '"""uses ground_truth from fakes"""\nfrom fakes.sim import render\nx = r.ground_truth(T)\n'
        "def f():\n    import drivers.recording\n"
    )
    assert _imports_of(tree, "fakes") == [2]
    assert _imports_of(tree, "drivers") == [5]
    assert _truth_uses(tree) == {"ground_truth": [3]}
