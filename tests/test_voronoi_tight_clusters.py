"""Ill-conditioned cells: clusters far tighter than the cells around them
(needle cells, nearly parallel or nearly concurrent bisectors) against the
oracles, and the regressions they found, pinned to exact rational arithmetic
(tests/oracles.py, exact_cell_oracle).
"""
from __future__ import annotations

import subprocess

import numpy as np
import pytest
import torch

from torchvor import CellStatus

from oracles import exact_cell_oracle, voronoi_cell_oracle
from voronoi_checks import RTOL, UNIT, box_of, check_against_oracle, check_global, pick_cells, run


def tight_clusters(gen, spread):
    """8 clusters of 40 points (float64) with Gaussian spread `spread` around
    centres in [0.1, 0.9]^3, clamped into the unit box."""
    centres = torch.rand(8, 3, generator=gen, dtype=torch.float64) * 0.8 + 0.1
    points = centres.repeat_interleave(40, 0) + spread * torch.randn(320, 3, generator=gen, dtype=torch.float64)
    return points.clamp(0, 1)


@pytest.mark.parametrize("spread", [1e-3, 1e-5, 1e-6])
def test_tight_clusters(device, dtype, gen, spread, cells_impl, vertex_balls):
    """Clusters of 40 points with Gaussian spread 1e-3 .. 1e-6 (far above the
    float64 resolution; 1e-6 is ~16 float32 ulps). The clusters' outer cells are
    needles (~1e-5 wide, ~0.1 long) whose faces float32 fixes only to about
    eps * R: float32 is compared with a conditioning allowance (the errors
    reach ~70 eps R A, i.e. up to 35% of a 5e-11 needle's volume)."""
    points = tight_clusters(gen, spread).to(dtype).to(device)
    cells = run(points, UNIT)
    lohi = box_of(points, UNIT)
    check_global(cells, points, [lohi], dtype)
    check_against_oracle(cells, points, lohi, pick_cells(points, 30, gen, *lohi), RTOL[dtype],
                         conditioning=256.0 if dtype == torch.float32 else 0.0)


def test_isolated_point_and_tight_cluster_regression(device, cells_impl):
    """A minimal float64 case of test_tight_clusters: a point 0.5 away from a
    cluster of 5 points spread over ~1e-6. Its cell is cut by 5 nearly identical
    bisectors, which must not leave it BOUNDARY_ERROR (NaN) after the recovery
    passes."""
    points = torch.tensor([
        [0.2808163687166727, 0.5465951753340205, 0.5700229974517792],
        [0.645556639486295, 0.6963005660028954, 0.28212514775911424],
        [0.645556509586697, 0.6963016712265706, 0.282123828585993],
        [0.6455563428642276, 0.696300099215462, 0.2821248385088811],
        [0.645555560803219, 0.6963008066546875, 0.2821215098277126],
        [0.6455553229128691, 0.6963016050455724, 0.2821243632640453]], dtype=torch.float64).to(device)
    cells = run(points, UNIT)
    lohi = box_of(points, UNIT)
    check_global(cells, points, [lohi], torch.float64)
    check_against_oracle(cells, points, lohi, range(6), 1e-10)


def seeded_tight_clusters(seed, spread, cell, point):
    """test_tight_clusters' float64 input for `seed` (a regression case),
    after checking that point `cell` is still `point` (the generator and
    tight_clusters unchanged)."""
    gen = torch.Generator()
    gen.manual_seed(seed)
    points = tight_clusters(gen, spread)
    assert points[cell].tolist() == point
    return points


def assert_pinned_cell(cells, cell, volume, second_moment, centroid=None):
    """Cell `cell` succeeded with these integrals: relative 1e-12, the
    centroid (where given) absolute 1e-12."""
    assert cells.status[cell].item() == CellStatus.SUCCESS
    assert cells.volume[cell].item() == pytest.approx(volume, rel=1e-12, abs=0)
    assert cells.second_moment[cell].item() == pytest.approx(second_moment, rel=1e-12, abs=0)
    if centroid is not None:
        np.testing.assert_allclose(cells.centroid[cell].cpu().numpy(), centroid, rtol=0, atol=1e-12)


def test_needle_cell_exact_float64(device, cells_impl):
    """test_tight_clusters' input for seed 1047518939: cell 59 is a needle
    (~1e-5 wide, ~0.1 long, volume 1.5e-11) of a cluster point. The paper's
    tetrahedra (feet of the seed on far planes) cancel on it (their absolute
    volumes sum to ~3e6 times the cell's) and plain float64 is 7e-10 off; the
    cell must be flagged ILL_CONDITIONED and recomputed in double-double.
    Reference values: exact rational arithmetic (Fractions) over the cell's
    half-spaces; Qhull's volume is 1.7e-11 off. (Only with all 320 points:
    the cell alone with its 15 facet neighbours comes out right even without
    the recomputation.)"""
    points = seeded_tight_clusters(1047518939, 1e-5, 59,
                                   [0.35760402697859545, 0.8997942077279265, 0.6421634167118496])
    cells = run(points.to(device), UNIT)
    assert_pinned_cell(cells, 59, 1.4992333652678265e-11, 1.8417640051644332e-14)
    check_global(cells, points.to(device), [box_of(points, UNIT)], torch.float64)


