"""torchvor.voronoi against a per-cell scipy/Qhull half-space oracle (tests/oracles.py),
plus exact identities (sum of volumes, first moments, lattices).

Inputs are drawn fresh per test (``gen`` / ``seed`` fixtures; the seed is
printed on failure) on the CPU in float64, rounded to the tested dtype, and
moved to ``device``. The oracle always sees exactly the values torchvor saw.
"""
from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
import torch

import torchvor
from torchvor import CellStatus, samples

from oracles import brute_force_knn, exact_cell_oracle, voronoi_cell_oracle

has_cuda = torch.cuda.is_available()
UNIT = ([0.0, 0.0, 0.0], [1.0, 1.0, 1.0])
VORONOI_FIELDS = ("volume", "centroid", "second_moment", "status", "neighbors")

# tolerances relative to each cell (volume, second moment) or its size (centroid)
RTOL = {torch.float64: 1e-10, torch.float32: 1e-4}
# sums over all cells, relative to the box volume (and box centre)
SUM_RTOL = {torch.float64: 1e-11, torch.float32: 1e-5}


def rand(n, gen, dtype, device, lo=0.0, hi=1.0):
    lo = torch.as_tensor(lo, dtype=torch.float64)
    hi = torch.as_tensor(hi, dtype=torch.float64)
    return (torch.rand(n, 3, generator=gen, dtype=torch.float64) * (hi - lo) + lo).to(dtype).to(device)


def ragged_batch(sizes, device):
    return torch.repeat_interleave(torch.arange(len(sizes)), torch.tensor(sizes)).to(device)


def assert_same_cells(cells, expected, dtype):
    """The same statuses and neighbour counts, and the same integrals up to
    rounding (relative, or absolute at the scale of the mean cell)."""
    assert torch.equal(expected.neighbors, cells.neighbors)
    assert_same_integrals(cells, expected, dtype)


def assert_same_integrals(cells, expected, dtype, offset=0.0):
    """The same statuses, and the same integrals up to rounding, whatever
    neighbours the cells counted (assert_same_cells without them). Centroids
    near `offset` may also differ by the rounding of coordinates there."""
    assert torch.equal(expected.status, cells.status)
    rtol = RTOL[dtype]
    size = float(expected.volume.double().mean()) ** (1 / 3)
    torch.testing.assert_close(cells.volume, expected.volume, rtol=rtol, atol=rtol * size ** 3)
    torch.testing.assert_close(cells.second_moment, expected.second_moment, rtol=rtol, atol=rtol * size ** 5)
    coordinate_ulp = float(torch.finfo(dtype).eps) * abs(offset)
    torch.testing.assert_close(cells.centroid, expected.centroid, rtol=0, atol=rtol * size + 2 * coordinate_ulp)


def assert_same_cloud(part, alone, dtype):
    """A batch element's cells (`part`) against its cloud computed alone. In
    float64 they are equal bit for bit. In float32 a cell's last pass can
    differ: the first pass's k is the pilot's, which follows the whole batch,
    so a cell may succeed in a thread cell of the first tier (vertices held
    to 18 mantissa bits, CompactTriangles) in one run and after a retry of a
    higher tier (full float32 vertices) in the other; then the integrals
    agree up to rounding and the neighbour counts within one (the radius of
    security comes from the vertices)."""
    if dtype == torch.float64:
        for a, b in zip(part, alone):
            assert torch.equal(a, b)
        return
    assert_same_integrals(part, alone, dtype)
    assert int((part.neighbors - alone.neighbors).abs().max()) <= 1


def point_set(kind, gen, seed, dtype, device):
    """The point sets that tests comparing two ways of computing the cells
    run on: 3000 uniform, clustered or perturbed-grid points, a 10^3
    lattice, or 1000 uniform points and 300 exact copies of some of them."""
    if kind == "clustered":
        return samples.clustered(3000, seed=seed, dtype=dtype).to(device)
    if kind == "lattice":
        return samples.lattice(10, dtype=dtype).to(device)
    if kind == "perturbed":
        return samples.perturbed_grid(3000, seed=seed, dtype=dtype).to(device)
    if kind == "duplicates":
        points = rand(1000, gen, dtype, device)
        return torch.cat([points, points[:300]])
    return rand(3000, gen, dtype, device)


def near_faces(n, gen, dtype, device):
    """n uniform points, each pressed against one face of the unit box (within
    0.02 of it, some near edges and corners), and every tenth exactly on it."""
    points = torch.rand(n, 3, generator=gen, dtype=torch.float64)
    rows = torch.arange(n)
    axis = torch.randint(0, 3, (n,), generator=gen)
    depth = 0.02 * points[rows, axis]
    depth[::10] = 0.0
    upper = torch.rand(n, generator=gen) < 0.5
    points[rows, axis] = torch.where(upper, 1.0 - depth, depth)
    return points.to(dtype).to(device)


def box_of(points, box):
    """(lo, hi) float64 numpy, as torchvor.voronoi interprets `box` (no batch)."""
    if box is None:
        p = points.detach().cpu().double().numpy()
        return p.min(0), p.max(0)
    if isinstance(box, torch.Tensor):
        b = box.detach().cpu().double().numpy().reshape(2, 3)
        return b[0], b[1]
    # (lo, hi) sequences, rounded to the points' dtype as torchvor does
    lo, hi = (torch.as_tensor(b, dtype=points.dtype).double().numpy() for b in box)
    return lo, hi


