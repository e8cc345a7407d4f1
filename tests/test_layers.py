"""The import layers of cell/, read from the source with ast: every import counts, at module level, inside a
function (a late import) or under TYPE_CHECKING, so no edge hides. The rules are the ones the code already
follows; a file that breaks one today is listed in KNOWN_OFFENDERS with the reason and the change that
removes it, and the list may only shrink. ``python tests/test_layers.py`` prints the package
graph."""

from __future__ import annotations

import ast
from collections import defaultdict
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
CELL = ROOT / "cell"

FOUNDATION = (
    "cell.defaults",
    "cell.errors",
    "cell.geometry",
    "cell.schema",
    "cell.contracts",
    "cell.runs",
    "cell.raycast",
    "cell.run_data",
    "cell.storage",
    "cell.chromium",
)
# the domain packages, lowest first: each imports only packages before it
DOMAIN = (
    "cell.sensing",
    "cell.analysis",
    "cell.planning",
    "cell.glass",
    "cell.calibration",
    "cell.verification",
)

# what the controller runs (cell.controller.Job) or runs its routines under it, and the run-level modules
# that build devices for one command (inspection_run, scan_run, calibration.latency)
JOBS = (
    "cell.inspection",
    "cell.inspection_run",
    "cell.scan_run",
    "cell.calibration.latency",
    "cell.calibration.procedures",
    "cell.calibration.routines",
    "cell.calibration.sensor_routines",
    "cell.calibration.handeye_routines",
    "cell.calibration.validation_routine",
    "cell.verification.job",
    "cell.glass.job",
)


@dataclass(frozen=True)
class Rule:
    """Modules under ``importers`` (but not under ``exempt``) import nothing under ``forbidden`` (but what is
    under ``allowed``)."""

    name: str
    importers: tuple[str, ...]
    forbidden: tuple[str, ...]
    exempt: tuple[str, ...] = ()
    allowed: tuple[str, ...] = ()


RULES = [
    Rule(
        "typer and rich belong to the CLI",
        ("cell",),
        ("typer", "rich"),
        ("cell.cli", "cell.cli_coercion", "cell.commands"),
    ),
    Rule(
        "the library never imports the commands",
        ("cell",),
        ("cell.commands", "cell.cli"),
        ("cell.cli", "cell.commands", "cell.__main__"),
    ),
    Rule("hardware only through the device registry", ("cell",), ("drivers", "fakes"), ("cell.devices",)),
    # the station (the operator's web application) sits above the run library, beside the commands: it
    # starts runs as `cell` child processes and reads their folders; nothing below it imports it
    Rule(
        "only the entry points reach the station",
        ("cell",),
        ("cell.station",),
        ("cell.station", "cell.cli", "cell.commands"),
    ),
    Rule(
        "the station's web framework stays in the station",
        ("cell",),
        ("starlette", "uvicorn", "jinja2", "sse_starlette"),
        ("cell.station",),
    ),
    Rule(
        "the foundation stands alone",
        FOUNDATION,
        ("cell",),
        allowed=("cell.defaults", "cell.errors", "cell.geometry", "cell.schema", "cell.storage"),
    ),
    Rule(
        "libraries never import a job, the controller or the device registry",
        (
            *FOUNDATION,
            "cell.config",
            "cell.mesh",
            "cell.sensing",
            "cell.analysis",
            "cell.planning",
            "cell.glass",
            "cell.results",
        ),
        ("cell.controller", "cell.inspection", "cell.devices", "cell.calibration_state", "cell.docgen"),
        exempt=JOBS,  # a package's job module (cell.glass.job) builds its devices
    ),
    Rule(
        "only jobs, the controller and the entry points reach the controller and the device registry",
        ("cell",),
        ("cell.controller", "cell.devices"),
        (*JOBS, "cell.controller", "cell.commands", "cell.cli", "cell.docgen"),
    ),
    *[
        Rule(f"{low} imports no domain package above it", (low,), DOMAIN[k + 1 :])
        for k, low in enumerate(DOMAIN[:-1])
    ],
]

# (importing module, imported module) -> why it is allowed for now
KNOWN_OFFENDERS = {
    ("cell.config", "cell.devices"): "load_cell_config has the simulator check a sim cell's world: section "
    "through cell.devices.check_world (late import); it belongs where cell.devices builds the sim cell",
}


def module_name(path: Path, root: Path = ROOT) -> str:
    """``cell/analysis/merge.py`` -> ``cell.analysis.merge``; a package's ``__init__`` is the package."""
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path, root: Path = ROOT) -> set[str]:
    """Every module ``path`` may import: ``import a.b`` gives a.b; ``from a.b import c`` gives a.b and a.b.c
    (c may be a submodule); relative imports are resolved against the file's package."""
    me = module_name(path, root)
    package = me.split(".") if path.name == "__init__.py" else me.split(".")[:-1]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join([*package[: len(package) - node.level + 1], *filter(None, [node.module])])
            found.add(base)
            found.update(f"{base}.{a.name}" for a in node.names if a.name != "*")
    return found


