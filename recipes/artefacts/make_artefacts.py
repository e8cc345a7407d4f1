"""Write the verification artefacts' meshes (STL, mm, each in its own frame) from a certificate, for viewing
or for a print/machining drawing check.

Run ``.venv/bin/python recipes/artefacts/make_artefacts.py --out DIR [--certificate FILE]``. Nothing needs the
files: the simulator builds the same meshes from the certificate when it places an artefact
(cell/verification/artefacts.py), so no mesh is committed and the meshes can never disagree with the
certified values.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from cell.verification.artefacts import ball_bar, plane, sphere_artefact
from cell.verification.certificate import DEFAULT_CERTIFICATE, load_certificate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True, help="output folder (created)")
    ap.add_argument("--certificate", type=Path, default=DEFAULT_CERTIFICATE, help="certificate YAML")
    args = ap.parse_args()
    cert = load_certificate(args.certificate)
    args.out.mkdir(parents=True, exist_ok=True)
    meshes = {
        "sphere": sphere_artefact(cert.sphere),
        "ball_bar": ball_bar(cert.ball_bar),
        "plane": plane(cert.plane),
    }
    if cert.ball_bar_long is not None:
        meshes["ball_bar_long"] = ball_bar(cert.ball_bar_long)
    for name, mesh in meshes.items():
        path = args.out / f"{name}.stl"
        mesh.export(path)
        print(f"{path}: {len(mesh.faces)} triangles, extents {mesh.extents.round(2).tolist()} mm")


if __name__ == "__main__":
    main()
