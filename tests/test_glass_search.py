"""Reflection search against an analytic mirror: a plane pane displaced along its normal (the case the
single-camera method is exact for); golden section vs exhaustive vs step-wise."""

import numpy as np
import trimesh

from cell.glass.reflection import RaySearchProblem, ReflectionLaw, exhaustive, golden_section, stepwise
from cell.glass.surface import SmoothSurface, unit
from fakes.sim.glass import fresnel_unpolarised, refract


def _plane(z: float) -> trimesh.Trimesh:
    v = np.array([[-200, -200, z], [200, -200, z], [200, 200, z], [-200, 200, z]], float)
    return trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)


def _problem(z_actual: float, n: int = 12) -> tuple[RaySearchProblem, np.ndarray]:
    rng = np.random.default_rng(3)
    cam = np.array([-400.0, 0.0, 500.0])
    marker = np.column_stack([rng.uniform(100, 250, n), rng.uniform(-80, 80, n), np.full(n, 250.0)])
    # the true reflection point on the mirror z = z_actual: line from the camera to the marker's mirror image
    img = marker.copy()
    img[:, 2] = 2 * z_actual - marker[:, 2]
    s = (cam[2] - z_actual) / (cam[2] - img[:, 2])
    truth = cam + s[:, None] * (img - cam)
    return RaySearchProblem(np.tile(cam, (n, 1)), unit(truth - cam), marker), truth


def test_fresnel_and_snell_match_closed_forms():
    assert np.isclose(fresnel_unpolarised(np.array([1.0]), 1.0, 1.52)[0], (0.52 / 2.52) ** 2)
    assert fresnel_unpolarised(np.array([np.cos(np.radians(60))]), 1.52, 1.0)[0] == 1.0  # beyond TIR
    d = unit(np.array([[np.sin(0.7), 0, -np.cos(0.7)]]))
    t = refract(d, np.array([[0, 0, 1.0]]), 1 / 1.52)
    assert np.isclose(np.sin(0.7) / np.hypot(t[0, 0], t[0, 1]), 1.52)


def test_golden_exhaustive_and_stepwise_find_the_mirror_point():
    prob, truth = _problem(-0.5)
    law = ReflectionLaw(prob, SmoothSurface(_plane(0.0)))
    g = golden_section(law, max_error_mm=1.0, angle_tol_rad=1e-9, length_tol_mm=1e-5)
    e = exhaustive(law, max_error_mm=1.0, step_mm=5e-4)
    s = stepwise(law, step_mm=0.1, angle_tol_rad=1e-9, length_tol_mm=1e-5)
    assert np.max(np.linalg.norm(g.points - truth, axis=1)) < 1e-3
    assert np.max(np.abs(g.t - e.t)) < 1e-3  # golden vs exhaustive within 1 um
    assert np.max(np.linalg.norm(s.points - truth, axis=1)) < 1e-3
    assert np.all(g.iterations <= 40) and np.all(g.iterations * 50 < e.iterations)
    n_true = np.array([0, 0, 1.0])
    assert np.max(np.linalg.norm(g.normals - n_true, axis=1)) < 1e-6
