"""Generate the glass panes of the glass recipes: the nominal windshield-like top skin and a made pane with a
known sag (truth in ``pane_sag.truth.json``).

Run ``.venv/bin/python recipes/glass/make_panes.py [--out DIR]`` (default: ``recipes/glass/panes``). The
output is deterministic. Units mm; the pane lies convex side up with its apex at the origin of {W}
(T_W_P = identity).
The pane is a height field z = -(x^2 / 2 Rx + y^2 / 2 Ry) over 300 x 200 mm, tessellated every 3 mm (chord
error 0.75 um at R = 1500 mm; the simulator interpolates vertex normals, see cell/glass/surface.py); the sag
is a Gaussian dip of the top skin (fakes/sim/glass_pane.py).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict, dataclass
from pathlib import Path

HERE = Path(__file__).resolve().parent


@dataclass(frozen=True)
class PaneSpec:
    """Shape of the nominal pane and of the made pane's sag (mm)."""

    size_mm: tuple[float, float] = (300.0, 200.0)
    radius_x_mm: float = 1500.0
    radius_y_mm: float = 3000.0
    spacing_mm: float = 3.0
    sag_depth_mm: float = 0.8
    sag_centre_mm: tuple[float, float] = (30.0, 20.0)
    sag_sigma_mm: float = 60.0


def make_panes(out: Path, spec: PaneSpec = PaneSpec()) -> dict[str, Path]:
    """Write pane_nominal.stl, pane_sag.stl and pane_sag.truth.json into ``out``; return their paths."""
    import sys

    sys.path.insert(0, str(HERE.parents[1]))  # run as a script from anywhere in the repo
    from fakes.sim.glass_pane import heightfield_mesh, sag_height, windshield_height

    out.mkdir(parents=True, exist_ok=True)
    base = windshield_height(spec.radius_x_mm, spec.radius_y_mm)
    sag = sag_height(base, spec.sag_depth_mm, spec.sag_centre_mm, spec.sag_sigma_mm)
    paths = {
        "nominal": out / "pane_nominal.stl",
        "sag": out / "pane_sag.stl",
        "truth": out / "pane_sag.truth.json",
    }
    heightfield_mesh(base, spec.size_mm, spec.spacing_mm).export(paths["nominal"])
    heightfield_mesh(sag, spec.size_mm, spec.spacing_mm).export(paths["sag"])
    truth = {
        "description": "made pane = nominal with a Gaussian sag of the top skin (positive depth = down)",
        **asdict(spec),
    }
    paths["truth"].write_text(json.dumps(truth, indent=2) + "\n")
    return paths


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=HERE / "panes")
    for name, path in make_panes(parser.parse_args().out).items():
        print(f"{name}: {path}")