def pick_cells(points, count, gen, lo, hi):
    """`count` random cells plus the cells whose seeds are nearest the box faces
    (those are clipped by the box, and some may lie on it)."""
    n = points.shape[0]
    if n <= count:
        return np.arange(n)
    p = points.detach().cpu().double().numpy()
    gap = np.minimum(p - lo, hi - p).min(1)
    near_face = np.argsort(gap, kind="stable")[: count // 4]
    rnd = torch.randperm(n, generator=gen)[: count - len(near_face)].numpy()
    return np.unique(np.concatenate([near_face, rnd]))


def check_against_oracle(cells, points, box, subset, rtol, *, tag="", conditioning=0.0):
    """Compare cells `subset` with the Qhull oracle (box = (lo, hi) numpy).
    Where a cell is outside the tolerance of Qhull's, the exact oracle
    (rational arithmetic, exact_cell_oracle) decides: Qhull's own error
    reaches 7e-8 of the volume on cells ~1e-6 wide (tight clusters, where
    torchvor's float64 cell agreed with the exact one to 7e-16).

    `conditioning` > 0 adds, for sliver cells whose faces are fixed only to the
    dtype's resolution, an absolute volume tolerance of conditioning * eps * R * A
    (R: cell radius about the seed, A: cell surface area), carried over to the
    centroid (times R / V) and the second moment (times R^2)."""
    lo, hi = box
    p = points.detach().cpu().double().numpy()
    vol = cells.volume.detach().cpu().double().numpy()
    cen = cells.centroid.detach().cpu().double().numpy()
    m2 = cells.second_moment.detach().cpu().double().numpy()
    status = cells.status.cpu().numpy()

    def mismatch(i, ref, where):
        """What is outside the tolerance of `ref` (None: nothing)."""
        size = max(ref.radius, ref.volume ** (1 / 3))
        slack = 0.0
        if conditioning:
            eps = float(torch.finfo(cells.volume.dtype).eps)
            slack = conditioning * eps * ref.radius * ref.area
        if abs(vol[i] - ref.volume) > rtol * ref.volume + slack:
            return f"{where}: volume {vol[i]!r} vs oracle {ref.volume!r} (rel {abs(vol[i] / ref.volume - 1):.2e})"
        err = np.abs(cen[i] - ref.centroid).max()
        # plus the rounding of an absolute coordinate to the output dtype (large offsets)
        ulp = np.abs(ref.centroid).max() * float(torch.finfo(cells.centroid.dtype).eps)
        if err > rtol * size + ulp + slack * ref.radius / ref.volume:
            return (f"{where}: centroid {cen[i].tolist()} vs oracle {ref.centroid.tolist()} "
                    f"(err {err:.2e}, size {size:.2e})")
        if abs(m2[i] - ref.second_moment) > rtol * ref.second_moment + slack * ref.radius ** 2:
            return (f"{where}: second moment {m2[i]!r} vs oracle {ref.second_moment!r} "
                    f"(rel {abs(m2[i] / ref.second_moment - 1):.2e})")
        return None

    for i in subset:
        i = int(i)
        ref = voronoi_cell_oracle(p, i, (lo, hi))
        where = f"{tag} cell {i} (seed {p[i].tolist()})"
        if ref.duplicate:
            assert status[i] == CellStatus.DUPLICATE, f"{where}: duplicate, status {status[i]}"
            assert vol[i] == 0 and m2[i] == 0, f"{where}: duplicate with volume {vol[i]}, moment {m2[i]}"
            np.testing.assert_array_equal(cen[i], p[i], err_msg=f"{where}: duplicate centroid")
            continue
        assert status[i] == CellStatus.SUCCESS, f"{where}: status {status[i]}"
        against_qhull = mismatch(i, ref, where)
        if against_qhull is not None:
            against_exact = mismatch(i, exact_cell_oracle(p, i, (lo, hi)), where + " (exact oracle)")
            assert against_exact is None, f"{against_exact}; Qhull: {against_qhull}"


def check_global(cells, points, boxes, dtype, batch=None):
    """Statuses, no NaN/poison left, sum of volumes = box volume and
    sum(volume * centroid) = box volume * box centre, per cloud."""
    n = points.shape[0]
    assert cells.volume.shape == (n,) and cells.centroid.shape == (n, 3)
    assert cells.second_moment.shape == (n,) and cells.status.shape == (n,) and cells.neighbors.shape == (n,)
    assert cells.volume.dtype == dtype and cells.centroid.dtype == dtype and cells.second_moment.dtype == dtype
    assert cells.status.dtype == torch.int8 and cells.neighbors.dtype == torch.int32
    for t in cells:
        assert t.device == points.device
    status = cells.status.cpu()
    ok = (status == CellStatus.SUCCESS) | (status == CellStatus.DUPLICATE)
    assert ok.all(), f"failed cells: {torch.nonzero(~ok).flatten().tolist()[:20]}, status {status[~ok].unique()}"
    vol = cells.volume.cpu().double()
    cen = cells.centroid.cpu().double()
    m2 = cells.second_moment.cpu().double()
    for name, t in (("volume", vol), ("centroid", cen), ("second_moment", m2)):
        assert torch.isfinite(t).all(), f"non-finite {name} in successful cells"
    assert (vol >= 0).all() and (m2 >= 0).all()
    assert (cells.neighbors.cpu() >= 0).all()
    dup = status == CellStatus.DUPLICATE
    if dup.any():
        assert (vol[dup] == 0).all() and (m2[dup] == 0).all()
        assert torch.equal(cen[dup], points.cpu().double()[dup])
    b = torch.zeros(n, dtype=torch.long) if batch is None else batch.cpu()
    for k, (lo, hi) in enumerate(boxes):
        mine = b == k
        if not mine.any():
            continue
        box_volume = float(np.prod(hi - lo))
        centre = torch.as_tensor((lo + hi) / 2)
        total = vol[mine].sum().item()
        assert abs(total - box_volume) <= SUM_RTOL[dtype] * box_volume, (
            f"cloud {k}: sum of volumes {total!r} != box volume {box_volume!r}")
        moment = (vol[mine, None] * cen[mine]).sum(0)
        size = float(np.max(hi - lo))
        err = (moment - box_volume * centre).abs().max().item()
        # relative to the box size, plus the rounding of absolute centroids (offsets)
        eps = float(torch.finfo(dtype).eps)
        tol = box_volume * (10 * SUM_RTOL[dtype] * size + 4 * eps * float(centre.abs().max()))
        assert err <= tol, (
            f"cloud {k}: sum(volume * centroid) {moment.tolist()} != box volume * centre "
            f"{(box_volume * centre).tolist()}")


@pytest.fixture(params=["thread", "cooperative"])
def cells_impl(request, monkeypatch):
    """Which implementation clips the cells (TORCHVOR_CELLS): one thread per
    cell (ConvexCell, the CPU's default) or a group of lanes per cell
    (CooperativeCell: a warp on CUDA, its default; one lane on the CPU). The
    tests that take this fixture run both on every device."""
    monkeypatch.setenv("TORCHVOR_CELLS", request.param)
    return request.param


@pytest.fixture(params=["past 256", "every retry"])
def vertex_balls(request, monkeypatch):
    """The most neighbours a retry asks for (TORCHVOR_VERTEX_BALLS_K): cells
    that need more are finished on the grid by the empty balls of their
    vertices, from a list of that many. By default 256; with 1, every cell a
    retry takes is finished so, from its nearest neighbour alone. The tests
    that take this fixture run both."""
    if request.param == "every retry":
        monkeypatch.setenv("TORCHVOR_VERTEX_BALLS_K", "1")
    return request.param


def run(points, box=None, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a RuntimeWarning (failed cell) fails the test
        return torchvor.voronoi(points, box, **kwargs)


# ----------------------------------------------------------- random point sets


def test_oracle_check_falls_back_to_the_exact_oracle_and_still_fails(gen):
    """check_against_oracle's arbiter: a cell off Qhull's by more than the
    tolerance is checked against the exact oracle, which must fail it too
    (here: one volume 1e-6 too large)."""
    points = torch.rand(60, 3, generator=gen, dtype=torch.float64)
    cells = run(points, UNIT)
    check_against_oracle(cells, points, box_of(points, UNIT), [7], 1e-10)
    wrong = cells._replace(volume=cells.volume.clone())
    wrong.volume[7] *= 1 + 1e-6
    with pytest.raises(AssertionError, match=r"exact oracle.*Qhull"):
        check_against_oracle(wrong, points, box_of(points, UNIT), [7], 1e-10)


@pytest.mark.parametrize("kind", ["white", "clustered", "near_faces"])
def test_random_vs_oracle(device, dtype, gen, seed, kind, cells_impl):
    if kind == "white":
        points = rand(1000, gen, dtype, device)
    elif kind == "near_faces":  # seeds near or on the box faces, edges and corners
        points = torch.cat([rand(300, gen, dtype, device), near_faces(700, gen, dtype, device)])
    else:
        points = samples.clustered(1000, clusters=12, spread=0.03, seed=seed, dtype=torch.float64)
        points = points.to(dtype).to(device)
    for box in (UNIT, None):
        cells = run(points, box)
        lohi = box_of(points, box)
        check_global(cells, points, [lohi], dtype)
        check_against_oracle(cells, points, lohi, pick_cells(points, 60, gen, *lohi), RTOL[dtype],
                             tag=f"box={box}")


@pytest.mark.parametrize("kind", ["white", "clustered", "lattice", "duplicates", "small_k"])
def test_cooperative_cells_match_thread_cells(monkeypatch, device, dtype, gen, seed, kind):
    """The two implementations of a cell (one thread, or a group of lanes:
    csrc/core/cooperative_cell.h) take the same decisions: the same statuses
    and neighbour counts, the same integrals up to rounding (the lanes sum
    the tetrahedra in another order). On the CPU a thread per cell runs the
    AVX2+FMA loop where the CPU has it, and the lanes the baseline loop: fused
    and separate roundings moved the security radius by one neighbour in ~6%
    of clustered sets, so both run the baseline loop here. Float32 thread
    cells keep full triangle records here (TORCHVOR_THREAD_TRIANGLES=full):
    compact ones round their vertices, which moves some radii of security as
    well (test_compact_triangles_match_full)."""
    monkeypatch.setenv("TORCHVOR_CPU_ISA", "baseline")
    monkeypatch.setenv("TORCHVOR_THREAD_TRIANGLES", "full")
    points = point_set(kind, gen, seed, dtype, device)
    k = 4 if kind == "small_k" else None  # small_k: every cell retried, the later passes too
    results = {}
    for impl in ("thread", "cooperative"):
        monkeypatch.setenv("TORCHVOR_CELLS", impl)
        results[impl] = torchvor.voronoi(points, UNIT, k=k)
    thread, coop = results["thread"], results["cooperative"]
    check_global(coop, points, [box_of(points, UNIT)], dtype)
    assert_same_cells(coop, thread, dtype)


@pytest.mark.parametrize("kind", ["white", "clustered", "lattice", "perturbed", "duplicates", "batch", "k6",
                                  "near_faces"])
def test_tetrahedron_start_matches_box_start(monkeypatch, device, dtype, gen, seed, kind):
    """A thread cell starts from the tetrahedron of four of its first
    neighbours' bisectors where they surround the seed inside the box, else
    from the box (csrc/core/convex_cell.h, start_tetrahedron; warp cells
    always start from the box). TORCHVOR_CELL_START=box forces the box: the
    same cells, up to rounding, with the same statuses and neighbour counts.
    On white noise some volumes differ in their last bits: the tetrahedra
    were used. Lattices (flat first neighbours), most seeds near the box
    (near_faces: pressed against the faces, or on them), duplicates, batches
    and k < 7 (no tetrahedron) take the box."""
    monkeypatch.setenv("TORCHVOR_CELLS", "thread")  # every pass, on either device
    batch, box, k = None, UNIT, 6 if kind == "k6" else None
    if kind == "batch":
        batch = ragged_batch([1500, 0, 2, 900], device)
        points = rand(2402, gen, dtype, device)
        box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]] * 4, dtype=dtype, device=device)
    elif kind == "near_faces":
        points = torch.cat([rand(1000, gen, dtype, device), near_faces(2000, gen, dtype, device)])
    else:
        points = point_set(kind, gen, seed, dtype, device)
    results = {}
    for start in ("box", "tetrahedron"):
        monkeypatch.setenv("TORCHVOR_CELL_START", start)
        results[start] = torchvor.voronoi(points, box, batch=batch, k=k)
    from_box, from_tetrahedron = results["box"], results["tetrahedron"]
    boxes = [box_of(points, UNIT)] * (1 if batch is None else 4)
    check_global(from_tetrahedron, points, boxes, dtype, batch=batch)
    assert_same_cells(from_tetrahedron, from_box, dtype)
    if kind == "white":
        assert not torch.equal(from_box.volume, from_tetrahedron.volume)


@pytest.mark.parametrize("kind", ["white", "clustered", "lattice", "perturbed", "duplicates", "near_faces",
                                  "offset", "small", "large"])
def test_compact_triangles_match_full(monkeypatch, device, gen, seed, kind):
    """Float32 thread cells of up to 32 planes keep their triangles in 12
    bytes (csrc/core/convex_cell.h, CompactTriangles: coordinates rounded to
    18 mantissa bits, the plane ids in the 5 bits that frees).
    TORCHVOR_THREAD_TRIANGLES=full keeps 16-byte records. Both meet the
    oracle, with the same statuses and the same integrals up to rounding, at
    any offset and scale (small: a box of 1e-6, large: of 1e8 at -3e8). The
    radius of security comes from the rounded vertices, so a neighbour count
    may differ by one, rarely (by two where a neighbour has an exact copy).
    (The oracle's Qhull works to absolute tolerances: not at those two
    scales.)"""
    monkeypatch.setenv("TORCHVOR_CELLS", "thread")  # every pass, on either device
    dtype = torch.float32
    box, lo = UNIT, 0.0
    if kind == "near_faces":
        points = torch.cat([rand(1000, gen, dtype, device), near_faces(2000, gen, dtype, device)])
    elif kind in ("offset", "small", "large"):
        lo, size = {"offset": (1e4, 1.0), "small": (0.0, 1e-6), "large": (-3e8, 1e8)}[kind]
        box = ([lo] * 3, [lo + size] * 3)
        points = rand(500 if kind == "offset" else 3000, gen, dtype, device, lo, lo + size)
    else:
        points = point_set(kind, gen, seed, dtype, device)
    results = {}
    for triangles in ("full", "compact"):
        monkeypatch.setenv("TORCHVOR_THREAD_TRIANGLES", triangles)
        results[triangles] = torchvor.voronoi(points, box)
    full, compact = results["full"], results["compact"]
    lohi = box_of(points, box)
    check_global(compact, points, [lohi], dtype)
    if kind not in ("small", "large"):
        check_against_oracle(compact, points, lohi, pick_cells(points, 40, gen, *lohi), RTOL[dtype])
    assert_same_integrals(compact, full, dtype, offset=lo)
    differ = (compact.neighbors - full.neighbors).abs()
    # A neighbour and its exact copy come in a row, and the copy is skipped
    # but counted: where one run stops at the first of the pair and the
    # other clips it, the count moves by two (TORCHVOR_TEST_SEED=9713905,
    # duplicates: 42 with full triangles, 44 with compact ones).
    most = 2 if kind == "duplicates" else 1
    assert differ.max() <= most and (differ > 0).float().mean() < 0.01
    if kind == "white":
        assert not torch.equal(full.volume, compact.volume)  # the compact form was used


@pytest.mark.parametrize("k", [4, None])
def test_cooperative_knn_in_voronoi(monkeypatch, device, dtype, gen, k):
    """The passes' neighbour searches by a thread or a group of lanes per
    query (TORCHVOR_KNN) find the same neighbours: equal cells, bit for bit.
    k=4 retries every cell; k=None adds the pilot."""
    points = rand(3000, gen, dtype, device)
    results = {}
    for impl in ("thread", "cooperative"):
        monkeypatch.setenv("TORCHVOR_KNN", impl)
        results[impl] = torchvor.voronoi(points, UNIT, k=k)
    for name in ("volume", "centroid", "second_moment", "status", "neighbors"):
        assert torch.equal(getattr(results["thread"], name), getattr(results["cooperative"], name)), name


