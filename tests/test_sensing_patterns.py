"""Pattern sets against the dissertation's counts (2.1.4) and the coding rules they must satisfy."""

from __future__ import annotations

import numpy as np
import pytest

from cell.config import DEFAULT_CELL, load_cell_config
from cell.errors import ConfigError
from cell.sensing.patterns import (
    dissertation_gcls,
    gcls_patterns,
    gcps_patterns,
    measuring_patterns,
    sensor_calibration_patterns,
)
from fakes.sim.testing import small_sensor


def test_dissertation_set_has_64_stripes_of_12px_and_768_codes() -> None:
    ps = dissertation_gcls()
    code = ps.code("columns")
    got = (code.n_gray, 1 << code.n_gray, code.stripe_px, code.n_shifts, code.n_codes)
    assert got == (6, 64, 12, 12, 768)
    assert len(ps) == 2 + 2 * 6 + 2 * 12 and ps.frames.shape == (38, 768, 1024)
    v = dissertation_gcls("0.4mm").code("columns")
    assert (v.shift_px, v.n_shifts, v.n_codes) == (2, 6, 384)  # 1024 * 0.4 / 200 ~ 2 px; 64 x 6 codes


def test_every_coded_frame_is_the_inverse_of_its_partner_and_gray_codes_are_unique() -> None:
    ps = gcls_patterns(256, 64, 8, 4, "both")
    for i, name in enumerate(ps.names):
        if name.endswith("_inv"):
            a, b = ps.frames[ps.index(name[:-4])].astype(int), ps.frames[i].astype(int)
            code = ps.code("columns" if name.startswith("col") else "rows")
            inside = np.zeros_like(a, bool)
            if code.axis == "columns":
                inside[:, code.offset_px : code.offset_px + code.extent_px] = True
            else:
                inside[code.offset_px : code.offset_px + code.extent_px, :] = True
            assert np.all((a + b)[inside] == 255), name
    # Gray bits along a row: consecutive stripes differ in exactly one bit, and all stripes differ.
    code = ps.code("columns")
    bits = np.stack([ps.frames[ps.index(f"col_gray{b}")][0] > 0 for b in range(code.n_gray)])
    per_stripe = bits[:, code.offset_px :: code.stripe_px][:, : 1 << code.n_gray]
    assert np.all(np.abs(np.diff(per_stripe.astype(int), axis=1)).sum(0) == 1)
    assert len({tuple(c) for c in per_stripe.T}) == 1 << code.n_gray


def test_line_shift_edges_fall_every_shift_px() -> None:
    ps = gcls_patterns(128, 8, 12, 6, n_gray=3)
    code = ps.code("columns")
    edges = set()
    for j in range(code.n_shifts):
        row = ps.frames[ps.index(f"col_shift{j}")][0].astype(int)
        edges |= set(np.flatnonzero(np.diff(row)) + 1)
    inner = sorted(e - code.offset_px for e in edges if code.offset_px < e < code.offset_px + code.extent_px)
    assert inner == list(range(code.shift_px, code.extent_px, code.shift_px))


def test_gcps_same_image_count_and_bad_parameters() -> None:
    assert len(gcps_patterns(1024, 768, 12, 24, n_gray=6)) == len(dissertation_gcls())
    with pytest.raises(ConfigError, match="multiple"):
        gcls_patterns(stripe_px=12, n_shifts=5)
    with pytest.raises(ConfigError, match="direction"):
        gcls_patterns(direction="diagonal")  # type: ignore[arg-type]


def test_the_cells_measuring_code_is_the_dissertations_set():
    """On the prototype's 1024x768 projector the measuring code is the dissertation's GCLS set (6 Gray
    patterns, 64 stripes of 12 px, 12 shifts of 1 px: 768 codes); on a small projector as few Gray patterns
    as cover it. The sensor calibration codes both axes with shifts of 2 px."""
    proj = load_cell_config(DEFAULT_CELL).sensor.projector
    assert (proj.width_px, proj.height_px) == (1024, 768)
    measuring, paper = measuring_patterns(proj), dissertation_gcls("full")
    assert measuring.names == paper.names and measuring.codes == paper.codes
    # the same bits; the line shifts' edges ramped over MEASURING_EDGE_PX (grey levels beside each boundary)
    np.testing.assert_array_equal(measuring.frames > 127, paper.frames > 127)
    shifts = [i for i, n in enumerate(measuring.names) if "shift" in n]
    assert np.array_equal(measuring.frames[: shifts[0]], paper.frames[: shifts[0]])
    grey = set(np.unique(measuring.frames[shifts])) - {0, 255}
    assert len(grey) == 2 and sum(grey) == 255  # one level either side of each boundary, mirrored
    small = small_sensor().projector
    assert len(measuring_patterns(small).frames) < len(measuring_patterns(proj).frames)
    both = sensor_calibration_patterns(proj)
    assert {c.axis for c in both.codes} == {"columns", "rows"}
