"""The ``cell`` entry point: commands load on demand, and usage errors end in one line with exit code 2."""

from __future__ import annotations

import importlib
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

import cell.commands
from cell.cli import COMMANDS, load_module_commands

REPO = Path(__file__).resolve().parent.parent


def run(*code_or_args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, *code_or_args], capture_output=True, text=True, cwd=REPO, timeout=120
    )


def test_the_command_table_names_exactly_what_the_modules_register() -> None:
    registered = {}
    for info in pkgutil.iter_modules(cell.commands.__path__):
        if not hasattr(importlib.import_module(f"cell.commands.{info.name}"), "register"):
            continue  # a sub-command's module (latency), added to its group by the group's module
        for name in load_module_commands(info.name):
            registered[name] = info.name
    assert registered == {name: module for name, (module, _) in COMMANDS.items()}
    assert all(help_line.strip() for _, help_line in COMMANDS.values())


def test_help_lists_every_command_without_importing_any_command_or_the_library() -> None:
    code = (
        "import sys\nfrom cell.cli import main\nmain(['--help'])\n"
        "heavy = [m for m in sys.modules if m.startswith('cell.commands.') or m.split('.')[0] in "
        "('numpy', 'trimesh', 'scipy', 'matplotlib', 'numba', 'rich')]\nprint('HEAVY', heavy)"
    )
    proc = run("-c", code)
    assert proc.returncode == 0, proc.stderr
    for name in COMMANDS:
        assert f"  {name} " in proc.stdout
    assert "HEAVY []" in proc.stdout


def command_lines() -> list[list[str]]:
    """Every command and sub-command, as the words that name it (``["calibrate", "sensor"]``)."""
    lines: list[list[str]] = []

    def walk(words: list[str], command: object) -> None:
        lines.append(words)
        for name, sub in (getattr(command, "commands", None) or {}).items():
            walk([*words, name], sub)

    for module in dict.fromkeys(module for module, _ in COMMANDS.values()):
        for name, command in load_module_commands(module).items():
            walk([name], command)
    return lines


@pytest.mark.parametrize("width", [50, 64, 78])
def test_cell_help_is_printed_as_typer_prints_it(width: int, capsys: pytest.CaptureFixture[str]) -> None:
    """`cell --help` is written from the command table without typer (a tenth of the start-up); it must
    read exactly as typer's own help of the same group, at any terminal width."""
    from typer._click import formatting

    from cell.cli import build_app, root_help

    saved, formatting.FORCED_WIDTH = formatting.FORCED_WIDTH, width
    try:
        build_app()(args=["--help"], prog_name="cell", standalone_mode=False)
    finally:
        formatting.FORCED_WIDTH = saved
    assert capsys.readouterr().out == root_help(width)


def test_every_command_help_and_usage_error_loads_no_library() -> None:
    """`cell CMD --help` and a usage error of every command and sub-command import only typer and the
    command modules: no numpy, scipy, trimesh, numba, matplotlib, pydantic (typer's option conversion
    included, see cell.cli_coercion), rich or the command's library. The first command line that loads one
    is named."""
    words = command_lines()
    code = (
        "import json, sys\nfrom cell.cli import main\n"
        f"heavy = ('numpy', 'scipy', 'trimesh', 'numba', 'matplotlib', 'pydantic', 'rich', 'yaml')\n"
        f"for line in {words!r}:\n"
        "    for args in (line + ['--help'], line + ['--bogus-option']):\n"
        "        try:\n            main(args)\n        except SystemExit:\n            pass\n"
        "        loaded = sorted({m.split('.')[0] for m in sys.modules} & set(heavy))\n"
        "        lib = sorted(m for m in sys.modules if m.startswith('cell.') and m.split('.')[1] not in "
        "('cli', 'cli_coercion', 'commands', 'errors', 'defaults', 'runs', 'storage', 'exit_codes'))\n"
        "        if loaded or lib:\n"
        "            print('HEAVY', json.dumps([args, loaded, lib]))\n            sys.exit(0)\n"
        "print('HEAVY none')\n"
    )
    proc = run("-c", code)
    assert "HEAVY none" in proc.stdout, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert len(words) > 25  # every group's sub-commands were walked