@pytest.mark.parametrize("kind", ["white", "clustered"])
def test_cpu_baseline_loop_vs_oracle(monkeypatch, dtype, gen, seed, kind):
    """On CPUs with AVX2 and FMA the CPU clips cells with a copy of its loop
    compiled for them (csrc/cpu/isa.h), which every other CPU test exercises
    there. TORCHVOR_CPU_ISA=baseline forces the baseline loop: it must meet the
    same oracle and agree with the other copy up to rounding."""
    if kind == "white":
        points = rand(1000, gen, dtype, "cpu")
    else:
        points = samples.clustered(1000, clusters=12, spread=0.03, seed=seed, dtype=torch.float64).to(dtype)
    best = run(points, UNIT)
    monkeypatch.setenv("TORCHVOR_CPU_ISA", "baseline")
    assert torch.ops.torchvor.cpu_isa() == "baseline"
    baseline = run(points, UNIT)
    lohi = box_of(points, UNIT)
    check_global(baseline, points, [lohi], dtype)
    check_against_oracle(baseline, points, lohi, pick_cells(points, 60, gen, *lohi), RTOL[dtype])
    assert torch.equal(baseline.status, best.status)
    size = float(best.volume.double().mean()) ** (1 / 3)
    torch.testing.assert_close(baseline.volume, best.volume, rtol=RTOL[dtype], atol=0)
    torch.testing.assert_close(baseline.second_moment, best.second_moment, rtol=RTOL[dtype], atol=0)
    torch.testing.assert_close(baseline.centroid, best.centroid, rtol=0, atol=RTOL[dtype] * size)


def test_neighbors_radius_of_security(monkeypatch, device, gen):
    """`neighbors` counts the nearest neighbours a cell used: every true Voronoi
    neighbour is among them, and the next one is beyond twice the cell radius.
    (Of the cells that the radius of security finishes: here all of them, as
    no retry finishes its cells by their vertices' balls.)"""
    monkeypatch.setenv("TORCHVOR_VERTEX_BALLS_K", str(10 ** 9))
    points = rand(600, gen, torch.float64, device)
    cells = run(points, UNIT)
    p = points.cpu().numpy()
    _, order = brute_force_knn(points.cpu(), len(p) - 1)  # full (distance, index) order
    used = cells.neighbors.cpu().numpy()
    box = (np.zeros(3), np.ones(3))
    for i in pick_cells(points, 60, gen, *box):
        ref = voronoi_cell_oracle(p, int(i), box)
        rank = {int(j): r for r, j in enumerate(order[i])}
        needed = max(rank[int(j)] for j in ref.facet_neighbors) + 1
        assert used[i] >= needed, f"cell {i}: used {used[i]} neighbours, its facets need {needed}"
        if used[i] < len(p) - 1:
            nxt = order[i, used[i]]
            d = np.linalg.norm(p[nxt] - p[i])
            assert d >= 2 * ref.radius * (1 - 1e-9), (
                f"cell {i}: stopped at {used[i]} neighbours but the next one (dist {d}) is within "
                f"2 x cell radius {ref.radius}")


def test_sums_larger_random(device, dtype, gen):
    """Global identities on a larger cloud (no oracle)."""
    points = rand(5000, gen, dtype, device)
    cells = run(points, UNIT)
    check_global(cells, points, [box_of(points, UNIT)], dtype)


# --------------------------------------------------------------------- lattices


def lattice_expectations(cells, points, edge, dtype, rtol):
    vol = cells.volume.cpu().double()
    cen = cells.centroid.cpu().double()
    m2 = cells.second_moment.cpu().double()
    p = points.cpu().double()
    a = np.asarray(edge, dtype=np.float64)
    volume = float(np.prod(a))
    moment = volume * float((a ** 2).sum()) / 12  # integral of |x - centre|^2 over a box
    assert (cells.status.cpu() == CellStatus.SUCCESS).all()
    err = (vol - volume).abs().max().item()
    assert err <= rtol * volume, f"lattice volumes off by {err:.3e} (cell volume {volume:.3e})"
    err = (cen - p).abs().max().item()
    assert err <= rtol * a.max(), f"lattice centroids off by {err:.3e} (cell size {a.max():.3e})"
    err = (m2 - moment).abs().max().item()
    assert err <= rtol * moment, f"lattice second moments off by {err:.3e} (expected {moment:.3e})"


@pytest.mark.parametrize("m", [3, 7, 10])
def test_lattice_exact(device, dtype, m, cells_impl):
    """samples.lattice(m): every cell is a cube of volume 1/m^3 centred on its point."""
    points = samples.lattice(m, dtype=dtype).to(device)
    cells = run(points, UNIT)
    check_global(cells, points, [box_of(points, UNIT)], dtype)
    lattice_expectations(cells, points, [1 / m] * 3, dtype, {torch.float64: 1e-12, torch.float32: 1e-5}[dtype])


def test_lattice_scaled_offset_float64(device, gen):
    """Lattice scaled by 1e-3 and moved to 1e4: relative to the cell size the
    inputs carry ~1e-8 rounding, so the cube volumes hold to ~1e-7 and the
    oracle (same rounded inputs) to 1e-10."""
    m = 6
    points = (samples.lattice(m) * 1e-3 + 1e4).to(device)
    box = ([1e4] * 3, [1e4 + 1e-3] * 3)
    cells = run(points, box)
    lohi = box_of(points, box)
    check_global(cells, points, [lohi], torch.float64)
    lattice_expectations(cells, points, [1e-3 / m] * 3, torch.float64, 1e-7)
    check_against_oracle(cells, points, lohi, pick_cells(points, 40, gen, *lohi), 1e-10)


def test_lattice_flat_box(device, dtype, cells_impl):
    """Lattice squeezed into a 1 x 1 x 0.001 box: flat cells of 1/m x 1/m x 0.001/m."""
    m = 6
    scale = torch.tensor([1.0, 1.0, 1e-3], dtype=torch.float64)
    points = (samples.lattice(m) * scale).to(dtype).to(device)
    box = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1e-3]], dtype=dtype, device=device)
    cells = run(points, box)
    check_global(cells, points, [box_of(points, box)], dtype)
    lattice_expectations(cells, points, [1 / m, 1 / m, 1e-3 / m], dtype,
                         {torch.float64: 1e-10, torch.float32: 1e-4}[dtype])


def test_lattice_single_layer(device, dtype):
    """One layer of an m x m grid in a cube: square columns spanning the box."""
    m = 8
    axis = (torch.arange(m, dtype=torch.float64) + 0.5) / m
    y, x = torch.meshgrid(axis, axis, indexing="ij")
    points = torch.stack([x.flatten(), y.flatten(), torch.full((m * m,), 0.5, dtype=torch.float64)], 1)
    points = points.to(dtype).to(device)
    cells = run(points, UNIT)
    lattice_expectations(cells, points, [1 / m, 1 / m, 1.0], dtype,
                         {torch.float64: 1e-12, torch.float32: 1e-5}[dtype])


