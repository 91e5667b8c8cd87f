"""The fuzzing campaign's CI slice (tests/fuzz.py): a fixed campaign seed,
small cases of every kind in both dtypes under both cell implementations,
on every device; and checks that the fuzzer itself replays its cases and
catches wrong results.

Deterministic: the cases follow from CI_SEED alone (no OS-random seed), so a
failure replays with the command printed next to each problem.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import torchvor
from torchvor import CellStatus

import fuzz
import fuzz_workers

CI_SEED = 44
CI_CASES = 90  # six rounds of the 15 kinds: each kind three times in each dtype
CI_MAX_N = 3000


def test_fuzz_ci_slice(device):
    """Cases 0..CI_CASES-1 of campaign CI_SEED (sizes up to CI_MAX_N, float32
    and float64, TORCHVOR_CELLS=thread and =cooperative): no failed cell, no
    silently wrong cell, every cloud's volumes summing to its box, no
    unexpected exception, and the deliberately invalid inputs rejected with
    a ValueError naming the cause."""
    report = fuzz.run_campaign(CI_SEED, range(CI_CASES), device=device.type, max_n=CI_MAX_N, dtype="both",
                               cells="all")
    counts = report.counts
    text = fuzz.summary(report)
    assert counts["cases"] == CI_CASES
    assert set(report.per_kind) == set(fuzz.KINDS), text
    assert counts["expected_errors"] == 2 * len(range(fuzz.INVALID_EVERY - 1, CI_CASES, fuzz.INVALID_EVERY)), text
    assert counts["certified"] > 0, text
    assert counts["graphs"] > 0 and counts["faces_certified"] > 0, text
    assert counts["failed_cells"] == 0, text
    assert counts["silently_wrong"] == 0, text
    assert counts["wrong_volume_sums"] == 0, text
    assert counts["unexpected_exceptions"] == 0, text


# Cases of earlier campaigns that once failed, replayed on every device:
# (seed, index, max_n, dtype, what went wrong).
REGRESSIONS = [
    (2, 232, 20000, "both", "close pairs 1-4 ulps apart (float64): BOUNDARY_ERROR after double-double"),
    (2, 625, 20000, "both", "density r^7.8 about a point (float64): BOUNDARY_ERROR after double-double"),
    (1, 17, 1000000, "both", "points on a 5 x 5 x 5 grid through the walls (float64): BOUNDARY_ERROR after double-double"),
    (2, 210, 5000, "float32", "11 clusters of spread 1.4e-4: a cell 4.4e-4 off (ill-conditioned vertices)"),
    (3, 255, 20000, "float32", "4 clusters of spread 2.5e-4: a cell 5.4e-3 off (ill-conditioned vertices)"),
    (3, 358, 20000, "float32", "a cell a few ulps wide beside a box start: 4.9e-2 off (vertices' rounding decided cuts)"),
    (1, 228, 20000, "both", "5 points above a wall layer: TOO_MANY_PLANES at the largest tier"),
    (2, 939, 20000, "both", "26 points on a line copied 14192 times: minutes in the kNN (grid sized for the copies)"),
    (5, 1832, 20000, "float32", "needle cells 0.003 x 6 far from the origin: 2.3e-3 off (long side's rounding)"),
    (4, 103, 1000000, "float32", "anisotropic lattice, cells 0.3 x 96: 5e-4 off (long side's rounding)"),
    (11, 1349, 1000000, "both", "anisotropic lattice, cells 2 x 2e-4 (float64): 1.2e-9 off (long side's rounding)"),
    (5, 22, 3000, "both", "two close pairs 1-4 ulps apart (float64): faces split wrongly, not closed (graph)"),
    (5, 37, 3000, "float32", "close pairs 1-4 ulps apart: 138 cells' faces not closed (graph)"),
    (13, 145, 20000, "both", "density r^8.3 about a point, cells 1e-12 wide: Qhull lost the cell (oracle)"),
    (14, 2285, 20000, "float32", "lattice of needle cells (float32): faces to the wrong neighbours (float32 kNN ties)"),
    (14, 367, 20000, "both", "close pairs 1.7e-10 apart, slab cells: a copy's face dropped within the band (graph)"),
    (14, 967, 20000, "both", "close pairs 1.7e-10 apart, slab cells: a copy's face dropped within the band (graph)"),
    (19, 673, 1000000, "float32", "a cell beside a cluster, cancellation 31: 1.26e-4 off (compact vertices' rounding)"),
    (19, 1855, 1000000, "float64", "points 7-100 ulps apart, a box start 1e15 times wider: faces 7e-4 off (graph)"),
    (23, 36, 20000, "float32", "jittered lattice: a vertex put beyond the cell it cut, radius 22% over (compact triangles)"),
    (33, 28, 1000000, "both", "4 clouds, periodic power cells: retried rows out of cloud order (knn's query_batch)"),
    (44, 2359, 1000000, "both", "periodic thin slab, lattice jittered 1e-9: the oracle moved points inside the box (oracle)"),
    (44, 1078, 1000000, "both", "a pair 2e-12 apart in a 33-point gradient: faces not closed on CUDA (graph)"),
    (44, 3379, 1000000, "both", "periodic thin slab, lattice planes 2e-11 apart across a face: sum 2e-8 off (images round)"),
]


@pytest.mark.parametrize("fuzz_seed, index, max_n, case_dtype, what", REGRESSIONS,
                         ids=[f"seed{seed}-case{index}" for seed, index, *_ in REGRESSIONS])
def test_fuzz_regressions(device, fuzz_seed, index, max_n, case_dtype, what):
    """Every cell of a case in REGRESSIONS computed and right, under both
    cell implementations (one test a case: shards of the suite share them)."""
    report = fuzz.run_campaign(fuzz_seed, [index], device=device.type, max_n=max_n, dtype=case_dtype, cells="all")
    assert report.ok(), f"{what}\n{fuzz.summary(report)}"


def test_cases_replay_alone():
    """A case depends only on (seed, index) and the generator's settings:
    drawn again, or after other cases, it is the same input."""
    first = fuzz.make_case(CI_SEED, 17, max_n=CI_MAX_N)
    fuzz.make_case(CI_SEED, 16, max_n=CI_MAX_N)
    again = fuzz.make_case(CI_SEED, 17, max_n=CI_MAX_N)
    assert first.kind == again.kind and first.dtype == again.dtype and first.box_arg == again.box_arg
    np.testing.assert_array_equal(first.points, again.points)
    np.testing.assert_array_equal(first.boxes, again.boxes)
    assert fuzz.make_case(CI_SEED + 1, 17, max_n=CI_MAX_N).points.tobytes() != first.points.tobytes()


def test_cases_are_valid_inputs_in_their_dtype():
    """Every valid case's points and boxes are values of its dtype, each
    point inside its cloud's box, each box non-flat; the batch is sorted."""
    for index in range(2 * len(fuzz.KINDS)):
        case = fuzz.make_case(CI_SEED, index, max_n=CI_MAX_N)
        if case.expect_error:
            continue
        np_dtype = np.float32 if case.dtype == torch.float32 else np.float64
        np.testing.assert_array_equal(case.points.astype(np_dtype).astype(np.float64), case.points)
        np.testing.assert_array_equal(case.boxes.astype(np_dtype).astype(np.float64), case.boxes)
        if case.batch is not None:
            assert np.all(np.diff(case.batch) >= 0)
        for _, members, (lo, hi) in case.clouds():
            assert np.all(hi > lo), case.describe()
            assert np.all(case.points[members] >= lo) and np.all(case.points[members] <= hi), case.describe()


