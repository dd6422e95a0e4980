"""The density rule of Park & Hodgins' deformation (stages/skin/density.py)."""

from __future__ import annotations

import numpy as np

from mocapflow.stages.skin.density import density_warning, marker_density


def _grid(n: int, spacing: float) -> np.ndarray:
    """``n`` markers on a line ``spacing`` apart (their nearest-neighbour spacing)."""
    return np.stack([np.arange(n) * spacing, np.zeros(n), np.zeros(n)], 1)


def test_two_dense_parts_suit_the_method():
    d = marker_density(_grid(30, 0.05), np.repeat([0, 1], 15))
    assert d["suited"] and d["part_markers"] == [15, 15] and d["covered"] == 1.0


def test_one_rigid_part_does_not_suit_the_method():
    """A static trial segments into one part (c3d.org sample28 standing.C3D: 32 markers
    45 mm apart, one part): the spacing and coverage tests pass, the method does not."""
    d = marker_density(_grid(32, 0.045), np.zeros(32, int))
    assert d["spacing_mm"] == 45.0 and d["covered"] == 1.0
    assert not d["suited"] and ">= 2 parts" in d["rule"]
    assert "1 part(s): below the density" in density_warning(d, "standing.C3D")


def test_sparse_or_uncovered_markers_do_not_suit_the_method():
    assert not marker_density(_grid(30, 0.09), np.repeat([0, 1], 15))["suited"]
    assert not marker_density(_grid(30, 0.05), np.arange(30) // 5)["suited"]  # parts of 5