def test_query_commands_load_only_what_their_answer_needs(tmp_path: Path) -> None:
    """`cell station users list` reads its YAML file without the cell config (numpy), the results database
    or the station's web stack; `cell verify history` and `cell history` read an up-to-date database
    without Alembic (its migrations run only when the schema is behind) and without numpy or scipy. One
    process runs the three commands in that order and says what is loaded after each (the set only grows)."""
    from cell.results import open_results
    from cell.station.users import Role, add_user

    runs = tmp_path / "runs"
    add_user(runs / ".station" / "users.yaml", "anna", Role.TECHNICIAN, "1234")
    assert open_results(None, runs).runs() == []  # creates and migrates results.sqlite
    code = (
        "import json, sys\nfrom cell.cli import main\n"
        "heavy = ('numpy', 'scipy', 'sqlalchemy', 'alembic', 'starlette', 'uvicorn', 'jinja2', 'psycopg')\n"
        f"for args in {[['station', 'users', 'list'], ['verify', 'history'], ['history']]!r}:\n"
        f"    try:\n        main([*args, '--runs', {str(runs)!r}])\n    except SystemExit:\n        pass\n"
        "    loaded = sorted({m.split('.')[0] for m in sys.modules} & set(heavy))\n"
        "    config = sorted(m for m in ('cell.config', 'cell.station.app') if m in sys.modules)\n"
        "    print('LOADED', json.dumps([args, loaded + config]), flush=True)\n"
    )
    proc = run("-c", code)
    assert proc.returncode == 0, proc.stderr[-2000:]
    loaded = [line for line in proc.stdout.splitlines() if line.startswith("LOADED")]
    assert loaded == [
        'LOADED [["station", "users", "list"], []]',
        'LOADED [["verify", "history"], ["sqlalchemy"]]',
        'LOADED [["history"], ["sqlalchemy"]]',
    ], proc.stdout
    assert "anna\ttechnician" in proc.stdout and f"no runs in {runs / 'results.sqlite'}" in proc.stdout


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["compare"], "Missing argument"),
        (["compare", "a.stl", "b.ply", "--bogus"], "No such option: --bogus"),
        (["nosuch"], "No such command 'nosuch'"),
        (["sensor", "error-table", "--x"], "No such option: --x"),
        # a serial a folder cannot hold, before anything is read or written
        (["inspect", "recipes/pillar.yaml", "--serial", "../SN 7"], "field '--serial': '../SN 7' is not a"),
    ],
)
def test_usage_errors_are_one_line_with_exit_code_2(args: list[str], says: str) -> None:
    proc = run("-m", "cell", *args)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and says in lines[0] and lines[0].startswith("error:"), proc.stderr
    assert "Traceback" not in proc.stderr


def test_cell_devices_exits_1_when_a_device_fails() -> None:
    """The lab cell's real devices are not attached here: every one fails to connect, and the exit code says
    so (a wrapper script must not have to parse the table); the simulated cell's all connect."""
    failed = run("-m", "cell", "devices", "--cell", "recipes/cells/lab.yaml")
    assert failed.returncode == 1, failed.stdout + failed.stderr
    assert "FAILED" in failed.stdout and "error:" in failed.stderr
    ok = run("-m", "cell", "devices")
    assert ok.returncode == 0, ok.stdout + ok.stderr


def test_results_are_never_written_over(tmp_path: Path) -> None:
    """plan, scan and compare refuse an --out folder that holds files (as inspect and glass do): a compare
    into a scan's folder used to replace the scan's cloud.ply without a word."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "cloud.ply").write_text("a scan's cloud")
    for args in (["compare", "n.stl", "c.ply"], ["scan"], ["plan", "recipes/pillar.yaml"]):
        r = run("-m", "cell", *args, "--out", str(out))
        assert r.returncode == 2 and "--out holds files already" in r.stderr, (args, r.stderr)
    assert (out / "cloud.ply").read_text() == "a scan's cloud"


def _report(verdict: str, **fields: object) -> dict:
    """A report.json (docs/report-schema.md) with the fields the verdict's reasons read."""
    return {
        "verdict": verdict,
        "tolerance": {"lower_mm": -0.3, "upper_mm": 0.3},
        "deviation": {"min_mm": -0.1, "max_mm": 0.1},
        "n_points": 1000,
        "n_out_of_tolerance": 0,
        "coverage": 0.9993,
        "min_coverage": 0.95,
        "regions": [],
        "region_verdicts": [],
        "incomplete_reasons": [],
        **fields,
    }


