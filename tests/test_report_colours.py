"""The report's colour scale against its tolerance band: in tolerance neutral, beyond it saturated, a step at
each limit, and the same colours in the static views, the 3D view's plotly scale and the legend."""

from __future__ import annotations

import colorsys
import re

import numpy as np
import pytest

from cell.analysis.colour_scale import BandedScale


def saturation(rgb: np.ndarray) -> np.ndarray:
    return np.array([colorsys.rgb_to_hsv(*(c / 255.0))[1] for c in rgb])


@pytest.mark.parametrize("band", [(-0.3, 0.3), (-0.1, 0.25), (0.05, 0.5)])
def test_inside_the_band_is_neutral_beyond_it_saturated(band: tuple[float, float]) -> None:
    lo, hi = band
    scale = BandedScale(lo, hi)
    inside = np.linspace(lo, hi, 201)
    below = np.linspace(lo - 2 * (hi - lo), lo - 1e-6, 50)
    above = np.linspace(hi + 1e-6, hi + 2 * (hi - lo), 50)
    assert saturation(scale.rgb(inside)).max() < 0.25  # pale greys, faintly tinted
    assert scale.rgb(inside).min() > 170  # and light
    assert saturation(scale.rgb(below)).min() > 0.75 and saturation(scale.rgb(above)).min() > 0.75
    b, r = scale.rgb(below).astype(int), scale.rgb(above).astype(int)
    assert (b[:, 2] > b[:, 0]).all() and (r[:, 0] > r[:, 2]).all()  # blue below, red above
    assert (np.diff(b.sum(1)) >= 0).all() and (np.diff(r.sum(1)) <= 0).all()  # darker farther out


def test_the_colour_steps_at_each_limit_and_is_plain_grey_at_zero() -> None:
    scale = BandedScale(-0.3, 0.3)
    at_lo, past_lo, at_hi, past_hi, zero = scale.rgb([-0.3, -0.3001, 0.3, 0.3001, 0.0])
    assert np.abs(at_lo.astype(int) - past_lo).sum() > 150 and np.abs(at_hi.astype(int) - past_hi).sum() > 150
    assert len(set(zero.tolist())) == 1  # grey
    assert scale.zone([-0.3, -0.3001, 0.3, 0.3001]).tolist() == [0, -1, 0, 1]  # limits are in tolerance


def test_a_one_sided_band_is_neutral_at_its_centre() -> None:
    scale = BandedScale(0.1, 0.5)
    assert scale.reference_mm == pytest.approx(0.3)
    assert len(set(scale.rgb([0.3])[0].tolist())) == 1 and saturation(scale.rgb([0.0])).min() > 0.75


def test_the_plotly_scale_and_the_legend_give_the_same_colours() -> None:
    """plotly interpolates its scale linearly between stops: sampled that way it must give rgb()'s colours;
    the CSS gradient of the legend has the same stops and marks at the limits."""
    scale = BandedScale(-0.2, 0.35)
    c0, c1 = scale.range_mm
    stops = scale.plotly_colorscale()
    pos = np.array([s[0] for s in stops])
    cols = np.array([[int(v) for v in re.findall(r"\d+", s[1])] for s in stops], float)
    assert pos[0] == 0 and pos[-1] == 1 and (np.diff(pos) >= 0).all()
    for d in np.r_[np.linspace(c0, c1, 97), c0 - 1, c1 + 1]:
        t = np.clip((d - c0) / (c1 - c0), 0, 1)
        k = np.searchsorted(pos, t, side="right") - 1
        k = min(k, len(pos) - 2)
        if pos[k + 1] == pos[k]:
            k += 1
        w = (t - pos[k]) / (pos[k + 1] - pos[k]) if pos[k + 1] > pos[k] else 0.0
        expected = cols[k] + w * (cols[k + 1] - cols[k])
        assert np.abs(expected - scale.rgb([d])[0]).max() <= 1.0, d
    legend = scale.legend_html()
    assert legend.count('class="tick limit"') == 2 and "\u22120.200" in legend and "+0.350" in legend
    assert scale.css_gradient().count("%") == len(stops)