def _corrupting(monkeypatch, change, periodic=False, power=False):
    """fuzz's torchvor.voronoi replaced by one whose result `change` edits
    (the periodic calls' only with `periodic`, the power calls' only with
    `power`, else the others')."""
    real = torchvor.voronoi

    def voronoi(*args, **kwargs):
        cells = real(*args, **kwargs)
        if bool(kwargs.get("periodic")) != periodic or (kwargs.get("weights") is not None) != power:
            return cells
        cells = torchvor.VoronoiCells(*(t.clone() for t in cells))
        change(cells)
        return cells

    monkeypatch.setattr(fuzz.torchvor, "voronoi", voronoi)


def _white_noise_case():
    index = list(fuzz.KINDS).index("white_noise") + len(fuzz.KINDS)  # the second round: float64
    case = fuzz.make_case(CI_SEED, index, max_n=CI_MAX_N)
    assert case.kind == "white_noise" and case.dtype == torch.float64 and case.n > 20
    return index


def test_fuzzer_flags_a_silently_wrong_cell(monkeypatch):
    """The largest cell's volume 1e-5 too large (status SUCCESS): the oracle
    (which samples the largest cell) and the volume sum both catch it."""
    index = _white_noise_case()

    def change(cells):
        cells.volume[int(torch.argmax(cells.volume))] *= 1 + 1e-5

    _corrupting(monkeypatch, change)
    report = fuzz.run_campaign(CI_SEED, [index], max_n=CI_MAX_N)
    assert report.counts["silently_wrong"] == 1 and report.counts["wrong_volume_sums"] == 1
    assert not report.ok()
    wrong = [p for p in report.problems if p.category == "silently_wrong"]
    assert "volume" in wrong[0].message and f"--case {index}" in wrong[0].replay