# ---------------------------------------------------------- awkward geometries


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
    eps * R: float32 is compared with a conditioning allowance (measured errors
    reach ~70 eps R A, i.e. up to 35% of a 5e-11 needle's volume)."""
    points = tight_clusters(gen, spread).to(dtype).to(device)
    cells = run(points, UNIT)
    lohi = box_of(points, UNIT)
    check_global(cells, points, [lohi], dtype)
    check_against_oracle(cells, points, lohi, pick_cells(points, 30, gen, *lohi), RTOL[dtype],
                         conditioning=256.0 if dtype == torch.float32 else 0.0)


def test_isolated_point_and_tight_cluster_regression(device, cells_impl):
    """Minimal float64 case found by test_tight_clusters: a point 0.5 away from a
    cluster of 5 points spread over ~1e-6. Its cell is cut by 5 nearly identical
    bisectors; it came back BOUNDARY_ERROR (NaN) after every recovery pass."""
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
    """Regression found by test_tight_clusters (seed 1047518939): cell 59 is a
    needle (~1e-5 wide, ~0.1 long, volume 1.5e-11) of a cluster point. The
    paper's tetrahedra (feet of the seed on far planes) cancel on it (their
    absolute volumes sum to ~3e6 times the cell's) and float64 came out 7e-10
    off; the cell must be flagged ILL_CONDITIONED and recomputed in
    double-double. Reference values: exact rational arithmetic (Fractions) over
    the cell's half-spaces; Qhull's volume is 1.7e-11 off. (Only with all 320
    points: the cell alone with its 15 facet neighbours comes out right even
    without the recomputation.)"""
    points = seeded_tight_clusters(1047518939, 1e-5, 59,
                                   [0.35760402697859545, 0.8997942077279265, 0.6421634167118496])
    cells = run(points.to(device), UNIT)
    assert_pinned_cell(cells, 59, 1.4992333652678265e-11, 1.8417640051644332e-14)
    check_global(cells, points.to(device), [box_of(points, UNIT)], torch.float64)


def test_float64_cell_at_nearly_concurrent_bisectors(device):
    """Found by test_tight_clusters (seed 3321684543, spread 1e-5): cell 211, a
    large cell (volume 0.032, radius 0.76) next to a cluster of 40 points
    spread over ~1e-5, has 12 vertices where ~10 of the cluster's bisectors
    nearly meet (the sine of their angle down to 1.3e-10). Exact rational
    arithmetic (tests/oracles.py, exact_cell_oracle) agrees with the Qhull
    oracle to 2e-16; torchvor's float64 cell was 8e-11 off in volume and
    1.6e-10 in second moment, unflagged: Cramer's rule on three nearly
    parallel bisectors loses the determinant to cancellation. With such
    planes solved relative to the first (core::intersect_planes) it is within
    1e-15. The oracles are held to each other at 1e-13."""
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
    """Found by test_tight_clusters (seed 3627362118, spread 1e-6, every retry
    finished on the grid): cell 117 (volume 0.0059) has five faces on the
    bisectors of a cluster 0.38 away whose points lie within ~1e-6 of each
    other, their normals ~3e-6 apart. Cramer's rule on three of them (the
    determinant ~1e-11 |n|^3, its rounding error 5e-7 of it) put a vertex
    3e-7 off, across a fourth plane: the faces there joined wrongly, the
    volume came out 2.9e-11 low (the volumes summed to 1 - 2.9e-11) and no
    flag caught it. By default the pass-wide escalation to double-double
    (another cell's BOUNDARY_ERROR) reached this cell first and hid it.
    Reference values: exact rational arithmetic (exact_cell_oracle; Qhull
    agrees to 2e-18)."""
    points = seeded_tight_clusters(3627362118, 1e-6, 117,
                                   [0.1535408973827895, 0.43792968493351175, 0.7812599555814832])
    cells = run(points.to(device), UNIT)
    assert_pinned_cell(cells, 117, 0.005919962692627301, 0.00030368775329608363,
                       [0.09119880337270697, 0.25030488899203174, 0.7544930536055348])
    check_global(cells, points.to(device), [box_of(points, UNIT)], torch.float64)


def test_tight_cluster_cell_where_qhull_is_off(device, vertex_balls):
    """Found by test_tight_clusters (seed 912262376, spread 1e-6): cell 62 of a
    cluster (volume 7.3e-19, ~1e-6 wide). Qhull's volume is 6.6e-8 off the
    exact one (rational arithmetic), which failed the test at 1e-10 while
    torchvor's float64 cell was within 1e-15 of exact; check_against_oracle
    now lets the exact oracle decide where Qhull disagrees."""
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
    """Found by scanning tight clusters (spread 1e-6, seed 25): cell 5's
    tetrahedra cancel beyond float32's resolution. Computed in float32 it came
    out 2.8e-4 off the float64 computation of the same (float32-rounded)
    points; flagged ILL_CONDITIONED and recomputed in float64, it must match
    that to float32 output rounding (the scan's worst cell: 3e-6)."""
    gen = torch.Generator()
    gen.manual_seed(25)
    points = tight_clusters(gen, 1e-6).float()
    cells = run(points.to(device), UNIT)
    reference = run(points.double(), UNIT)
    assert cells.status[5].item() == CellStatus.SUCCESS
    assert cells.volume[5].item() == pytest.approx(reference.volume[5].item(), rel=1e-5, abs=0)
    assert cells.second_moment[5].item() == pytest.approx(reference.second_moment[5].item(), rel=1e-5, abs=0)


def test_flat_box_random(device, dtype, gen, cells_impl):
    lo, hi = [0.0, 0.0, 0.0], [1.0, 1.0, 1e-3]
    points = rand(600, gen, dtype, device, lo, hi)
    box = (lo, hi)
    cells = run(points, box)
    lohi = box_of(points, box)
    check_global(cells, points, [lohi], dtype)
    check_against_oracle(cells, points, lohi, pick_cells(points, 50, gen, *lohi), RTOL[dtype])


def test_nearly_planar_points(device, gen):
    """z = 0.5 + 1e-9 * noise: every cell is a column through the unit cube."""
    points = rand(400, gen, torch.float64, device)
    points[:, 2] = 0.5 + 1e-9 * (2 * torch.rand(400, generator=gen, dtype=torch.float64) - 1).to(device)
    cells = run(points, UNIT)
    lohi = box_of(points, UNIT)
    check_global(cells, points, [lohi], torch.float64)
    check_against_oracle(cells, points, lohi, pick_cells(points, 50, gen, *lohi), 1e-10)


def test_close_pairs(device, dtype, gen, cells_impl):
    """Points 1e-7 apart (float64) or a few ulps apart (float32)."""
    base = rand(300, gen, torch.float64, "cpu", 0.1, 0.9)
    direction = torch.nn.functional.normalize(torch.randn(20, 3, generator=gen, dtype=torch.float64), dim=1)
    gap = 1e-7 if dtype == torch.float64 else 3e-6
    partners = base[:20] + gap * direction
    points = torch.cat([base, partners]).to(dtype)
    assert ((points[:20] - points[300:]).abs().sum(1) > 0).all()  # not rounded together
    points = points.to(device)
    cells = run(points, UNIT)
    lohi = box_of(points, UNIT)
    check_global(cells, points, [lohi], dtype)
    subset = np.concatenate([np.arange(20), np.arange(300, 320), np.arange(20, 300, 15)])
    check_against_oracle(cells, points, lohi, subset, RTOL[dtype])


def test_points_on_box_boundary(device, dtype, gen):
    """Seeds on faces, edges and corners of the box."""
    points = rand(300, gen, dtype, device)
    points[:6, 0] = 0.0
    points[6:12, 1] = 1.0
    points[12:16, :2] = 0.0
    points[16] = torch.tensor([1.0, 1.0, 1.0])
    points[17] = torch.tensor([0.0, 1.0, 0.0])
    cells = run(points, UNIT)
    lohi = box_of(points, UNIT)
    check_global(cells, points, [lohi], dtype)
    check_against_oracle(cells, points, lohi, np.arange(40), RTOL[dtype])


@pytest.mark.parametrize("n", [1, 2, 5])
def test_few_points(device, dtype, gen, n, cells_impl):
    lo, hi = [-1.0, 0.0, 2.0], [1.0, 0.5, 5.0]
    points = rand(n, gen, dtype, device, lo, hi)
    cells = run(points, (lo, hi))
    lohi = box_of(points, (lo, hi))
    check_global(cells, points, [lohi], dtype)
    check_against_oracle(cells, points, lohi, range(n), RTOL[dtype])
    if n == 1:  # the whole box
        size = np.array(hi) - np.array(lo)
        assert cells.volume.item() == pytest.approx(float(np.prod(size)), rel=RTOL[dtype], abs=0)
        # a sum of signed tetrahedra: a few ulps of the coordinates (float32
        # once gave 8 ulps at z = 3.5, i.e. 1.9e-6, seed 3952057584)
        scale = float(np.abs(np.array(lo + hi)).max())
        torch.testing.assert_close(cells.centroid[0].cpu().double(),
                                   torch.tensor((np.array(lo) + np.array(hi)) / 2), rtol=0,
                                   atol=32 * torch.finfo(dtype).eps * scale)
        assert cells.neighbors.item() == 0


def test_two_points_halves(device, dtype):
    points = torch.tensor([[0.25, 0.5, 0.5], [0.75, 0.5, 0.5]], dtype=dtype, device=device)
    cells = run(points, UNIT)
    torch.testing.assert_close(cells.volume, torch.full((2,), 0.5, dtype=dtype, device=device))
    torch.testing.assert_close(cells.centroid, points)
    expected = 0.5 * (0.25 + 1 + 1) / 12  # box 0.5 x 1 x 1 about its centre
    torch.testing.assert_close(cells.second_moment, torch.full((2,), expected, dtype=dtype, device=device))


def test_single_point_bounding_box(device, dtype):
    """box=None with one point: a degenerate (zero-size) box, an empty cell."""
    points = torch.tensor([[0.3, 0.4, 0.5]], dtype=dtype, device=device)
    cells = run(points)
    assert cells.volume.item() == 0 and cells.second_moment.item() == 0
    assert torch.equal(cells.centroid, points)
    assert cells.status.item() in (CellStatus.SUCCESS, CellStatus.DUPLICATE)


def test_coplanar_points_bounding_box(device, dtype, gen):
    """box=None around coplanar points: the box is flat, every cell has volume 0,
    and no NaN comes out."""
    points = rand(50, gen, dtype, device)
    points[:, 2] = 0.5
    cells = run(points)
    assert (cells.volume == 0).all() and (cells.second_moment == 0).all()
    assert torch.isfinite(cells.centroid).all()
    assert ((cells.status == CellStatus.SUCCESS) | (cells.status == CellStatus.DUPLICATE)).all()


@pytest.mark.parametrize("box", [([-1.0, 0.0, 0.2], [2.0, 1.5, 0.7]), ([-100.0] * 3, [100.0] * 3)],
                         ids=["near", "huge"])
def test_explicit_larger_box(device, dtype, gen, box, vertex_balls):
    """A box well beyond the points: hull cells reach the box and need (almost) all
    points. In the huge box they are cones ~100 long whose faces come from points
    ~0.03 apart: float32 gets the conditioning allowance of test_tight_clusters
    (seen on CUDA: 4e-4 relative on a 6.3-volume cone, ~2 eps R A)."""
    points = rand(500, gen, dtype, device, 0.3, 0.6)
    cells = run(points, box)
    lohi = box_of(points, box)
    check_global(cells, points, [lohi], dtype)
    huge32 = dtype == torch.float32 and box[1][0] > 10
    check_against_oracle(cells, points, lohi, pick_cells(points, 40, gen, *lohi), RTOL[dtype],
                         conditioning=256.0 if huge32 else 0.0)


def test_quantised_offset_float32(device, gen):
    """float32 points at 1e4 with spread 0.01: coordinates snap to ~10 values per
    axis (ulp 1e-3), so the set is a degenerate lattice full of exact duplicates."""
    points = (1e4 + 0.01 * torch.rand(2000, 3, generator=gen, dtype=torch.float64)).float().to(device)
    assert len(points.unique(dim=0)) < 1500
    cells = run(points)
    lohi = box_of(points, None)
    check_global(cells, points, [lohi], torch.float32)
    check_against_oracle(cells, points, lohi, pick_cells(points, 40, gen, *lohi), RTOL[torch.float32])


def test_large_offset_box(device, dtype, gen):
    """Points and box near 1e4 (relative coordinates keep the precision)."""
    lo, hi = [1e4, 1e4, 1e4], [1e4 + 1, 1e4 + 1, 1e4 + 1]
    points = rand(500, gen, dtype, device, lo, hi)
    for box in ((lo, hi), None):
        cells = run(points, box)
        lohi = box_of(points, box)
        check_global(cells, points, [lohi], dtype)
        check_against_oracle(cells, points, lohi, pick_cells(points, 40, gen, *lohi), RTOL[dtype])


def test_duplicates(device, dtype, gen, cells_impl, vertex_balls):
    """Exact copies: the lowest index keeps the whole cell; later copies are
    DUPLICATE with volume 0, centroid = the point and second moment 0."""
    base = rand(200, gen, dtype, "cpu")
    copies = torch.randint(0, 200, (100,), generator=gen)
    points = torch.cat([base, base[copies], base[copies[:30]]])
    perm = torch.randperm(len(points), generator=gen)
    points = points[perm].to(device)
    cells = run(points, UNIT)
    lohi = box_of(points, UNIT)
    check_global(cells, points, [lohi], dtype)
    p = points.cpu()
    first = {}
    for i, row in enumerate(map(tuple, p.tolist())):
        first.setdefault(row, i)
    expected_dup = torch.tensor([first[tuple(r)] != i for i, r in enumerate(p.tolist())])
    status = cells.status.cpu()
    assert torch.equal(status == CellStatus.DUPLICATE, expected_dup)
    assert (status[~expected_dup] == CellStatus.SUCCESS).all()
    owners = sorted(set(first.values()))
    subset = np.concatenate([np.array(owners)[:: max(1, len(owners) // 40)],
                             torch.nonzero(expected_dup).flatten().numpy()[:20]])
    check_against_oracle(cells, points, lohi, subset, RTOL[dtype])


def test_duplicates_many(device, dtype, gen):
    """Many exact copies (each cloud: 300 points, half of them copied once, a
    sixth twice): global identities and no NaN in SUCCESS cells. A cell whose
    neighbours include two copies of one point is cut twice by the same plane."""
    for _ in range(12):
        base = rand(300, gen, dtype, "cpu")
        points = torch.cat([base, base[:150], base[:50]]).to(device)
        cells = run(points, UNIT)
        check_global(cells, points, [box_of(points, UNIT)], dtype)


@pytest.mark.parametrize("dtype_", [torch.float32, torch.float64], ids=["float32", "float64"])
def test_duplicate_neighbours_regression(device, dtype_):
    """Minimal case found by test_duplicates: points 0 and 3 are exact copies, so
    cell 1 is clipped twice by the same bisector. float32 gave volume NaN with
    status SUCCESS for cell 1 (silent poison)."""
    points = torch.tensor([
        [0.4551128149032593, 0.1561974287033081, 0.6241004467010498],
        [0.7751314640045166, 0.5810326933860779, 0.3472025990486145],
        [0.556449830532074, 0.1850108951330185, 0.41748368740081787],
        [0.4551128149032593, 0.1561974287033081, 0.6241004467010498],
        [0.7269694209098816, 0.7763248085975647, 0.6628854274749756]], dtype=torch.float32)
    points = points.to(dtype_).to(device)
    cells = run(points, UNIT)
    lohi = box_of(points, UNIT)
    check_global(cells, points, [lohi], dtype_)
    check_against_oracle(cells, points, lohi, range(5), RTOL[dtype_])


def test_inverse_order_in_ranges(device, dtype, gen, monkeypatch):
    """The inverse of the grid order is written in ranges of rows that fit
    the GPU's L2 cache (one range below ~6M points on an H100):
    TORCHVOR_TEST_SCATTER_BYTES=1000 splits 3000 points into 12 ranges, and
    the outputs, in the caller's rows, are those of one range bit for bit."""
    points = rand(3000, gen, dtype, device)
    reference = torchvor.voronoi(points, UNIT, on_failure="flag")
    monkeypatch.setenv("TORCHVOR_TEST_SCATTER_BYTES", "1000")
    cells = torchvor.voronoi(points, UNIT, on_failure="flag")
    for name in ("volume", "centroid", "second_moment", "status", "neighbors"):
        assert torch.equal(getattr(cells, name), getattr(reference, name)), name
    check_against_oracle(cells, points, (np.zeros(3), np.ones(3)), pick_cells(points, 20, gen, np.zeros(3), np.ones(3)),
                         RTOL[dtype])


def test_unwritten_cell_reads_not_computed(device, dtype, monkeypatch):
    """Only the statuses are poisoned before the passes; a cell that no pass
    writes (simulated: the first pass's result for one grid position is
    dropped and its record zeroed) must come out NOT_COMPUTED with NaN
    outputs and 0 neighbours, not as the zeroed record. On a jittered lattice
    every cell succeeds in the first pass, so no retry recomputes it."""
    gen = torch.Generator().manual_seed(0)
    axis = (torch.arange(4, dtype=torch.float64) + 0.5) / 4
    lattice = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    points = (lattice + 0.05 * (torch.rand(lattice.shape, generator=gen, dtype=torch.float64) - 0.5) / 4)
    points = points.to(dtype).to(device)
    monkeypatch.setenv("TORCHVOR_TEST_UNWRITTEN_CELL", "5")
    cells = torchvor.voronoi(points, UNIT, k=26, on_failure="flag")
    not_computed = cells.status == int(torchvor.CellStatus.NOT_COMPUTED)
    assert int(not_computed.sum()) == 1
    assert (cells.status[~not_computed] == int(torchvor.CellStatus.SUCCESS)).all()
    row = int(not_computed.nonzero()[0, 0])
    assert torch.isnan(cells.volume[row]) and torch.isnan(cells.centroid[row]).all()
    assert torch.isnan(cells.second_moment[row]) and int(cells.neighbors[row]) == 0
    assert torch.isfinite(cells.volume[~not_computed]).all()
    # the other cells are those of a run without the hook
    monkeypatch.delenv("TORCHVOR_TEST_UNWRITTEN_CELL")
    reference = torchvor.voronoi(points, UNIT, k=26, on_failure="flag")
    torch.testing.assert_close(cells.volume[~not_computed], reference.volume[~not_computed], rtol=0, atol=0)
    monkeypatch.setenv("TORCHVOR_TEST_UNWRITTEN_CELL", "5")
    with pytest.raises(RuntimeError, match=r"1 cell\(s\) could not be computed \(NOT_COMPUTED\)"):
        torchvor.voronoi(points, UNIT, k=26, on_failure="raise")


def test_all_points_identical(device, dtype, cells_impl):
    points = torch.full((5, 3), 0.25, dtype=dtype, device=device)
    cells = run(points, UNIT)
    assert cells.status.tolist() == [CellStatus.SUCCESS] + [CellStatus.DUPLICATE] * 4
    assert cells.volume[0].item() == pytest.approx(1.0)
    assert (cells.volume[1:] == 0).all()


# ------------------------------------------------------------------------ batch


def test_batch_per_cloud_boxes(device, dtype, gen, cells_impl, vertex_balls):
    sizes = [300, 1, 0, 150, 2]
    batch = ragged_batch(sizes, device)
    los = torch.tensor([[0.0, 0.0, 0.0], [5.0, 5.0, 5.0], [0.0, 0.0, 0.0], [-2.0, 1.0, 0.0], [0.0, 0.0, 10.0]],
                       dtype=torch.float64)
    his = los + torch.tensor([[1.0, 1.0, 1.0], [1.0, 2.0, 3.0], [1.0, 1.0, 1.0], [0.5, 4.0, 1.0], [1.0, 1.0, 0.1]],
                             dtype=torch.float64)
    parts = [rand(s, gen, torch.float64, "cpu", lo, hi) for s, lo, hi in zip(sizes, los, his)]
    points = torch.cat(parts).to(dtype).to(device)
    box = torch.stack([los, his], 1).to(dtype).to(device)  # (B, 2, 3)
    cells = run(points, box, batch=batch)
    boxes = [(b[0].cpu().double().numpy(), b[1].cpu().double().numpy()) for b in box]
    check_global(cells, points, boxes, dtype, batch)
    start = 0
    for s, lohi in zip(sizes, boxes):
        if s:
            part = points[start:start + s]
            sub = run(part, torch.stack([torch.as_tensor(lohi[0]), torch.as_tensor(lohi[1])]).to(dtype).to(device))
            # each cloud is its own diagram: same as computing it alone
            if vertex_balls == "every retry":
                # which cells a retry takes follows the first pass's k, the
                # pilot's, which follows the whole batch; the vertex balls
                # clip in another order than the radius of security
                assert_same_integrals(type(sub)(*(a[start:start + s] for a in cells)), sub, dtype)
            else:
                assert_same_cloud(type(sub)(*(a[start:start + s] for a in cells)), sub, dtype)
            check_against_oracle(sub, part, lohi, pick_cells(part, 25, gen, *lohi), RTOL[dtype], tag=f"cloud@{start}")
        start += s


def test_batch_bounding_boxes(device, dtype, gen):
    """box=None with a batch: each cloud clipped to its own bounding box."""
    sizes = [200, 0, 120, 3]
    batch = ragged_batch(sizes, device)
    points = torch.cat([rand(200, gen, dtype, device), rand(120, gen, dtype, device, 3.0, 3.5),
                        rand(3, gen, dtype, device, -1.0, 0.0)])
    cells = run(points, batch=batch)
    boxes, start = [], 0
    for s in sizes:
        part = points[start:start + s].cpu().double().numpy()
        boxes.append((part.min(0), part.max(0)) if s else (np.zeros(3), np.zeros(3)))
        start += s
    check_global(cells, points, boxes, dtype, batch)
    part = points[200:320]
    sub = run(part)
    assert_same_cloud(type(sub)(*(a[200:320] for a in cells)), sub, dtype)
    check_against_oracle(sub, part, boxes[2], pick_cells(part, 30, gen, *boxes[2]), RTOL[dtype])


def test_batch_single_cloud_box_shapes(device, dtype, gen):
    """All box spellings give the same result."""
    points = rand(300, gen, dtype, device)
    ref = run(points, UNIT)
    spellings = [
        torch.tensor([[0.0, 0, 0], [1, 1, 1]], dtype=dtype, device=device),
        torch.tensor([[[0.0, 0, 0], [1, 1, 1]]], dtype=dtype, device=device),
        (torch.zeros(3), torch.ones(3)),
        [[0, 0, 0], [1, 1, 1]],
    ]
    for box in spellings:
        got = run(points, box)
        for a, b in zip(got, ref):
            assert torch.equal(a, b)
    batch = torch.zeros(300, dtype=torch.long, device=device)
    got = run(points, spellings[1], batch=batch)
    for a, b in zip(got, ref):
        assert torch.equal(a, b)


# ------------------------------------------------------ recovery and chunking


def test_small_k_recovery(device, dtype, gen, cells_impl, vertex_balls):
    """k=4 is far too few for any cell: the retry passes must give the exact cells."""
    points = rand(800, gen, dtype, device)
    cells = run(points, UNIT, k=4)
    lohi = box_of(points, UNIT)
    check_global(cells, points, [lohi], dtype)
    assert (cells.neighbors > 4).any()
    check_against_oracle(cells, points, lohi, pick_cells(points, 40, gen, *lohi), RTOL[dtype])
    ref = run(points, UNIT)
    # same cells as with the default k (integrals agree to rounding)
    torch.testing.assert_close(cells.volume, ref.volume, rtol=RTOL[dtype], atol=0)
    assert torch.equal(cells.status, ref.status)


@pytest.mark.parametrize("capacity", ["0", "16", "default"])
def test_speculative_retry_changes_no_cell(monkeypatch, device, dtype, gen, cells_impl, capacity):
    """The first retry runs before the host reads how many cells failed, on
    the device's list of them (ops::speculative_retry), if they fit its
    capacity (TORCHVOR_SPECULATIVE_CELLS: 16384 by default, 0 never). When
    the first pass's cells ask only for more neighbours, as here (k=10, no
    cell near 32 planes), that is the retry the host would have run: the
    outputs are bitwise those without it, whether it ran (the default: every
    failed cell fits) or ran no cell at all (they overflow 16)."""
    points = rand(3000, gen, dtype, device)
    k = 10
    monkeypatch.setenv("TORCHVOR_SPECULATIVE_CELLS", "0")
    plain = run(points, UNIT, k=k)
    failed_first = int((plain.neighbors > k).sum())  # the cells that needed more than the first pass had
    assert 16 < failed_first <= 16384
    if capacity == "default":
        monkeypatch.delenv("TORCHVOR_SPECULATIVE_CELLS")
    else:
        monkeypatch.setenv("TORCHVOR_SPECULATIVE_CELLS", capacity)
    cells = run(points, UNIT, k=k)
    for name, got, expected in zip(VORONOI_FIELDS, cells, plain):
        assert torch.equal(got, expected), name
    check_global(cells, points, [box_of(points, UNIT)], dtype)


def test_clusters_with_voids(monkeypatch, device, dtype, seed, gen):
    """Dense clusters with empty space between them: the cells at a cluster's
    edge reach far into the void, and the radius of security would ask for
    every point within twice their farthest vertex, whole clusters. Past 256
    neighbours a retry finishes them by the empty balls of their vertices
    instead (core::finish_by_vertex_balls): the exact cells, the largest ones
    (in the voids) checked against the oracle, and the same cells, up to
    rounding, as asking for neighbours until the radius of security holds."""
    points = samples.clustered(3000, clusters=20, spread=0.02, seed=seed, dtype=torch.float64).to(dtype).to(device)
    cells = run(points, UNIT)
    lohi = box_of(points, UNIT)
    check_global(cells, points, [lohi], dtype)
    largest = torch.argsort(cells.volume.cpu(), descending=True)[:15].numpy()
    subset = np.unique(np.concatenate([largest, pick_cells(points, 25, gen, *lohi)]))
    check_against_oracle(cells, points, lohi, subset, RTOL[dtype])
    monkeypatch.setenv("TORCHVOR_VERTEX_BALLS_K", str(10 ** 9))
    by_radius = run(points, UNIT)
    assert int(by_radius.neighbors.max()) > 1000  # what the vertex balls spared
    assert_same_integrals(cells, by_radius, dtype)


@pytest.mark.parametrize("most", ["1", "8", "0", "-3", "8x"])
def test_vertex_balls_k_changes_no_cell(monkeypatch, device, dtype, gen, most):
    """TORCHVOR_VERTEX_BALLS_K sets the most neighbours a retry asks for
    before it finishes its cells by their vertices' balls (values that are
    not an integer >= 1 keep the default, 256). Either way the cells are
    exact: the same statuses and integrals up to rounding (the planes come
    in another order); only `neighbors` counts other work."""
    points = rand(4000, gen, dtype, device)
    default = run(points, UNIT, k=6)
    monkeypatch.setenv("TORCHVOR_VERTEX_BALLS_K", most)
    cells = run(points, UNIT, k=6)
    check_global(cells, points, [box_of(points, UNIT)], dtype)
    assert_same_integrals(cells, default, dtype)
    if most in ("1", "8"):
        assert not torch.equal(cells.neighbors, default.neighbors)


@pytest.mark.parametrize("k", [1, 2, 10000])
def test_tiny_k(device, gen, k):
    points = rand(300, gen, torch.float64, device)
    cells = run(points, UNIT, k=k)
    check_global(cells, points, [box_of(points, UNIT)], torch.float64)


def test_tiny_memory_budget(device, dtype, gen, cells_impl):
    """memory_budget=1 forces the smallest chunks (at most 1024 cells): identical results."""
    points = rand(2600, gen, dtype, device)
    ref = run(points, UNIT)
    cells = run(points, UNIT, memory_budget=1)
    for a, b in zip(cells, ref):
        assert torch.equal(a, b)
    lohi = box_of(points, UNIT)
    check_global(cells, points, [lohi], dtype)
    check_against_oracle(cells, points, lohi, pick_cells(points, 30, gen, *lohi), RTOL[dtype])
    small_k = run(points, UNIT, memory_budget=1, k=4)
    torch.testing.assert_close(small_k.volume, ref.volume, rtol=RTOL[dtype], atol=0)


def test_non_contiguous_points(device, dtype, gen):
    points = rand(400, gen, dtype, device).t().contiguous().t()
    assert not points.is_contiguous()
    cells = run(points, UNIT)
    ref = run(points.contiguous(), UNIT)
    for a, b in zip(cells, ref):
        assert torch.equal(a, b)
    # strided batch vector and box
    batch = ragged_batch([150, 250], device)
    box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]] * 2, dtype=dtype, device=device)
    ref = run(points.contiguous(), box, batch=batch)
    batch_view = torch.stack([batch, batch], 1)[:, 0]
    box_view = box.transpose(1, 2).contiguous().transpose(1, 2)
    assert not batch_view.is_contiguous() and not box_view.is_contiguous()
    for a, b in zip(run(points, box_view, batch=batch_view), ref):
        assert torch.equal(a, b)