def test_an_incomplete_or_failed_verdict_says_why_under_its_line(tmp_path: Path, capsys) -> None:
    """`cell inspect`/`resume`/`report`/`demo` print the report's reasons under an INCOMPLETE or FAIL verdict
    (as report.html gives them), nothing under a PASS; and exit with the verdict's code."""
    import json
    from types import SimpleNamespace

    from cell.commands.inspect import _finish, verdict_reasons_lines
    from cell.inspection_run import RunOutcome

    disagree = "overlapping views disagree by more than 0.1 mm over 16248 mm^2: the calibration does not hold"
    incomplete = _report(
        "incomplete",
        incomplete_reasons=[disagree],
        region_verdicts=[{"name": "seal", "verdict": "no_data", "coverage": None}],
    )
    dent = {
        "name": "out-of-tolerance-1",
        "verdict": "fail",
        "kind": "dent",
        "n_points": 40,
        "extreme_mm": -0.59,
        "extreme_at_mm": [21.0, 10.0, 39.0],
        "limit_mm": -0.3,
        "beyond_mm": -0.29,
    }
    failed = _report("fail", n_out_of_tolerance=40, regions=[dent])
    said = {}
    for doc in (incomplete, failed, _report("pass")):
        results = tmp_path / doc["verdict"] / "results"
        results.mkdir(parents=True)
        (results / "report.json").write_text(json.dumps(doc))
        run = SimpleNamespace(path=results.parent, results_dir=results)
        summary = {"verdict": doc["verdict"], "n_points": 1000, "coverage": 0.9993}
        with pytest.raises(SystemExit) as ended:
            _finish(RunOutcome(run, "done", "", summary))  # type: ignore[arg-type]
            raise SystemExit(0)
        said[doc["verdict"]] = (ended.value.code, capsys.readouterr().out.splitlines())
        assert said[doc["verdict"]][1][1:-1] == verdict_reasons_lines(results / "report.json")
    code, lines = said["incomplete"]
    assert code == 5 and lines[0].startswith("verdict: INCOMPLETE") and lines[-1].startswith("report: ")
    assert lines[1:-1] == [
        f"  - {disagree}",
        "  - Region \u201cseal\u201d is not measured: it cannot be judged.",
    ]
    code, lines = said["fail"]
    assert (
        code == 4
        and len(lines) == 3
        and lines[1].startswith("  - 40 points beyond the tolerance in 1 region")
    )
    assert "a dent of" in lines[1] and "0.290 mm beyond the limit" in lines[1]
    code, lines = said["pass"]
    assert code == 0 and len(lines) == 2  # the verdict and the report's path
    assert verdict_reasons_lines(tmp_path / "nowhere.json") == []


def test_an_uncalibrated_cell_is_warned_of_with_the_way_to_calibrate(tmp_path: Path) -> None:
    """The warning `cell inspect`/`resume` print when the cell config names no calibration: how to
    calibrate, or the calibration `cell calibrate all` made of this very file (as `cell demo` finds it);
    none when a calibration is named."""
    import hashlib
    import json
    import shutil
    from types import SimpleNamespace

    from cell.config import load_cell_config
    from cell.defaults import DEFAULT_CELL
    from cell.inspection_run import _warn_if_uncalibrated, uncalibrated_warning

    cfg = load_cell_config(DEFAULT_CELL)
    runs = tmp_path / "runs"
    runs.mkdir()
    warning = uncalibrated_warning(DEFAULT_CELL, cfg, [runs], "sim.yaml")
    assert warning is not None and "\n" not in warning
    assert "names no calibration" in warning and "usually ends INCOMPLETE" in warning
    assert "`cell calibrate all --cell sim.yaml --out DIR`, then inspect with --cell DIR/cell.yaml" in warning
    # a finished `cell calibrate all` of this file (calibration.json names its digest): named
    calibrated = runs / "calibration-sim"
    calibrated.mkdir()
    shutil.copy(DEFAULT_CELL, calibrated / "cell.yaml")
    digest = hashlib.sha256(DEFAULT_CELL.read_bytes()).hexdigest()
    (calibrated / "calibration.json").write_text(json.dumps({"source_sha256": digest}))
    (runs / "calibration-other").mkdir()  # of another file: passed over
    (runs / "calibration-other" / "calibration.json").write_text(json.dumps({"source_sha256": "0" * 64}))
    (runs / "calibration-other" / "cell.yaml").write_text("name: other\n")
    warning = uncalibrated_warning(DEFAULT_CELL, cfg, [runs])
    assert warning and f"inspect with --cell {calibrated.resolve() / 'cell.yaml'}" in warning
    # a run folder under runs/: its inputs' copy of the cell, named as given
    inputs = runs / "run" / "inputs"
    inputs.mkdir(parents=True)
    shutil.copy(DEFAULT_CELL, inputs / "cell.original.yaml")
    shutil.copy(DEFAULT_CELL, inputs / "cell.yaml")
    manifest = {"cell": "cell.yaml", "cell_as_given": "cell.original.yaml", "sources": {"cell": "given.yaml"}}
    (inputs / "manifest.json").write_text(json.dumps(manifest))
    said: list[str] = []
    _warn_if_uncalibrated(SimpleNamespace(path=inputs.parent), said.append)  # type: ignore[arg-type]
    assert len(said) == 1 and "the cell config given.yaml names no calibration" in said[0]
    assert f"--cell {calibrated.resolve() / 'cell.yaml'}" in said[0]
    # calibrated: nothing to say
    cfg.calibration.hand_eye = Path("handeye.yaml")
    assert uncalibrated_warning(DEFAULT_CELL, cfg, [runs]) is None