def test_float64_cell_at_nearly_concurrent_bisectors(device):
    """test_tight_clusters' input for seed 3321684543, spread 1e-5: cell 211, a
    large cell (volume 0.032, radius 0.76) next to a cluster of 40 points
    spread over ~1e-5, has 12 vertices where ~10 of the cluster's bisectors
    nearly meet (the sine of their angle down to 1.3e-10). Exact rational
    arithmetic (tests/oracles.py, exact_cell_oracle) agrees with the Qhull
    oracle to 2e-16. Cramer's rule on three nearly parallel bisectors loses
    the determinant to cancellation (the float64 cell 8e-11 off in volume and
    1.6e-10 in second moment, unflagged); with such planes solved relative to
    the first (core::intersect_planes) it is within 1e-15. The oracles are
    held to each other at 1e-13."""
    points = seeded_tight_clusters(3321684543, 1e-5, 211,
                                   [0.3885020495206787, 0.8110196492366557, 0.639860898022586])
    lohi = box_of(points, UNIT)
    exact = exact_cell_oracle(points.numpy(), 211, lohi)
    qhull = voronoi_cell_oracle(points.numpy(), 211, lohi)
    assert exact.volume == pytest.approx(qhull.volume, rel=1e-13, abs=0)
    assert exact.second_moment == pytest.approx(qhull.second_moment, rel=1e-13, abs=0)
    cells = run(points.to(device), UNIT)
    assert_pinned_cell(cells, 211, exact.volume, exact.second_moment, exact.centroid)


def test_float64_cell_at_nearly_parallel_far_bisectors(device, cells_impl, vertex_balls):
    """test_tight_clusters' input for seed 3627362118, spread 1e-6 (shown with
    every retry finished on the grid): cell 117 (volume 0.0059) has five
    faces on the bisectors of a cluster 0.38 away whose points lie within
    ~1e-6 of each other, their normals ~3e-6 apart. Cramer's rule on three
    of them (the determinant ~1e-11 |n|^3, its rounding error 5e-7 of it)
    puts a vertex 3e-7 off, across a fourth plane: the faces there join
    wrongly, the volume comes out 2.9e-11 low (the volumes sum to
    1 - 2.9e-11) and no flag catches it. By default the pass-wide escalation
    to double-double (another cell's BOUNDARY_ERROR) may reach this cell
    first and hide that. Reference values: exact rational arithmetic
    (exact_cell_oracle; Qhull agrees to 2e-18)."""
    points = seeded_tight_clusters(3627362118, 1e-6, 117,
                                   [0.1535408973827895, 0.43792968493351175, 0.7812599555814832])
    cells = run(points.to(device), UNIT)
    assert_pinned_cell(cells, 117, 0.005919962692627301, 0.00030368775329608363,
                       [0.09119880337270697, 0.25030488899203174, 0.7544930536055348])
    check_global(cells, points.to(device), [box_of(points, UNIT)], torch.float64)


def test_tight_cluster_cell_where_qhull_is_off(device, vertex_balls):
    """test_tight_clusters' input for seed 912262376, spread 1e-6: cell 62 of
    a cluster (volume 7.3e-19, ~1e-6 wide). Qhull's volume is 6.6e-8 off the
    exact one (rational arithmetic), beyond the tolerance of 1e-10, while
    torchvor's float64 cell is within 1e-15 of exact: check_against_oracle
    lets the exact oracle decide where Qhull disagrees."""
    points = seeded_tight_clusters(912262376, 1e-6, 62,
                                   [0.6403995042764254, 0.153386069545652, 0.3282359608740357])
    lohi = box_of(points, UNIT)
    exact = exact_cell_oracle(points.numpy(), 62, lohi)
    qhull = voronoi_cell_oracle(points.numpy(), 62, lohi)
    assert abs(qhull.volume / exact.volume - 1) > 1e-8  # why the exact oracle decides here
    cells = run(points.to(device), UNIT)
    assert_pinned_cell(cells, 62, exact.volume, exact.second_moment, exact.centroid)
    check_against_oracle(cells, points.to(device), lohi, [62], 1e-10)


def test_ill_conditioned_float32_cell_recomputed_in_float64(device, cells_impl):
    """Tight clusters (spread 1e-6, seed 25): cell 5's tetrahedra cancel
    beyond float32's resolution. Computed in float32 it is 2.8e-4 off the
    float64 computation of the same (float32-rounded) points; flagged
    ILL_CONDITIONED and recomputed in float64, it must match that to float32
    output rounding (up to 3e-6 on such clusters)."""
    gen = torch.Generator()
    gen.manual_seed(25)
    points = tight_clusters(gen, 1e-6).float()
    cells = run(points.to(device), UNIT)
    reference = run(points.double(), UNIT)
    assert cells.status[5].item() == CellStatus.SUCCESS
    assert cells.volume[5].item() == pytest.approx(reference.volume[5].item(), rel=1e-5, abs=0)
    assert cells.second_moment[5].item() == pytest.approx(reference.second_moment[5].item(), rel=1e-5, abs=0)