def test_deterministic(device, dtype, seed):
    points = samples.clustered(3000, seed=seed, dtype=dtype).to(device)
    a, b = run(points, UNIT), run(points, UNIT)
    for x, y in zip(a, b):
        assert torch.equal(x, y)


# ---------------------------------------------------------------- bad input


def test_points_outside_box(device, dtype, gen):
    points = rand(50, gen, dtype, device)
    bad = points.clone()
    bad[10, 2] = 1.5
    with pytest.raises(ValueError, match="box"):
        torchvor.voronoi(bad, UNIT)
    bad = points.clone()
    bad[3, 0] = -1e-3
    with pytest.raises(ValueError, match="box"):
        torchvor.voronoi(bad, UNIT)
    # a batch element outside its own box (but inside another's)
    batch = ragged_batch([25, 25], device)
    box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]], [[2.0, 2, 2], [3, 3, 3]]], dtype=dtype, device=device)
    with pytest.raises(ValueError, match="box"):
        torchvor.voronoi(points, box, batch=batch)


def test_bad_values(device, dtype):
    points = torch.rand(30, 3, dtype=dtype, device=device)
    for value in (float("nan"), float("inf"), -float("inf")):
        bad = points.clone()
        bad[4, 1] = value
        with pytest.raises(ValueError, match="points"):
            torchvor.voronoi(bad, UNIT)
        with pytest.raises(ValueError, match="box"):
            torchvor.voronoi(points, ([0, 0, 0], [1, value, 1]))
    with pytest.raises(ValueError, match="box"):
        torchvor.voronoi(points, ([0, 0, 1], [1, 1, 0]))  # lo > hi
    with pytest.raises(ValueError, match="k"):
        torchvor.voronoi(points, UNIT, k=0)
    with pytest.raises(ValueError, match="memory_budget"):
        torchvor.voronoi(points, UNIT, memory_budget=0)


