"""The robotic 3D surface inspection cell (import cell)."""

import sys
from types import FrameType

__version__ = "0.1.0"


class _DeferCascadio:
    """Keeps trimesh from loading OpenCASCADE when trimesh is imported.

    ``trimesh.exchange.cascade`` imports ``cascadio`` (its STEP reader, a shared library that costs ~0.9 s of
    CPU to load) on every ``import trimesh``: a third of a whole ``cell compare``. Only STEP files need it.
    This import hook refuses that one import (trimesh then marks STEP unavailable); every other import of
    cascadio works, and :func:`cell.mesh.load_mesh` imports it and registers trimesh's STEP loader the first
    time it reads a STEP file.
    """

    @staticmethod
    def find_spec(name: str, path: object = None, target: object = None) -> None:
        if name != "cascadio":
            return None
        frame: FrameType | None = sys._getframe(1)
        while frame is not None and frame.f_globals.get("__name__", "").startswith("importlib"):
            frame = frame.f_back
        if frame is not None and frame.f_globals.get("__name__") == "trimesh.exchange.cascade":
            raise ModuleNotFoundError("cascadio is loaded on demand by cell.mesh", name=name)
        return None


if not any(isinstance(f, _DeferCascadio) for f in sys.meta_path):
    sys.meta_path.insert(0, _DeferCascadio())