def test_fuzzer_flags_a_silently_wrong_periodic_cell(monkeypatch):
    """A periodic cell's volume 1e-5 too large: the volume sum and, where the
    oracle samples it, the oracle over the images catch it."""
    index = _white_noise_case()

    def change(cells):
        cells.volume[:] *= 1 + 1e-5

    _corrupting(monkeypatch, change, periodic=True)
    report = fuzz.run_campaign(CI_SEED, [index], max_n=CI_MAX_N)
    assert report.counts["wrong_volume_sums"] == 1 and report.counts["silently_wrong"] >= 1
    assert any(p.cells_impl == "periodic" for p in report.problems) and not report.ok()


def test_fuzzer_flags_a_silently_wrong_power_cell(monkeypatch):
    """A power cell's volume 1e-5 too large: the volume sum and, where the
    oracle samples it, the oracle with power bisectors catch it."""
    index = _white_noise_case()

    def change(cells):
        cells.volume[:] *= 1 + 1e-5

    _corrupting(monkeypatch, change, power=True)
    report = fuzz.run_campaign(CI_SEED, [index], max_n=CI_MAX_N)
    assert report.counts["wrong_volume_sums"] == 1 and report.counts["silently_wrong"] >= 1
    assert any(p.cells_impl == "power" for p in report.problems) and not report.ok()


def test_fuzzer_checks_float32_suspects(monkeypatch):
    """In float32, the cell whose volume differs most from torchvor's float64
    cell of the same points goes to the oracle even outside the sample:
    the smallest cell 1e-3 too large is caught with no sampled cell."""
    index = list(fuzz.KINDS).index("white_noise")  # the first round: float32
    case = fuzz.make_case(CI_SEED, index, max_n=CI_MAX_N)
    assert case.dtype == torch.float32 and case.n > 20

    def change(cells):
        if cells.volume.dtype == torch.float32:  # not the float64 cells it is compared with
            cells.volume[int(torch.argmin(cells.volume))] *= 1 + 1e-3

    _corrupting(monkeypatch, change)
    report = fuzz.run_campaign(CI_SEED, [index], max_n=CI_MAX_N, sample=0)
    assert report.counts["silently_wrong"] == 1
    assert "volume" in report.problems[0].message


def test_fuzzer_flags_failed_cells_and_false_duplicates(monkeypatch):
    """A cell with a failure status is counted as failed; a DUPLICATE status
    on a point that has no copy is silently wrong."""
    index = _white_noise_case()

    def change(cells):
        cells.status[0] = CellStatus.BOUNDARY_ERROR
        cells.volume[0] = float("nan")
        cells.status[1] = CellStatus.DUPLICATE

    _corrupting(monkeypatch, change)
    report = fuzz.run_campaign(CI_SEED, [index], max_n=CI_MAX_N, sample=0)
    assert report.counts["failed_cells"] == 1
    assert report.counts["silently_wrong"] == 1
    assert not report.ok()