def test_bad_values_with_batch(device, dtype):
    """With a batch, NaN/Inf points are caught by their own check; without one,
    by the bounds (point_bounds). Both say "points", whichever element holds
    them, also next to an empty batch element."""
    points = torch.rand(40, 3, dtype=dtype, device=device)
    batch = torch.tensor([0] * 20 + [2] * 20, device=device)  # element 1 is empty
    box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]] * 3, dtype=dtype, device=device)
    assert run(points, box, batch=batch).status.eq(CellStatus.SUCCESS).all()
    for value in (float("nan"), float("inf"), -float("inf")):
        for row in (3, 33):
            bad = points.clone()
            bad[row, 2] = value
            with pytest.raises(ValueError, match="points contains NaN or Inf"):
                torchvor.voronoi(bad, box, batch=batch)
            with pytest.raises(ValueError, match="points contains NaN or Inf"):
                torchvor.voronoi(bad, UNIT)


def test_box_of_numbers_copied_once(device):
    """A box given as numbers reaches the op through one device copy per (values,
    dtype, device), kept for later calls (ops._box_for_call); other boxes are
    converted on every call. The results equal as_box's either way."""
    from torchvor.ops import _box_for_call, as_box

    points = torch.rand(20, 3, device=device)
    first = _box_for_call(points, UNIT, None)
    assert _box_for_call(points, ([0, 0, 0], [1, 1, 1]), None) is first  # equal numbers, one copy
    torch.testing.assert_close(first, as_box(points, UNIT), rtol=0, atol=0)
    assert first.shape == (1, 2, 3) and first.dtype == points.dtype and first.device == points.device
    wide = _box_for_call(points, ([-1.0, 0, 0], [1.0, 1, 1]), None)
    assert wide is not first and wide[0, 0, 0].item() == -1.0
    as_double = _box_for_call(points.double(), UNIT, None)
    assert as_double is not first and as_double.dtype == torch.float64
    # Tensors, batches and malformed boxes take as_box on every call.
    given = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]], device=device)
    assert _box_for_call(points, given, None) is given
    batch = torch.zeros(20, dtype=torch.int64, device=device)
    assert _box_for_call(points, UNIT, batch) is not _box_for_call(points, UNIT, batch)
    with pytest.raises(ValueError, match="box"):
        _box_for_call(points, ([0, 0], [1, 1]), None)
    # The op never writes its box: a cached box stays as made after calls.
    cells = torchvor.voronoi(points, UNIT)
    assert _box_for_call(points, UNIT, None) is first and first.flatten().tolist() == [0, 0, 0, 1, 1, 1]
    assert cells.volume.sum().item() == pytest.approx(1.0, rel=1e-5)


def test_bad_shapes_and_types(device):
    points = torch.rand(30, 3, device=device)
    for shape in [(30, 2), (30,), (30, 3, 1), (90,)]:
        with pytest.raises(ValueError, match="points"):
            torchvor.voronoi(torch.rand(shape, device=device), UNIT)
    for box in [torch.zeros(3, 2), torch.zeros(2, 2, 2), torch.zeros(6), ([0, 0], [1, 1])]:
        with pytest.raises(ValueError, match="box"):
            torchvor.voronoi(points, box)
    for dt in (torch.int64, torch.int32, torch.float16, torch.bool):
        with pytest.raises(TypeError, match="points"):
            torchvor.voronoi(points.to(dt), UNIT)
    with pytest.raises(TypeError, match="points"):
        torchvor.voronoi(points.tolist(), UNIT)
    with pytest.raises(TypeError, match="box"):  # the op itself: box dtype must match
        torch.ops.torchvor.voronoi_cells(points, torch.tensor([[[0.0, 0, 0], [1, 1, 1]]], dtype=torch.float64,
                                                              device=device))


def test_bad_batch(device):
    points = torch.rand(20, 3, device=device)
    good = ragged_batch([10, 10], device)
    box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]] * 2, device=device)
    run(points, box, batch=good)
    with pytest.raises(ValueError, match="batch"):
        torchvor.voronoi(points, box, batch=good.flip(0))
    with pytest.raises(ValueError, match="batch"):
        torchvor.voronoi(points, box, batch=good - 1)
    with pytest.raises(ValueError, match="batch"):
        torchvor.voronoi(points, box, batch=good[:-1])
    with pytest.raises(TypeError, match="batch"):
        torchvor.voronoi(points, box, batch=good.int())
    with pytest.raises(ValueError, match="box"):  # 2 clouds, 1 box
        torchvor.voronoi(points, box[:1], batch=good)
    with pytest.raises(ValueError, match="box"):  # several boxes without batch
        torchvor.voronoi(points, box)


