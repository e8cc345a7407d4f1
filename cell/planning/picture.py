"""A picture of the part with its viewpoints (matplotlib, headless Agg backend): the mesh shaded by patch and
the inspectable samples each viewpoint measures, each viewpoint drawn as its camera centre, view ray to the
target and tour number."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cell.planning.planner import Plan


def draw_plan(plan: Plan, path: Path) -> None:
    """Write a PNG of the part (samples coloured by first measuring viewpoint) and the viewpoints."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = plan.surface
    first = np.where(plan.predicted.any(axis=0), np.argmax(plan.predicted, axis=0), -1)
    fig = plt.figure(figsize=(9, 7), dpi=110)
    ax = fig.add_subplot(projection="3d")
    miss = s.inspectable & (first < 0)
    ax.scatter(*s.points[first >= 0].T, c=first[first >= 0], cmap="tab20", s=1, alpha=0.6)
    ax.scatter(*s.points[miss].T, c="red", s=2, label="inspectable, not covered")
    for k, v in enumerate(plan.viewpoints):
        c = v.T_W_C[:3, 3]
        tip = c + v.T_W_C[:3, 2] * plan.sensor.standoff_mm
        ax.plot(*np.c_[c, tip], color="k", lw=0.6)
        ax.scatter(*c, color="b", s=12)
        ax.text(*c, str(k), fontsize=7)
    pts = np.vstack([s.points, [v.T_W_C[:3, 3] for v in plan.viewpoints]]) if plan.viewpoints else s.points
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    mid, half = (lo + hi) / 2, (hi - lo).max() / 2
    ax.set_xlim(mid[0] - half, mid[0] + half)
    ax.set_ylim(mid[1] - half, mid[1] + half)
    ax.set_zlim(max(0.0, mid[2] - half), mid[2] + half)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
    ax.set_title(f"{len(plan.viewpoints)} viewpoints, predicted coverage {100 * plan.coverage:.1f}%")
    ax.legend(loc="upper left", fontsize=7)
    fig.savefig(path)
    plt.close(fig)
