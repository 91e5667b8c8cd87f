"""Shared helpers of the Voronoi tests (tests/test_voronoi_*.py): tolerances,
point generators, and the checks of torchvor.voronoi's cells against the
per-cell scipy/Qhull half-space oracle (tests/oracles.py) and against exact
identities (sum of volumes, first moments).

Inputs are drawn fresh per test (``gen`` / ``seed`` fixtures; the seed is
printed on failure) on the CPU in float64, rounded to the tested dtype, and
moved to ``device``. The oracle always sees exactly the values torchvor saw.
The fixtures ``cells_impl`` and ``vertex_balls`` are in tests/conftest.py.
"""
from __future__ import annotations

import math
import warnings

import numpy as np

import torch

import torchvor
from torchvor import CellStatus, samples

from oracles import exact_cell_oracle, voronoi_cell_oracle

has_cuda = torch.cuda.is_available()
UNIT = ([0.0, 0.0, 0.0], [1.0, 1.0, 1.0])
VORONOI_FIELDS = ("volume", "centroid", "second_moment", "status", "neighbors_needed", "radius")

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


def assert_same_cells(cells, expected, dtype, points=None, box=UNIT):
    """The same statuses and neighbour counts, and the same integrals up to
    rounding (relative, or absolute at the scale of the mean cell).

    With `points` (one cloud in `box`), a count may differ by one where
    computations whose vertices round differently (CUDA's thread and warp
    cells fuse different products) can decide a neighbour either way, and
    both are right (it cannot cut the cell, or cuts nothing measurable):
    the neighbour between the two counts lies at twice the cell's radius to
    within 1e-3 relative (the radius of security), or a point lies on the
    ball of one of the cell's vertices to within 1e-4 of the ball's radius (a
    vertex shared by five points up to rounding, which a cell finished by its
    vertices' empty balls, past 256 neighbours, counts or not)."""
    differ = (expected.neighbors_needed != cells.neighbors_needed).nonzero().squeeze(1).tolist()
    assert points is not None or not differ, f"neighbour counts differ at cells {differ[:10]}"
    x = points.detach().double().cpu() if differ else None
    for i in differ:
        fewer = int(min(expected.neighbors_needed[i], cells.neighbors_needed[i]))
        more = int(max(expected.neighbors_needed[i], cells.neighbors_needed[i]))
        dist2 = ((x - x[i]) ** 2).sum(1)
        dist2[i] = math.inf  # the seed itself
        between = float(dist2.sort().values[fewer])  # neighbour `fewer` (0-based): read by one, not the other
        security2 = 4 * float(max(expected.radius[i], cells.radius[i])) ** 2
        at_security = abs(between / security2 - 1) < 1e-3
        on_ball = math.inf if at_security else on_a_vertex_ball(x, i, box)
        assert more == fewer + 1 and (at_security or on_ball < 1e-4), (
            f"cell {i}: {fewer} and {more} neighbours, the one between at {between / security2:.6f} "
            f"of the radius of security squared, the nearest point to a vertex's ball {on_ball:.2e} off it")
    assert_same_integrals(cells, expected, dtype)


def on_a_vertex_ball(x, i, box):
    """How near a fifth point lies to the ball of one of cell i's vertices
    (centred on the vertex, through the seed and the vertex's other
    defining points: three, less the box walls through it): the least
    |distance to the vertex - ball radius| / ball radius over the
    exact cell's vertices (scipy oracle) and the other points, x (N, 3)
    float64. Near 0: the vertex is degenerate up to rounding."""
    pts = x.numpy()
    lo, hi = box_of(x, box)
    vertices = voronoi_cell_oracle(pts, i, (lo, hi)).vertices  # (V, 3)
    radius = np.sqrt(((vertices - pts[i]) ** 2).sum(1))  # (V,)
    gap = np.abs(np.sqrt(((vertices[:, None, :] - pts[None, :, :]) ** 2).sum(2)) - radius[:, None])  # (V, N)
    gap[:, i] = np.inf
    walls = (np.isclose(vertices, lo, rtol=0, atol=1e-12) | np.isclose(vertices, hi, rtol=0, atol=1e-12)).sum(1)
    defining = np.clip(3 - walls, 0, 3)  # (V,) points besides the seed whose bisectors meet there
    fifth = np.sort(gap, axis=1)[np.arange(len(vertices)), defining]  # the nearest point not defining it
    return float((fifth / radius).min())


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
    assert int((part.neighbors_needed - alone.neighbors_needed).abs().max()) <= 1


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
    radius = cells.radius.detach().cpu().double().numpy()
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
        # the farthest computed vertex, rounded up to float32, within its
        # rounding of the exact one: nearly parallel planes round a vertex more
        # than the volume (3e-6 short in a float64 cell 1e-12 wide, 1e-3
        # beyond in a 1e-15 cell of points a few ulps apart); certificates
        # allow 1% (torchvor.periodic)
        if ref.radius - radius[i] > max(rtol, 1e-4) * size + slack:
            return f"{where}: radius {radius[i]!r} short of the oracle's {ref.radius!r}"
        if radius[i] - ref.radius > 1e-2 * size + slack + 2.4e-7 * ref.radius:
            return f"{where}: radius {radius[i]!r} vs oracle {ref.radius!r}"
        return None

    for i in subset:
        i = int(i)
        ref = voronoi_cell_oracle(p, i, (lo, hi))
        where = f"{tag} cell {i} (seed {p[i].tolist()})"
        if ref.duplicate:
            assert status[i] == CellStatus.DUPLICATE, f"{where}: duplicate, status {status[i]}"
            assert vol[i] == 0 and m2[i] == 0, f"{where}: duplicate with volume {vol[i]}, moment {m2[i]}"
            np.testing.assert_array_equal(cen[i], p[i], err_msg=f"{where}: duplicate centroid")
            assert radius[i] == 0, f"{where}: duplicate with radius {radius[i]}"
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
    assert cells.second_moment.shape == (n,) and cells.status.shape == (n,) and cells.neighbors_needed.shape == (n,)
    assert cells.volume.dtype == dtype and cells.centroid.dtype == dtype and cells.second_moment.dtype == dtype
    assert cells.status.dtype == torch.int8 and cells.neighbors_needed.dtype == torch.int32
    assert cells.radius.shape == (n,) and cells.radius.dtype == dtype
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
    assert (cells.neighbors_needed.cpu() >= 0).all()
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


def run(points, box=None, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a RuntimeWarning (failed cell) fails the test
        return torchvor.voronoi(points, box, **kwargs)