def test_on_failure_values(device, gen):
    points = rand(100, gen, torch.float64, device)
    with pytest.raises(ValueError, match="on_failure"):
        torchvor.voronoi(points, UNIT, on_failure="ignore")
    with pytest.raises(ValueError, match="on_failure"):
        torchvor.voronoi(points, UNIT, on_failure=None)
    results = []
    for mode in ("raise", "warn", "flag"):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            results.append(torchvor.voronoi(points, UNIT, on_failure=mode))
    for other in results[1:]:
        for a, b in zip(results[0], other):
            assert torch.equal(a, b)


def sphere_around_centre(n, dtype, device):
    """A point at the centre of the unit cube and n points on a sphere around it
    (Fibonacci spiral): the centre cell has n facets, more than any cell array."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    phi = torch.acos(1 - 2 * i / n)
    theta = np.pi * (1 + 5 ** 0.5) * i
    s = torch.stack([torch.cos(theta) * torch.sin(phi), torch.sin(theta) * torch.sin(phi), torch.cos(phi)], 1)
    return torch.cat([torch.full((1, 3), 0.5, dtype=torch.float64), 0.5 + 0.3 * s]).to(dtype).to(device)


def test_failure_reporting(device, dtype, gen, cells_impl):
    """A cell that cannot be represented (400 facets) is reported, never silent:
    "raise" -> RuntimeError, "warn" -> RuntimeWarning, "flag" -> quiet; a failure
    status and NaN outputs for that cell, exact results for the others."""
    points = sphere_around_centre(400, dtype, device)
    with pytest.raises(RuntimeError, match="could not be computed"):
        torchvor.voronoi(points, UNIT, on_failure="raise")
    with pytest.warns(RuntimeWarning, match="could not be computed"):
        warned = torchvor.voronoi(points, UNIT, on_failure="warn")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cells = torchvor.voronoi(points, UNIT, on_failure="flag")
    for a, b in zip(warned, cells):
        torch.testing.assert_close(a, b, rtol=0, atol=0, equal_nan=True)
    status = cells.status.cpu()
    failed = (status != CellStatus.SUCCESS) & (status != CellStatus.DUPLICATE)
    assert failed[0] and not failed[1:].any(), status
    assert status[0] in (CellStatus.TOO_MANY_PLANES, CellStatus.TOO_MANY_VERTICES)
    assert torch.isnan(cells.volume[0]) and torch.isnan(cells.centroid[0]).all()
    assert torch.isnan(cells.second_moment[0])
    assert torch.isfinite(cells.volume[1:]).all() and torch.isfinite(cells.centroid[1:]).all()
    check_against_oracle(cells, points, box_of(points, UNIT), range(1, 401, 23), RTOL[dtype])


@pytest.mark.skipif(not has_cuda, reason="needs CUDA")
def test_device_mismatch():
    points = torch.rand(20, 3)
    box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]])
    with pytest.raises(ValueError, match="box"):
        torch.ops.torchvor.voronoi_cells(points.cuda(), box)
    with pytest.raises(ValueError, match="batch"):
        torchvor.voronoi(points.cuda(), UNIT, batch=torch.zeros(20, dtype=torch.long))
    with pytest.raises(ValueError, match="box"):
        torch.ops.torchvor.voronoi_cells(points, box.cuda())
    with pytest.raises(ValueError, match="batch"):
        torchvor.voronoi(points, UNIT, batch=torch.zeros(20, dtype=torch.long, device="cuda"))


def test_empty_points(device, dtype):
    cells = torchvor.voronoi(torch.empty(0, 3, dtype=dtype, device=device), UNIT)
    assert cells.volume.shape == (0,) and cells.centroid.shape == (0, 3)
    cells = torchvor.voronoi(torch.empty(0, 3, dtype=dtype, device=device))
    assert cells.status.shape == (0,)


# ---------------------------------------------------- opcheck / torch.compile


def test_opcheck_voronoi(device, dtype, gen):
    points = rand(30, gen, dtype, device)
    box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]], dtype=dtype, device=device)
    torch.library.opcheck(torch.ops.torchvor.voronoi_cells.default, (points, box, None, 40, 1 << 20))
    torch.library.opcheck(torch.ops.torchvor.voronoi_cells.default, (points, box, None, 3, 1))
    batch = ragged_batch([12, 0, 18], device)
    boxes = box.expand(3, 2, 3).contiguous()
    torch.library.opcheck(torch.ops.torchvor.voronoi_cells.default, (points, boxes, batch, 8, 1 << 20))


def test_memory_budget_default_matches_the_schemas():
    """The Python wrappers' default memory_budget is the ops' schema default."""
    for op in (torch.ops.torchvor.voronoi_cells.default, torch.ops.torchvor.voronoi_cells_grid_order.default):
        budget = next(a for a in op._schema.arguments if a.name == "memory_budget")
        assert budget.default_value == torchvor.ops.DEFAULT_MEMORY_BUDGET


def test_opcheck_voronoi_grid_order(device, dtype, gen):
    points = rand(30, gen, dtype, device)
    box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]], dtype=dtype, device=device)
    op = torch.ops.torchvor.voronoi_cells_grid_order.default
    torch.library.opcheck(op, (points, box, None, 40, 1 << 20))
    torch.library.opcheck(op, (points, box, None, 3, 1))
    batch = ragged_batch([12, 0, 18], device)
    torch.library.opcheck(op, (points, box.expand(3, 2, 3).contiguous(), batch, 8, 1 << 20))


@pytest.mark.parametrize("k", [3, None])
def test_grid_order_gives_the_same_cells_in_that_order(device, dtype, gen, k):
    """torchvor::voronoi_cells_grid_order (torchvor.lloyd's) computes the cells
    of voronoi_cells, bit for bit, row i for points[order[i]]: order is a
    permutation, sorted by batch element, that keeps exact duplicates in the
    caller's order (the lowest index keeps the cell). k=3 retries every cell."""
    from torchvor.ops import _voronoi_in_grid_order, as_box
    points = rand(900, gen, dtype, device)
    points[600:650] = points[100:150]  # exact duplicates, later rows
    batch = ragged_batch([400, 0, 500], device)
    for use_batch in (False, True):
        b = batch if use_batch else None
        box = as_box(points, None, b)
        reference = torchvor.voronoi(points, box, batch=b, k=k, on_failure="flag")
        cells, order = _voronoi_in_grid_order(points, box, b, k)
        assert order.dtype == torch.int64 and order.device == points.device
        assert torch.equal(torch.sort(order).values, torch.arange(900, device=device))
        for name in VORONOI_FIELDS:
            assert torch.equal(getattr(cells, name), getattr(reference, name)[order]), name
        if use_batch:
            assert bool((batch[order].diff() >= 0).all())
        rank = torch.empty_like(order).index_copy_(0, order, torch.arange(900, device=device))
        assert bool((rank[100:150] < rank[600:650]).all())
    cells, order = _voronoi_in_grid_order(points[:0], as_box(points, UNIT))
    assert order.shape == (0,) and order.dtype == torch.int64 and cells.centroid.shape == (0, 3)


def test_compile_voronoi_grid_order(device, dtype, gen):
    from torchvor.ops import _voronoi_in_grid_order
    torch._dynamo.reset()
    box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]], dtype=dtype, device=device)

    def f(p):
        cells, order = _voronoi_in_grid_order(p, box)
        return cells.centroid - p[order], order

    compiled = torch.compile(f, fullgraph=True)
    for n in (150, 260):
        points = rand(n, gen, dtype, device)
        for a, b in zip(compiled(points), f(points)):
            assert torch.equal(a, b)


def test_compile_voronoi(device, dtype, gen):
    torch._dynamo.reset()

    def f(p):
        cells = torchvor.voronoi(p, UNIT)
        return cells.volume, cells.centroid, cells.second_moment, cells.status, cells.neighbors

    def g(p):  # default (bounding) box and arithmetic around the op
        cells = torchvor.voronoi(p)
        return (cells.volume * 2).sum(), cells.centroid - p

    compiled_f = torch.compile(f, fullgraph=True)
    compiled_g = torch.compile(g, fullgraph=True)
    for n in (150, 260):
        points = rand(n, gen, dtype, device)
        for a, b in zip(compiled_f(points), f(points)):
            assert torch.equal(a, b)
        for a, b in zip(compiled_g(points), g(points)):
            torch.testing.assert_close(a, b)


def assert_cells_unchanged(cells, default_cells, dtype, same_passes=True):
    """The same statuses; in float64 the same neighbour counts and integrals,
    bit for bit. In float32 the integrals agree up to rounding: equally far
    neighbours may be clipped in another order, and with
    `same_passes=False` (another first pass's k) a cell may end in another
    pass, as in assert_same_cloud: a thread cell of the first tier (vertices
    held to 18 mantissa bits, CompactTriangles) in one run and a retry of a
    higher tier in the other. Its neighbour count may then move by one (the
    radius of security comes from the vertices). Over 200 pairs of 5000
    cells (pilot quantiles 0.5 and 1 against the default, seeds 100-199),
    4 cells counted one neighbour more or fewer; the largest relative
    differences were 1.18e-5 for the second moment (its terms cancel the
    most) and 4.2e-6 for the volume."""
    assert torch.equal(default_cells.status, cells.status), "status"
    if dtype == torch.float32 and not same_passes:
        assert int((default_cells.neighbors - cells.neighbors).abs().max()) <= 1, "neighbors"
    else:
        assert torch.equal(default_cells.neighbors, cells.neighbors), "neighbors"
    for name, rtol in (("volume", 1e-5), ("centroid", 1e-5), ("second_moment", 5e-5)):
        if dtype == torch.float64:
            assert torch.equal(getattr(default_cells, name), getattr(cells, name)), name
        else:
            torch.testing.assert_close(getattr(cells, name), getattr(default_cells, name), rtol=rtol, atol=0)


