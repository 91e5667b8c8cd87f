"""The test oracles (tests/oracles.py) against values known in closed form, so
that a wrong oracle cannot make a wrong torchvor pass."""
from __future__ import annotations

import numpy as np
import pytest

from oracles import exact_cell_oracle, voronoi_cell_oracle


def test_single_point_cell_is_the_box():
    """One point in a 2 x 1 x 1 box: the cell is the box. About the seed s,
    the second moment is the sum over axes of the integral of (x - s)^2."""
    lo, hi = np.zeros(3), np.array([2.0, 1.0, 1.0])
    seed = np.array([[0.5, 0.25, 0.75]])
    cell = voronoi_cell_oracle(seed, 0, (lo, hi))
    volume = 2.0
    second = sum(volume / (h - l) * ((h - s) ** 3 - (l - s) ** 3) / 3 for l, h, s in zip(lo, hi, seed[0]))
    assert cell.volume == pytest.approx(volume, rel=1e-14, abs=0)
    assert cell.area == pytest.approx(2 * (2 + 2 + 1), rel=1e-14, abs=0)
    assert cell.second_moment == pytest.approx(second, rel=1e-14, abs=0)
    np.testing.assert_allclose(cell.centroid, [1.0, 0.5, 0.5], rtol=1e-14)


def test_two_points_split_the_box():
    """Two points on the x axis of the unit cube: the bisector x = 0.4 splits it."""
    points = np.array([[0.2, 0.5, 0.5], [0.6, 0.5, 0.5]])
    box = (np.zeros(3), np.ones(3))
    left, right = (voronoi_cell_oracle(points, i, box) for i in range(2))
    assert left.volume == pytest.approx(0.4, rel=1e-14, abs=0) and right.volume == pytest.approx(0.6, rel=1e-14, abs=0)
    assert left.area == pytest.approx(2 + 4 * 0.4, rel=1e-14, abs=0)
    np.testing.assert_allclose(left.centroid, [0.2, 0.5, 0.5], rtol=1e-14)
    np.testing.assert_allclose(right.centroid, [0.7, 0.5, 0.5], rtol=1e-14)
    assert list(left.facet_neighbors) == [1] and list(right.facet_neighbors) == [0]


def test_exact_oracle_counts_copies_once():
    """Copies among the candidates (of a neighbour, and of the seed at a
    higher index) bound the cell as one point: the bisector x = 0.4 still
    gives the left cell 0.4 of the unit cube, not a face counted twice."""
    points = np.array([[0.2, 0.5, 0.5], [0.6, 0.5, 0.5], [0.6, 0.5, 0.5], [0.2, 0.5, 0.5]])
    cell = exact_cell_oracle(points, 0, (np.zeros(3), np.ones(3)), candidates=[1, 2, 3])
    assert cell.volume == pytest.approx(0.4, rel=1e-14, abs=0)
    np.testing.assert_allclose(cell.centroid, [0.2, 0.5, 0.5], rtol=1e-14)


def test_exact_oracle_with_weights_matches_qhull():
    """Power cells (weights up to 4 squared spacings: many cells lie away from
    their points) in rational arithmetic, against Qhull's half-space cells."""
    rng = np.random.default_rng(2)
    points, weights = rng.random((25, 3)), rng.random(25) * 0.6
    box = (np.zeros(3), np.ones(3))
    checked = 0
    for i in range(25):
        qhull = voronoi_cell_oracle(points, i, box, weights=weights)
        if qhull.empty:
            continue
        exact = exact_cell_oracle(points, i, box, weights=weights)
        assert exact.volume == pytest.approx(qhull.volume, rel=1e-10)
        np.testing.assert_allclose(exact.centroid, qhull.centroid, atol=1e-10)
        assert exact.second_moment == pytest.approx(qhull.second_moment, rel=1e-9)
        checked += 1
    assert checked >= 5


def test_exact_oracle_counts_a_face_on_a_wall_once():
    """A point mirrored across the wall x = 1 puts its bisector on the wall:
    the cell is the one without it, the face on the wall counted once."""
    points = np.array([[0.5, 0.5, 0.5], [1.5, 0.5, 0.5], [0.2, 0.3, 0.4], [0.8, 0.9, 0.1]])
    box = (np.zeros(3), np.ones(3))
    with_mirror = exact_cell_oracle(points, 0, box, candidates=[1, 2, 3])
    without = exact_cell_oracle(points[[0, 2, 3]], 0, box, candidates=[1, 2])
    assert with_mirror.volume == without.volume
    assert with_mirror.volume == pytest.approx(voronoi_cell_oracle(points, 0, box).volume, rel=1e-14)


def test_exact_oracle_takes_cells_of_hundreds_of_faces():
    """A seed at the centre of 300 points on a sphere (each radius jittered):
    every point gives a face; the exact cell agrees with Qhull's."""
    rng = np.random.default_rng(4)
    directions = rng.normal(size=(300, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    points = np.concatenate([[[0.5, 0.5, 0.5]], 0.5 + 0.1 * directions * (1 + 0.01 * rng.random((300, 1)))])
    box = (np.zeros(3), np.ones(3))
    qhull = voronoi_cell_oracle(points, 0, box)
    exact = exact_cell_oracle(points, 0, box, candidates=range(1, 301))
    assert len(exact.faces) == len(qhull.facet_neighbors) > 250
    assert exact.volume == pytest.approx(qhull.volume, rel=1e-12)
    np.testing.assert_allclose(exact.centroid, qhull.centroid, atol=1e-13)