@cache
def graph(root: Path = ROOT) -> dict[str, set[str]]:
    """Module -> the modules it imports, for every file under root/cell."""
    return {module_name(p, root): imports(p, root) for p in sorted((root / "cell").rglob("*.py"))}


def under(name: str, prefixes: tuple[str, ...]) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def violations(g: dict[str, set[str]]) -> dict[tuple[str, str], list[str]]:
    """(importer, imported) -> the rules that edge breaks; for a ``from a.b import c`` only the longest
    name of the edge is kept, so one edge is reported once."""
    out: dict[tuple[str, str], list[str]] = defaultdict(list)
    for mod, targets in g.items():
        for t in sorted(targets):
            if any(o.startswith(t + ".") for o in targets):
                continue  # a.b when a.b.c is also imported: report a.b.c
            for r in RULES:
                if not (under(mod, r.importers) and not under(mod, r.exempt)):
                    continue
                if under(t, r.forbidden) and not under(t, r.allowed) and not under(t, (mod,)):
                    out[(mod, t)].append(r.name)
    return dict(out)


def _offender(edge: tuple[str, str]) -> tuple[str, str] | None:
    """The known offender that covers an edge (the imported name may be a submodule of the listed one)."""
    for mod, target in KNOWN_OFFENDERS:
        if edge[0] == mod and under(edge[1], (target,)):
            return mod, target
    return None


def test_the_reader_sees_every_kind_of_import(tmp_path: Path) -> None:
    pkg = tmp_path / "cell" / "sub"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("from .leaf import x\n")
    (pkg / "leaf.py").write_text(
        "from __future__ import annotations\n"
        "import typer\n"
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n"
        "    from cell.controller import Controller\n"
        "from . import sibling\n"
        "from ..devices import build_devices\n"
        "def f():\n"
        "    import drivers.recording\n"
    )
    assert imports(pkg / "__init__.py", tmp_path) == {"cell.sub.leaf", "cell.sub.leaf.x"}
    assert imports(pkg / "leaf.py", tmp_path) == {
        "__future__",
        "__future__.annotations",
        "typer",
        "typing",
        "typing.TYPE_CHECKING",
        "cell.controller",
        "cell.controller.Controller",
        "cell.sub",
        "cell.sub.sibling",
        "cell.devices",
        "cell.devices.build_devices",
        "drivers.recording",
    }
    found = violations(graph(tmp_path))
    assert set(found) == {  # the late, TYPE_CHECKING and relative imports are caught like the plain one
        ("cell.sub.leaf", "typer"),
        ("cell.sub.leaf", "cell.controller.Controller"),
        ("cell.sub.leaf", "cell.devices.build_devices"),
        ("cell.sub.leaf", "drivers.recording"),
    }


def test_the_graph_covers_cell() -> None:
    g = graph()
    assert len(g) > 100 and "cell.cli" in g and "cell.analysis" in g
    assert "typer" in g["cell.cli"]  # an edge the rules depend on is seen


@pytest.mark.parametrize("rule", RULES, ids=lambda r: r.name)
def test_the_rule_holds_but_for_known_offenders(rule: Rule) -> None:
    broken = sorted(edge for edge, rules in violations(graph()).items() if rule.name in rules)
    unexpected = [f"{a} imports {b}" for a, b in broken if _offender((a, b)) is None]
    assert not unexpected, f"{rule.name}: " + "; ".join(unexpected)


def test_every_known_offender_still_offends() -> None:
    """A fixed file leaves the list, so the list never hides a new import of the same kind."""
    used = {_offender(edge) for edge in violations(graph())}
    stale = [f"{a} -> {b}" for a, b in KNOWN_OFFENDERS if (a, b) not in used]
    assert not stale, f"remove from KNOWN_OFFENDERS (no longer imported): {stale}"


def package_graph(g: dict[str, set[str]]) -> dict[str, set[str]]:
    """The graph on packages (cell.analysis, ...) and top-level modules (cell.config, ...), plus the
    outside packages the rules name."""

    def unit(name: str) -> str | None:
        parts = name.split(".")
        if parts[0] in ("typer", "rich", "drivers", "fakes"):
            return parts[0]
        if parts[0] != "cell" or len(parts) < 2:
            return None
        return (
            ".".join(parts[:2]) if (CELL / parts[1]).is_dir() or (CELL / f"{parts[1]}.py").exists() else None
        )

    out: dict[str, set[str]] = defaultdict(set)
    for mod, targets in g.items():
        src = unit(mod)
        if src is None:
            continue  # cell/__init__.py
        out[src].update(u for t in targets if (u := unit(t)) not in (None, src))
    return dict(out)


if __name__ == "__main__":
    for src, dst in sorted(package_graph(graph()).items()):
        print(f"{src} -> {', '.join(sorted(dst)) or '-'}")