@pytest.mark.parametrize("scale", ["0.3", "3"])
def test_grid_density_changes_no_result(monkeypatch, device, dtype, gen, scale):
    """TORCHVOR_POINTS_PER_CELL_SCALE (benchmarks/sweep_points_per_cell.py)
    scales the points per grid cell of the kNN searches: another grid finds
    the same neighbours (ties go to the lower index), so the kNN is equal to
    the default's, bit for bit, and so are the cells in float64. In float32,
    two neighbours of a cell can be exactly equally far (one cell in 5000
    with some seeds, e.g. TORCHVOR_TEST_SEED=1800692895); voronoi's kNN numbers
    points by their grid position, so such a pair is clipped in an order that
    depends on the grid: the same cell, its sums rounded in another order."""
    points = rand(5000, gen, dtype, device)
    default_cells = torchvor.voronoi(points, UNIT, k=24)
    default_knn = torchvor.knn(points, 16)
    monkeypatch.setenv("TORCHVOR_POINTS_PER_CELL_SCALE", scale)
    cells = torchvor.voronoi(points, UNIT, k=24)
    knn = torchvor.knn(points, 16)
    check_global(cells, points, [box_of(points, UNIT)], dtype)
    assert_cells_unchanged(cells, default_cells, dtype)
    assert torch.equal(default_knn.idx, knn.idx)
    assert torch.equal(default_knn.dist2, knn.dist2)


@pytest.mark.parametrize("quantile", ["0.5", "1", "2", "nonsense"])
def test_pilot_quantile_changes_no_result(monkeypatch, device, dtype, gen, quantile):
    """TORCHVOR_PILOT_QUANTILE (benchmarks/ab_env.py) sets the share of the
    pilot's cells that the default first-pass k covers (0.98; values outside
    (0, 1] keep it). Another k retries other cells, but each cell stops at the
    same neighbour: the same cells, bit for bit in float64. In float32 the
    grid follows k, and equally far neighbours may be clipped in another
    order, as in test_grid_density_changes_no_result; a cell may also end in
    another pass, whose vertices round otherwise, and count one neighbour
    more or fewer (seen in CI: TORCHVOR_TEST_SEED=2526752964 with 0.5)."""
    points = rand(5000, gen, dtype, device)
    default_cells = torchvor.voronoi(points, UNIT)
    monkeypatch.setenv("TORCHVOR_PILOT_QUANTILE", quantile)
    cells = torchvor.voronoi(points, UNIT)
    check_global(cells, points, [box_of(points, UNIT)], dtype)
    assert_cells_unchanged(cells, default_cells, dtype, same_passes=False)


# -------------------------------------------------------- CPU / CUDA parity


@pytest.mark.skipif(not has_cuda, reason="needs CUDA")
@pytest.mark.parametrize("blocks_per_sm", ["1", "1000"])
@pytest.mark.parametrize("k", [24, 48])
def test_cuda_cell_residency_changes_no_result(monkeypatch, dtype, gen, blocks_per_sm, k):
    """On CUDA, one thread per cell runs on a capped grid, each warp claiming
    32 cells at a time from a counter (CudaExec::for_each_cell), capped
    lower from k = 28; TORCHVOR_CELL_BLOCKS_PER_SM overrides the cap. One
    block an SM (every warp claims several times) and more than fit
    (clamped to what the SM holds) give the default's cells, bit for bit,
    and none is left unwritten."""
    points = rand(40000, gen, dtype, "cuda")
    monkeypatch.setenv("TORCHVOR_CELLS", "thread")  # every pass, the retries too
    default = torchvor.voronoi(points, UNIT, k=k)
    monkeypatch.setenv("TORCHVOR_CELL_BLOCKS_PER_SM", blocks_per_sm)
    capped = torchvor.voronoi(points, UNIT, k=k)
    check_global(capped, points, [box_of(points, UNIT)], dtype)
    for name in ("volume", "centroid", "second_moment", "status", "neighbors"):
        assert torch.equal(getattr(default, name), getattr(capped, name)), name


@pytest.mark.skipif(not has_cuda, reason="needs CUDA")
def test_cuda_warps_claim_many_cells(monkeypatch, dtype, gen):
    """On CUDA a warp per cell runs as a persistent kernel whose warps claim
    one cell at a time from a counter (CudaExec::for_each_cooperative). With
    40000 cells, several times the warps an H100 holds (at most 64 an SM),
    each warp claims many: every cell is written, and the cells are the
    thread cells' up to rounding. (Neighbour counts are compared on smaller
    sets, test_cooperative_cells_match_thread_cells: over 40000 cells a
    rounding may move one cell's radius of security by a neighbour.)"""
    points = rand(40000, gen, dtype, "cuda")
    results = {}
    for impl in ("thread", "cooperative"):
        monkeypatch.setenv("TORCHVOR_CELLS", impl)
        results[impl] = torchvor.voronoi(points, UNIT, k=24)
    coop, thread = results["cooperative"], results["thread"]
    check_global(coop, points, [box_of(points, UNIT)], dtype)
    assert torch.equal(coop.status, thread.status)
    rtol = RTOL[dtype]
    size = float(thread.volume.double().mean()) ** (1 / 3)
    torch.testing.assert_close(coop.volume, thread.volume, rtol=rtol, atol=rtol * size ** 3)
    torch.testing.assert_close(coop.centroid, thread.centroid, rtol=0, atol=rtol * size)


def clip_kernels_run(call):
    """Which clip kernels a CUDA call launched: 'thread' (a thread per cell,
    CudaExec::for_each_cell), 'warp' (a warp per cell, for_each_cooperative),
    and 'vertex balls, warp' or 'vertex balls, thread' (cells finished on the
    grid, ClipFunctor's kVertexBalls: the retries past 256 neighbours)."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        result = call()
        torch.cuda.synchronize()
    kinds = set()
    for name in (event.key for event in prof.key_averages() if "ClipFunctor" in event.key):
        cells = "warp" if "for_each_cooperative_claimed_kernel" in name else "thread"
        finished_on_grid = re.search(r"ClipFunctor<[^,>]*,[^,>]*,[^,>]*,\s*true\b", name) is not None  # kVertexBalls
        kinds.add(f"vertex balls, {cells}" if finished_on_grid else cells)
    return result, kinds


@pytest.mark.skipif(not has_cuda, reason="needs CUDA")
@pytest.mark.parametrize("kind", ["voids", "wide box"])
def test_cuda_vertex_balls_match_cpu(dtype, seed, kind, cells_impl):
    """The cells finished on the grid by their vertices' balls (past 256
    neighbours: clusters with voids between them, a box three times as wide
    as the points) run on CUDA as warp cells (by default) or thread cells
    (TORCHVOR_CELLS=thread) and equal the CPU's thread cells: the same
    statuses and integrals up to rounding."""
    if kind == "voids":
        points = samples.clustered(20000, clusters=20, spread=0.02, seed=seed, dtype=dtype)
        box = UNIT
    else:
        points = samples.white_noise(20000, seed=seed, dtype=dtype)
        box = ([-1.0, -1.0, -1.0], [2.0, 2.0, 2.0])
    gpu, launched = clip_kernels_run(lambda: run(points.cuda(), box))
    assert ("vertex balls, warp" if cells_impl == "cooperative" else "vertex balls, thread") in launched
    check_global(gpu, points.cuda(), [box_of(points.cuda(), box)], dtype)
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("TORCHVOR_CELLS", "thread")
        cpu = run(points, box)
    assert_same_integrals(type(cpu)(*(t.cpu() for t in gpu)), cpu, dtype)


@pytest.mark.skipif(not has_cuda, reason="needs CUDA")
@pytest.mark.parametrize("k", [None, 48])
@pytest.mark.parametrize("kind", ["jittered", "white"])
def test_cuda_cells_chosen_by_neighbor_spread(dtype, gen, seed, kind, k):
    """Over more than 16384 cells, CUDA computes a cell by a thread where the
    cells need about as many neighbours as each other, and by a warp where
    that varies widely: by the spread (standard deviation / mean) of the
    neighbours a pilot's ~1000 cells needed (CudaExec::cooperative_cells;
    0.14 on a jittered grid, 0.29-0.32 on white noise, against 0.25). A
    caller's k of 40 or more runs that pilot too, whose cells the main pass
    recomputes. Either way every cell is written and equals the CPU's up to
    rounding."""
    n = 100_000
    if kind == "jittered":
        points = samples.jittered_grid(n, seed=seed, dtype=dtype)
    else:
        points = rand(n, gen, dtype, "cpu")
    gpu, launched = clip_kernels_run(lambda: torchvor.voronoi(points.cuda(), UNIT, k=k))
    # The pilot and small retry passes are warps whatever the kind; a cell of
    # white noise near a box corner may need more than 256 neighbours.
    assert launched - {"vertex balls, warp"} == ({"thread", "warp"} if kind == "jittered" else {"warp"})
    check_global(gpu, points.cuda(), [box_of(points.cuda(), UNIT)], dtype)
    cpu = torchvor.voronoi(points, UNIT, k=k)
    assert torch.equal(cpu.status, gpu.status.cpu())
    rtol = RTOL[dtype]
    size = float(cpu.volume.double().mean()) ** (1 / 3)
    torch.testing.assert_close(gpu.volume.cpu(), cpu.volume, rtol=rtol, atol=rtol * size ** 3)
    torch.testing.assert_close(gpu.centroid.cpu(), cpu.centroid, rtol=0, atol=rtol * size)


@pytest.mark.skipif(not has_cuda, reason="needs CUDA")
@pytest.mark.parametrize("kind", ["white", "clustered", "lattice", "duplicates", "batch", "small_k"])
def test_cpu_cuda_parity(dtype, gen, seed, kind):
    batch, box, k = None, UNIT, None
    if kind == "white":
        points = rand(4000, gen, dtype, "cpu")
    elif kind == "clustered":
        points = samples.clustered(4000, seed=seed, dtype=dtype)
    elif kind == "lattice":
        points = samples.lattice(12, dtype=dtype)
    elif kind == "duplicates":
        points = rand(1000, gen, dtype, "cpu")
        points = torch.cat([points, points[:300]])
    elif kind == "batch":
        batch = ragged_batch([1500, 0, 2, 900], "cpu")
        points = rand(2402, gen, dtype, "cpu")
        box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]] * 4, dtype=dtype)
    else:
        points = rand(3000, gen, dtype, "cpu")
        k = 4
    cpu = torchvor.voronoi(points, box, batch=batch, k=k)
    gpu = torchvor.voronoi(points.cuda(), box if not isinstance(box, torch.Tensor) else box.cuda(),
                           batch=None if batch is None else batch.cuda(), k=k)
    assert torch.equal(cpu.status, gpu.status.cpu())
    rtol = RTOL[dtype]
    torch.testing.assert_close(gpu.volume.cpu(), cpu.volume, rtol=rtol, atol=rtol * cpu.volume.abs().max().item())
    torch.testing.assert_close(gpu.centroid.cpu(), cpu.centroid, rtol=rtol, atol=rtol)
    torch.testing.assert_close(gpu.second_moment.cpu(), cpu.second_moment, rtol=rtol,
                               atol=rtol * cpu.second_moment.abs().max().item())