def test_fuzzer_flags_unexpected_exceptions(monkeypatch):
    """An exception from a valid input is counted; so are an invalid input
    whose error is not a ValueError naming its cause, and one that raises
    nothing."""
    index = _white_noise_case()
    invalid = fuzz.INVALID_EVERY - 1
    assert fuzz.make_case(CI_SEED, invalid, max_n=CI_MAX_N).expect_error

    def boom(*args, **kwargs):
        raise RuntimeError("boom")

    monkeypatch.setattr(fuzz.torchvor, "voronoi", boom)
    report = fuzz.run_campaign(CI_SEED, [index, invalid], max_n=CI_MAX_N)
    # the valid case's plain, periodic and power calls, and the invalid case's
    assert report.counts["unexpected_exceptions"] == 4 and report.counts["expected_errors"] == 0
    assert all("boom" in p.message for p in report.problems)
    monkeypatch.setattr(fuzz.torchvor, "voronoi", lambda *args, **kwargs: None)
    report = fuzz.run_campaign(CI_SEED, [invalid], max_n=CI_MAX_N)
    assert report.counts["unexpected_exceptions"] == 1
    assert "raised no ValueError" in report.problems[0].message


def test_cells_impl_is_restored(monkeypatch):
    """A run under TORCHVOR_CELLS=thread or =cooperative leaves the variable
    as it found it, set or unset."""
    monkeypatch.setenv("TORCHVOR_CELLS", "thread")
    with fuzz._cells_impl("cooperative"):
        assert fuzz.os.environ["TORCHVOR_CELLS"] == "cooperative"
    assert fuzz.os.environ["TORCHVOR_CELLS"] == "thread"
    monkeypatch.delenv("TORCHVOR_CELLS")
    with fuzz._cells_impl("thread"):
        assert fuzz.os.environ["TORCHVOR_CELLS"] == "thread"
    assert "TORCHVOR_CELLS" not in fuzz.os.environ


def test_comparison_with_the_cpu_flags_differences():
    """The CUDA run's comparison with the CPU (here CPU against CPU): equal
    results pass; a status or a volume beyond the tolerance is flagged."""
    index = _white_noise_case()
    case = fuzz.make_case(CI_SEED, index, max_n=CI_MAX_N)
    campaign = fuzz.Campaign(CI_SEED, max_n=CI_MAX_N)
    points, box, batch = case.arguments("cpu")
    cells = torchvor.voronoi(points, box, batch=batch)
    campaign.compare_with_cpu(case, "default", cells)
    assert campaign.report.counts["silently_wrong"] == 0
    changed = torchvor.VoronoiCells(*(t.clone() for t in cells))
    changed.volume[3] *= 1 + 1e-8
    changed.status[5] = CellStatus.DUPLICATE
    campaign.compare_with_cpu(case, "default", changed)
    assert campaign.report.counts["silently_wrong"] == 2
    assert "differ from the CPU's" in campaign.report.problems[0].message


def test_workers_report_as_one_campaign(tmp_path):
    """--workers: the cases split over processes, one report whose counts
    are those of the same cases run in one process."""
    out = tmp_path / "fuzz.json"
    assert fuzz.main(["--seed", str(CI_SEED), "--cases", "6", "--max-n", "300", "--workers", "2",
                      "--quiet", "--json", str(out)]) == 0
    merged = json.loads(out.read_text())
    alone = fuzz.run_campaign(CI_SEED, range(6), max_n=300)
    assert merged["counts"] == alone.counts
    assert merged["per_kind"] == alone.per_kind


def test_workers_claim_each_case_once_in_order(tmp_path):
    """ClaimedCases: processes sharing a counter take the range's cases in
    order, each once, whichever asks next (a budget cuts the range at one place)."""
    counter = tmp_path / "next"
    counter.write_text("0")
    first = iter(fuzz_workers.ClaimedCases(range(10, 17), str(counter)))
    second = iter(fuzz_workers.ClaimedCases(range(10, 17), str(counter)))
    taken = [next(first), next(second), next(second), next(first)]
    taken += list(second) + list(first)
    assert taken == list(range(10, 17))
