"""torchvor.voronoi on random point sets against the per-cell scipy/Qhull
half-space oracle (tests/oracles.py) and exact identities (sum of volumes,
first moments); and the implementations of a cell compared with each other
(a thread or a group of lanes, tetrahedron or box start, compact or full
triangle records, the AVX2+FMA or the baseline CPU loop).
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

import torchvor
from torchvor import samples

from oracles import brute_force_knn, voronoi_cell_oracle
from voronoi_checks import (
    RTOL, UNIT, assert_same_cells, assert_same_integrals, box_of, check_against_oracle, check_global, near_faces,
    pick_cells, point_set, ragged_batch, rand, run,
)


# -------------------------------------- random point sets against the oracle


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


def test_neighbors_radius_of_security(monkeypatch, device, gen):
    """`neighbors_needed` counts the nearest neighbours a cell used: every true Voronoi
    neighbour is among them, and the next one is beyond twice the cell radius.
    (Of the cells that the radius of security finishes: here all of them, as
    no retry finishes its cells by their vertices' balls.)"""
    monkeypatch.setenv("TORCHVOR_VERTEX_BALLS_K", str(10 ** 9))
    points = rand(600, gen, torch.float64, device)
    cells = run(points, UNIT)
    p = points.cpu().numpy()
    _, order = brute_force_knn(points.cpu(), len(p) - 1)  # full (distance, index) order
    used = cells.neighbors_needed.cpu().numpy()
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


# ---------------------------------------- implementations of a cell compared


@pytest.mark.parametrize("kind", ["white", "clustered", "lattice", "duplicates", "small_k"])
def test_cooperative_cells_match_thread_cells(monkeypatch, device, dtype, gen, seed, kind):
    """The two implementations of a cell (one thread, or a group of lanes:
    csrc/core/cooperative_cell.h) take the same decisions: the same statuses
    and neighbour counts, the same integrals up to rounding (the lanes sum
    the tetrahedra in another order). On the CPU a thread per cell runs the
    AVX2+FMA loop where the CPU has it, and the lanes the baseline loop: fused
    and separate roundings can move the radius of security by one neighbour
    (on clustered sets), so both run the baseline loop here. Float32 thread
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
    # CUDA: the two fuse different products, which can move the radius of security by one neighbour
    assert_same_cells(coop, thread, dtype, points if device.type == "cuda" else None)


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
    """On CUDA, float32 thread cells of up to 32 planes keep their triangles
    in 12 bytes (csrc/core/convex_cell.h, CompactTriangles: coordinates
    rounded to 18 mantissa bits, the plane ids in the 5 bits that frees);
    TORCHVOR_THREAD_TRIANGLES=full keeps 16-byte records, as the CPU always
    does (there both runs are the same cells). Both meet the
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
    differ = (compact.neighbors_needed - full.neighbors_needed).abs()
    # A neighbour and its exact copy come in a row, and the copy is skipped
    # but counted: where one run stops at the first of the pair and the
    # other clips it, the count moves by two (TORCHVOR_TEST_SEED=9713905,
    # duplicates: 42 with full triangles, 44 with compact ones).
    most = 2 if kind == "duplicates" else 1
    assert differ.max() <= most and (differ > 0).float().mean() < 0.01
    if kind == "white":  # the compact form was used on CUDA only
        assert torch.equal(full.volume, compact.volume) == (torch.device(device).type == "cpu")


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
    for name in ("volume", "centroid", "second_moment", "status", "neighbors_needed", "radius"):
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