def fuzz_cell_neighbourhood(fuzz_seed, index, cell, max_n, dtype):
    """A float32 fuzz case's cell (tests/fuzz_cases.py): the 100 points nearest
    to point `cell` (itself first), float64 numpy of float32 values, and the
    case's box (lo, hi)."""
    import fuzz_cases

    case = fuzz_cases.make_case(fuzz_seed, index, max_n=max_n, dtype=dtype)
    assert case.dtype == torch.float32
    x = case.points
    near = np.argsort(((x - x[cell]) ** 2).sum(1), kind="stable")[:100]
    return x[near], (case.boxes[0, 0], case.boxes[0, 1])


@pytest.mark.parametrize("fuzz_seed, index, max_n, cell", [(34, 7, 200000, 17488), (34, 7, 200000, 7186),
                                                          (35, 7, 20000, 11611)])
def test_float32_cell_beside_close_pairs_keeps_its_radius(device, cells_impl, fuzz_seed, index, max_n, cell):
    """Close pairs 1-4 ulps apart (the fuzzer's cases; a cell among its 100
    nearest points): two neighbours at nearly the same distance in nearly the
    same direction have bisectors meeting at a sine of 3e-6 to 3e-5. Clipped
    in float32, the tolerance band around them let the cell keep a needle of
    no volume 2.3% to 31% past the exact cell's radius, the volume within
    3e-7. Such a cell must go to float64 (nearly_coincident_bisectors): its
    radius within 1e-3, its volume within 1e-4."""
    near, lohi = fuzz_cell_neighbourhood(fuzz_seed, index, cell, max_n, "float32")
    exact = voronoi_cell_oracle(near, 0, lohi)
    cells = run(torch.tensor(near, dtype=torch.float32, device=device), tuple(b.tolist() for b in lohi))
    assert cells.status[0].item() == CellStatus.SUCCESS
    assert cells.radius[0].item() == pytest.approx(exact.radius, rel=1e-3)
    assert cells.volume[0].item() == pytest.approx(exact.volume, rel=1e-4)


@pytest.mark.parametrize("fuzz_seed, index, cell", [(44, 4389, 2074), (44, 5379, 125794)])
def test_float32_slab_cell_on_a_wall_keeps_its_second_moment(device, cells_impl, fuzz_seed, index, cell):
    """A seed on a wall of a thin box (the fuzzer's cases): its cell is a slab
    whose tetrahedra from the seed's far feet cancel more in the second moment
    (weighted by |x|^2) than in the volume (4389: 69 against 13). Its float32
    second moment must stay within the volume's precision, or the cell go to
    float64 (the cancellation limit holds both)."""
    near, lohi = fuzz_cell_neighbourhood(fuzz_seed, index, cell, 1000000, "both")
    exact = exact_cell_oracle(near, 0, lohi)
    cells = run(torch.tensor(near, dtype=torch.float32, device=device), tuple(b.tolist() for b in lohi))
    assert cells.status[0].item() == CellStatus.SUCCESS
    assert cells.volume[0].item() == pytest.approx(exact.volume, rel=6e-5)
    assert cells.second_moment[0].item() == pytest.approx(exact.second_moment, rel=6e-5)


@pytest.fixture(scope="module")
def close_pairs_program(cpp_program):
    return cpp_program("close_pairs")


@pytest.mark.parametrize("pair_seed", [1, 2])
def test_nearly_coincident_bisectors_against_their_geometry(close_pairs_program, pair_seed):
    """The float32 close-pair test (core::nearly_coincident_bisectors) on
    200K pairs drawn near its limits, sines down to 1e-7, scales 1e-15 to
    1e4, against the double geometry of the same float32 points
    (tests/close_pairs.cpp): every pair whose bisectors meet at a sine under
    1e-3 along a line within twice the cell's radius is flagged, and none
    whose line lies beyond 2.5 radii or whose sine is over 1e-3."""
    result = subprocess.run([str(close_pairs_program), str(pair_seed), "200000"], capture_output=True, text=True,
                            timeout=600)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]


@pytest.mark.parametrize("pair_seed", [1, 2])
def test_nearly_parallel_bisectors_against_their_geometry(close_pairs_program, pair_seed):
    """voronoi_graph's float64 test of two neighbours' nearly parallel
    bisectors (core::nearly_parallel_bisectors: the faces' split there is
    not resolved, whatever faces the rounding left) on 200K double pairs,
    sines 1e-11 to 4e-7, scales 1e-100 to 1e100, against their geometry in
    long double (tests/close_pairs.cpp): every pair at a sine under 1e-7
    whose line lies within twice the cell's radius is flagged, and none
    whose line lies beyond 2.5 radii or whose sine is over 1e-7."""
    result = subprocess.run([str(close_pairs_program), str(pair_seed), "200000", "double"], capture_output=True,
                            text=True, timeout=600)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
