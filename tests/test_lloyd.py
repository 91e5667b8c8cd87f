"""Lloyd relaxation, the CVT energy op and the LloydRelaxation module.

The `device` fixture (conftest.py) runs tests on "cpu" and, when available, "cuda"."""
import math
import sys

import pytest
import torch

import torchvor
from torchvor import samples
from torchvor.cvt import _cvt_energy_op, cvt_energy
from torchvor.lloyd import LloydStep, lloyd
from torchvor.ops import _voronoi_in_grid_order
from torchvor.nn import LloydRelaxation

UNIT_BOX = ([0.0, 0.0, 0.0], [1.0, 1.0, 1.0])


def unit_box_tensor(dtype=torch.float64, device="cpu"):
    return torch.tensor([[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]], dtype=dtype, device=device)


def separated_points(device, dtype=torch.float64):
    """A 4x4x4 grid jittered by at most 0.15 cells: cells stay combinatorially
    stable under finite-difference steps, so gradcheck compares smooth values."""
    return samples.jittered_grid(64, amplitude=0.15, seed=3, dtype=dtype, device=device)


# ---- lloyd ----------------------------------------------------------------------------


def test_energy_decreases_monotonically_on_white_noise(device):
    points = samples.white_noise(1000, seed=1, dtype=torch.float64, device=device)
    _, history = lloyd(points, UNIT_BOX, iters=8, return_history=True)
    energies = [step.energy for step in history]
    assert len(energies) == 8
    for before, after in zip(energies, energies[1:]):
        assert after <= before * (1 + 1e-12), energies
    assert energies[-1] < 0.9 * energies[0]


def test_energy_of_an_iteration_is_the_sum_of_its_second_moments(device):
    points = samples.white_noise(500, seed=2, dtype=torch.float64, device=device)
    moved, history = lloyd(points, UNIT_BOX, iters=1, return_history=True)
    cells = torchvor.voronoi(points, UNIT_BOX)
    assert history[0].energy == pytest.approx(float(cells.second_moment.sum()), rel=1e-12, abs=0)
    torch.testing.assert_close(moved, cells.centroid, rtol=0, atol=1e-15)


def test_neighbors_needed_is_the_99th_percentile(device):
    points = samples.white_noise(700, seed=4, dtype=torch.float64, device=device)
    _, history = lloyd(points, UNIT_BOX, iters=1, k=20, return_history=True)
    needed = torch.sort(torchvor.voronoi(points, UNIT_BOX, k=20).neighbors_needed.cpu()).values
    assert history[0].neighbors_needed == int(needed[math.ceil(0.99 * 700) - 1])


def test_neighbors_needed_from_a_strided_sample_beyond_the_sample_size(device, monkeypatch):
    """The sample strides over the cells in lloyd's (grid) order."""
    lloyd_module = sys.modules["torchvor.lloyd"]
    monkeypatch.setattr(lloyd_module, "QUANTILE_SAMPLE", 100)
    points = samples.white_noise(700, seed=6, dtype=torch.float64, device=device)
    _, history = lloyd(points, UNIT_BOX, iters=1, k=20, return_history=True)
    cells, _ = _voronoi_in_grid_order(points, unit_box_tensor(device=device), k=20)
    sample = torch.sort(cells.neighbors_needed.cpu()[::7]).values
    assert history[0].neighbors_needed == int(sample[math.ceil(0.99 * 100) - 1])


def test_failed_cell_keeps_its_point(device, monkeypatch):
    """A cell that cannot be computed (NaN outputs and a failure status, as
    torchvor.voronoi leaves it) warns, keeps its point, and makes the energy NaN;
    every other point moves to its centroid. The op's test hook drops one
    cell's first-pass result, so lloyd_step also launches its tail again
    after that cell's outputs are poisoned. On a jittered lattice every cell
    succeeds in the first pass, so no retry recomputes the dropped one."""
    points = samples.jittered_grid(125, amplitude=0.1, seed=5, dtype=torch.float64, device=device)
    cells = torchvor.voronoi(points, UNIT_BOX, k=26)
    _, order = _voronoi_in_grid_order(points, unit_box_tensor(device=device), None, 26)
    position = 37
    row = int(order[position])  # the caller's point whose cell the hook drops
    monkeypatch.setenv("TORCHVOR_TEST_UNWRITTEN_CELL", str(position))
    with pytest.warns(RuntimeWarning, match="1 cell"):
        moved, history = lloyd(points, UNIT_BOX, iters=1, k=26, return_history=True)
    assert history[0].failed == 1 and math.isnan(history[0].energy)
    assert torch.equal(moved[row], points[row])
    others = torch.arange(125, device=device) != row
    torch.testing.assert_close(moved[others], cells.centroid[others], rtol=0, atol=1e-15)
    expected = (cells.centroid[others] - points[others]).norm(dim=1).max().item() / 3 ** 0.5
    assert history[0].max_displacement == pytest.approx(expected, rel=1e-12, abs=0)


def test_lattice_is_a_fixed_point(device):
    m = 5
    points = samples.lattice(m, dtype=torch.float64, device=device)
    relaxed, history = lloyd(points, UNIT_BOX, iters=3, return_history=True)
    assert (relaxed - points).abs().max().item() <= 1e-12
    # Every cell is a cube of side h = 1/m: second moment h^5 / 4, energy h^2 / 4.
    assert history[0].energy == pytest.approx(1 / (4 * m * m), rel=1e-12, abs=0)


def test_output_is_new_and_keeps_shape_dtype_device(device):
    for dtype in (torch.float32, torch.float64):
        points = samples.white_noise(300, seed=4, dtype=dtype, device=device).requires_grad_()
        original = points.detach().clone()
        relaxed = lloyd(points, iters=2)
        assert relaxed.shape == points.shape and relaxed.dtype == dtype and relaxed.device == points.device
        assert not relaxed.requires_grad
        assert torch.equal(points.detach(), original)
        assert not torch.equal(relaxed, original)


def test_box_defaults_to_the_input_bounding_box_and_stays_fixed(device):
    points = samples.white_noise(400, seed=5, dtype=torch.float64, device=device) * 2 - 1
    lower, upper = points.amin(0), points.amax(0)
    relaxed = lloyd(points, iters=3)
    explicit = lloyd(points, (lower, upper), iters=3)
    torch.testing.assert_close(relaxed, explicit, rtol=0, atol=0)
    assert bool((relaxed >= lower).all() and (relaxed <= upper).all())


def test_adaptive_k_shrinks_once_white_noise_becomes_regular(device):
    points = samples.white_noise(2000, seed=6, device=device)
    _, history = lloyd(points, UNIT_BOX, iters=6, return_history=True)
    ks = [step.k for step in history]
    # Each k is derived from what the previous iteration's cells needed ...
    for step, following in zip(history, history[1:]):
        assert following.k == max(8, min(256, step.neighbors_needed + 2))
    # ... and relaxed cells need far fewer neighbours than white noise ones.
    assert ks[-1] < ks[1]
    assert ks[-1] < ks[0]
    assert history[-1].neighbors_needed < history[0].neighbors_needed


def pilot_k_at_quantile_one(neighbors: torch.Tensor) -> int:
    """The pilot's first-pass k under TORCHVOR_PILOT_QUANTILE=1 when every cell
    is in its sample (fewer than 2048 points): the most neighbours a cell
    needed, capped at the pilot's own k (64), plus 2, at least 8."""
    return max(8, min(64, int(neighbors.max())) + 2)


@pytest.mark.parametrize("kind", ["white", "jittered"])
def test_first_iteration_takes_the_pilots_k(monkeypatch, device, kind):
    """With k=None the first iteration's k is the op's pilot's: under
    TORCHVOR_PILOT_QUANTILE=1 and fewer than 2048 points (every cell in the
    pilot's sample), the most neighbours a cell needed, capped at the pilot's
    64, plus 2. Relaxed points thus start small instead of at white noise's k."""
    monkeypatch.setenv("TORCHVOR_PILOT_QUANTILE", "1")
    if kind == "white":
        points = samples.white_noise(1500, seed=30, dtype=torch.float64, device=device)
    else:
        points = samples.jittered_grid(1000, amplitude=0.3, seed=31, dtype=torch.float64, device=device)
    needed = torchvor.voronoi(points, UNIT_BOX, k=256).neighbors_needed
    _, history = lloyd(points, UNIT_BOX, iters=2, return_history=True)
    assert history[0].k == pilot_k_at_quantile_one(needed)
    assert history[1].k == max(8, min(256, history[0].neighbors_needed + 2))
    if kind == "jittered":
        assert history[0].k < 50  # far below white noise's ~66


def test_first_pass_k_is_capped_by_the_cloud(device):
    """A cloud of fewer points than k asks each cell for all the others: the
    history reports the k the first pass used."""
    points = samples.white_noise(6, seed=32, dtype=torch.float64, device=device)
    for k in (None, 40):
        _, history = lloyd(points, UNIT_BOX, iters=1, k=k, return_history=True)
        assert history[0].k == 6


def test_fixed_k_gives_the_same_points(device):
    points = samples.white_noise(500, seed=7, dtype=torch.float64, device=device)
    adaptive = lloyd(points, UNIT_BOX, iters=3)
    fixed, history = lloyd(points, UNIT_BOX, iters=3, k=12, return_history=True)
    assert [step.k for step in history] == [12, 12, 12]
    torch.testing.assert_close(adaptive, fixed, rtol=0, atol=1e-14)


def test_tol_stops_at_the_first_small_move(device):
    points = samples.white_noise(500, seed=8, dtype=torch.float64, device=device)
    _, full = lloyd(points, UNIT_BOX, iters=12, return_history=True)
    displacements = [step.max_displacement for step in full]
    tol = 0.4 * displacements[0]
    expected = next(i for i, d in enumerate(displacements) if d < tol) + 1
    assert expected < len(full)
    relaxed, stopped = lloyd(points, UNIT_BOX, iters=12, tol=tol, return_history=True)
    assert len(stopped) == expected
    assert stopped[-1].max_displacement < tol
    # The stopping iteration's move is kept.
    torch.testing.assert_close(relaxed, lloyd(points, UNIT_BOX, iters=expected), rtol=0, atol=0)


def test_callback_sees_every_iteration_and_can_stop(device):
    points = samples.white_noise(300, seed=9, device=device)
    seen = []

    def callback(iteration, moved, cells):
        seen.append((iteration, moved.shape, cells.volume.shape))
        return iteration == 1  # stop after the second iteration

    _, history = lloyd(points, UNIT_BOX, iters=10, callback=callback, return_history=True)
    assert seen == [(0, (300, 3), (300,)), (1, (300, 3), (300,))]
    assert len(history) == 2 and all(isinstance(step, LloydStep) for step in history)


def test_iterations_match_a_loop_of_voronoi_calls(device):
    """lloyd keeps its points in grid order between iterations and returns them
    in the caller's: the same points as moving every point to its centroid with
    torchvor.voronoi, up to rounding (a pair of exactly equidistant neighbours
    may be clipped in another order). With exact duplicates, the lowest index
    keeps the cell (the others stay put) in both."""
    points = samples.white_noise(600, seed=21, dtype=torch.float64, device=device)
    points[500:520] = points[40:60]
    expected = points
    for _ in range(4):
        expected = torchvor.voronoi(expected, UNIT_BOX, k=16).centroid.clamp(0, 1)
    torch.testing.assert_close(lloyd(points, UNIT_BOX, iters=4, k=16), expected, rtol=0, atol=1e-12)


def test_callback_sees_the_callers_order(device):
    points = samples.white_noise(400, seed=22, dtype=torch.float64, device=device)
    seen = []

    def callback(iteration, moved, cells):
        seen.append((moved.clone(), cells))

    relaxed = lloyd(points, UNIT_BOX, iters=3, k=16, callback=callback)
    before = points
    for moved, cells in seen:
        reference = torchvor.voronoi(before, UNIT_BOX, k=16)
        for name in ("volume", "centroid", "second_moment", "status", "neighbors_needed", "radius"):
            torch.testing.assert_close(getattr(cells, name), getattr(reference, name), rtol=0, atol=1e-13)
        torch.testing.assert_close(moved, cells.centroid.clamp(0, 1), rtol=0, atol=0)
        before = moved
    assert torch.equal(relaxed, seen[-1][0])


# ---- lloyd_step (one iteration in one op: the cells in grid order, the move, its measures) ----


VoronoiCellsFields = ("volume", "centroid", "second_moment", "status", "neighbors_needed", "radius")


def expected_step(points, box, batch, k, stride, bins):
    """lloyd_step's outputs from the grid-order voronoi op and tensor ops (an
    oracle for the move and the measures; the cells are the voronoi op's)."""
    cells, order = _voronoi_in_grid_order(points, box, batch, k)
    element = batch.index_select(0, order) if batch is not None else torch.zeros_like(order)
    lower, upper = box[element, 0], box[element, 1]
    point = points.index_select(0, order)
    stays = ((cells.status != 0) & (cells.status != int(torchvor.CellStatus.DUPLICATE))).unsqueeze(1)
    moved = torch.where(stays, point, cells.centroid.clamp(lower, upper))
    displacement2 = (moved.double() - point.double()).square().sum(1) / (upper.double() - lower.double()).square().sum(1)
    measures = torch.tensor([cells.second_moment.double().sum().item(),
                             displacement2.max().item() if len(points) else 0.0], dtype=torch.float64)
    histogram = torch.histc(cells.neighbors_needed[::stride].double().cpu(), bins=bins, min=0, max=bins).int()
    return moved, cells, order, measures, histogram


def two_clouds(device, dtype):
    first = samples.white_noise(300, seed=21, dtype=dtype, device=device)
    second = samples.white_noise(200, seed=22, dtype=dtype, device=device) * 3 + 5
    boxes = torch.tensor([[[0.0] * 3, [1.0] * 3], [[5.0] * 3, [8.0] * 3]], dtype=dtype, device=device)
    batch = torch.cat([torch.zeros(300, dtype=torch.int64), torch.ones(200, dtype=torch.int64)]).to(device)
    return torch.cat([first, second]), boxes, batch


@pytest.mark.parametrize("speculative_cells", [None, "0", "16"])
@pytest.mark.parametrize("batched", [False, True])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_lloyd_step_against_the_voronoi_op_and_tensor_ops(device, dtype, batched, speculative_cells, monkeypatch):
    """The moved points (each centroid clamped into its box, or the point where
    its cell failed), the energy, the largest squared displacement over the
    squared box diagonal and the strided histogram of the neighbours needed,
    with the voronoi op's cells. k=8 on white noise fails many cells in the
    first pass: with the speculative retry on (default), off (0) and
    overflowing (16), the op launches its tail before the first status read
    and again after the later passes, whose results must be the final ones."""
    if speculative_cells is not None:
        monkeypatch.setenv("TORCHVOR_SPECULATIVE_CELLS", speculative_cells)
    if batched:
        points, box, batch = two_clouds(device, dtype)
    else:
        points, box, batch = samples.white_noise(600, seed=20, dtype=dtype, device=device), None, None
        box = unit_box_tensor(dtype, device)
    stride, bins = 3, 40
    moved, *outputs, order, measures, histogram = torch.ops.torchvor.lloyd_step(points, box, batch, 8, stride, bins)
    expected_moved, cells, expected_order, expected_measures, expected_histogram = expected_step(
        points, box, batch, 8, stride, bins)
    assert torch.equal(order, expected_order)
    for name, value in zip(VoronoiCellsFields, outputs):
        assert torch.equal(value, getattr(cells, name)), name
    assert torch.equal(moved, expected_moved)
    assert measures.device.type == "cpu" and measures.dtype == torch.float64 and measures.shape == (3,)
    torch.testing.assert_close(measures[:2], expected_measures, rtol=1e-12, atol=0)
    assert measures[2].item() == 8  # the first pass's k
    assert histogram.device.type == "cpu" and histogram.dtype == torch.int32
    assert torch.equal(histogram, expected_histogram)


@pytest.mark.parametrize("batched", [False, True])
def test_lloyd_step_without_k_runs_the_pilot(monkeypatch, device, batched):
    """k=None: the cells of the grid-order voronoi op without k (its pilot's
    first pass), and the pilot's k in measures[2]. Under
    TORCHVOR_PILOT_QUANTILE=1 with every cell in the pilot's sample (fewer
    than 2048 points) that k is the most neighbours a cell needed plus 2."""
    monkeypatch.setenv("TORCHVOR_PILOT_QUANTILE", "1")
    if batched:
        points, box, batch = two_clouds(device, torch.float64)
    else:
        points, batch = samples.jittered_grid(1000, amplitude=0.3, seed=26, dtype=torch.float64, device=device), None
        box = unit_box_tensor(torch.float64, device)
    moved, *outputs, order, measures, histogram = torch.ops.torchvor.lloyd_step(points, box, batch, None, 1, 80)
    expected_moved, cells, expected_order, expected_measures, expected_histogram = expected_step(
        points, box, batch, None, 1, 80)
    assert torch.equal(order, expected_order)
    for name, value in zip(VoronoiCellsFields, outputs):
        assert torch.equal(value, getattr(cells, name)), name
    assert torch.equal(moved, expected_moved)
    torch.testing.assert_close(measures[:2], expected_measures, rtol=1e-12, atol=0)
    assert torch.equal(histogram, expected_histogram)
    assert measures[2].item() == pilot_k_at_quantile_one(cells.neighbors_needed)


def test_lloyd_step_histogram_bins_edges(device):
    """Counts equal to histogram_bins go into the last bin, larger ones are left
    out (as torch.histc over [0, bins])."""
    points = samples.white_noise(400, seed=23, dtype=torch.float64, device=device)
    box = unit_box_tensor(device=device)
    cells, _ = _voronoi_in_grid_order(points, box, None, 16)
    needed = cells.neighbors_needed.cpu()
    bins = int(needed.median())
    *_, histogram = torch.ops.torchvor.lloyd_step(points, box, None, 16, 1, bins)
    expected = torch.bincount(needed[needed < bins], minlength=bins).int()
    expected[-1] += int((needed == bins).sum())
    assert torch.equal(histogram, expected)


def test_lloyd_step_empty_and_bad_inputs(device):
    box = unit_box_tensor(torch.float32, device)
    empty = torch.empty(0, 3, device=device)
    moved, volume, centroid, second_moment, status, neighbors, radius, order, measures, histogram = (
        torch.ops.torchvor.lloyd_step(empty, box, None, 8, 1, 16))
    assert moved.shape == (0, 3) and order.shape == (0,) and volume.shape == (0,)
    assert measures.tolist() == [0.0, 0.0, 0.0] and histogram.tolist() == [0] * 16
    points = samples.white_noise(50, seed=24, device=device)
    step = torch.ops.torchvor.lloyd_step
    with pytest.raises(ValueError, match="sample_stride must be >= 1"):
        step(points, box, None, 8, 0, 16)
    with pytest.raises(ValueError, match="histogram_bins must be in"):
        step(points, box, None, 8, 1, 0)
    with pytest.raises(ValueError, match="k must be"):
        step(points, box, None, 0, 1, 16)
    with pytest.raises(ValueError, match="inside box"):
        step(points + 2, box, None, 8, 1, 16)
    with pytest.raises(TypeError):
        step(points, box.double(), None, 8, 1, 16)


def test_lloyd_step_opcheck(device):
    for dtype in (torch.float32, torch.float64):
        points = samples.white_noise(60, seed=25, dtype=dtype, device=device)
        torch.library.opcheck(torch.ops.torchvor.lloyd_step.default,
                              (points, unit_box_tensor(dtype, device), None, 12, 2, 32))
        points, boxes, batch = two_clouds(device, dtype)
        torch.library.opcheck(torch.ops.torchvor.lloyd_step.default, (points, boxes, batch, 12, 1, 64))
        torch.library.opcheck(torch.ops.torchvor.lloyd_step.default, (points, boxes, batch, None, 1, 64))
    torch.library.opcheck(torch.ops.torchvor.lloyd_step.default,
                          (torch.empty(0, 3, device=device), unit_box_tensor(torch.float32, device), None, 8, 1, 8))


def test_progress_prints_one_line_per_iteration_to_stderr(capsys):
    lloyd(samples.white_noise(200, seed=10), UNIT_BOX, iters=3, progress=True)
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert captured.out == ""
    assert len(lines) == 3
    assert lines[0].startswith("lloyd 1/3") and "energy" in lines[0] and "displacement" in lines[0]


def test_batched_clouds_relax_independently(device):
    first = samples.white_noise(300, seed=11, dtype=torch.float64, device=device)
    second = samples.white_noise(200, seed=12, dtype=torch.float64, device=device) * 3 + 5
    boxes = torch.tensor([[[0.0] * 3, [1.0] * 3], [[5.0] * 3, [8.0] * 3]], dtype=torch.float64, device=device)
    batch = torch.cat([torch.zeros(300, dtype=torch.int64), torch.ones(200, dtype=torch.int64)]).to(device)
    together = lloyd(torch.cat([first, second]), boxes, iters=3, batch=batch)
    torch.testing.assert_close(together[:300], lloyd(first, boxes[0], iters=3), rtol=0, atol=1e-13)
    torch.testing.assert_close(together[300:], lloyd(second, boxes[1], iters=3), rtol=0, atol=1e-13)


def test_zero_iterations_return_a_copy():
    points = samples.white_noise(50)
    relaxed, history = lloyd(points, iters=0, return_history=True)
    assert history == [] and torch.equal(relaxed, points) and relaxed.data_ptr() != points.data_ptr()


def test_blue_noise_sample_uses_lloyd():
    points = samples.blue_noise(300, iters=2)
    assert points.shape == (300, 3)
    assert bool((points >= 0).all() and (points <= 1).all())


@pytest.mark.parametrize("arguments, error", [
    ((torch.zeros(10, 2),), ValueError),
    ((torch.zeros(10, 3, dtype=torch.int64),), TypeError),
    (([[0.0, 0.0, 0.0]],), TypeError),
    ((torch.rand(10, 3), None, -1), ValueError),
])
def test_bad_arguments_raise(arguments, error):
    with pytest.raises(error):
        lloyd(*arguments)


def test_points_outside_the_box_raise():
    with pytest.raises(ValueError, match="inside box"):
        lloyd(torch.rand(20, 3) + 2, UNIT_BOX)


# ---- LloydRelaxation -------------------------------------------------------------------


def test_module_matches_lloyd_and_blocks_gradients(device):
    points = samples.white_noise(400, seed=13, dtype=torch.float64, device=device).requires_grad_()
    module = LloydRelaxation(iters=3, box=UNIT_BOX)
    relaxed = module(points)
    torch.testing.assert_close(relaxed, lloyd(points, UNIT_BOX, iters=3), rtol=0, atol=0)
    assert not relaxed.requires_grad
    assert "iters=3" in repr(module)
    pipeline = torch.nn.Sequential(LloydRelaxation(iters=1), torch.nn.Flatten(0))
    assert pipeline(points).shape == (1200,)


def test_module_with_tol_and_batch():
    points = samples.jittered_grid(125, amplitude=0.05, seed=14, dtype=torch.float64)
    batch = torch.zeros(points.shape[0], dtype=torch.int64)
    relaxed = LloydRelaxation(iters=100, box=unit_box_tensor(), tol=1e-3)(points, batch)
    assert relaxed.shape == points.shape


# ---- cvt_energy ------------------------------------------------------------------------


def test_cvt_energy_is_the_sum_of_second_moments(device):
    points = samples.white_noise(500, seed=15, dtype=torch.float64, device=device)
    cells = torchvor.voronoi(points, UNIT_BOX)
    energy = cvt_energy(points, UNIT_BOX)
    assert energy.shape == () and energy.dtype == torch.float64 and energy.device == points.device
    assert energy.item() == pytest.approx(float(cells.second_moment.sum()), rel=1e-14, abs=0)


def test_cvt_energy_gradient_is_the_closed_form(device):
    points = samples.white_noise(500, seed=16, dtype=torch.float64, device=device).requires_grad_()
    cvt_energy(points, UNIT_BOX).backward()
    cells = torchvor.voronoi(points.detach(), UNIT_BOX)
    expected = 2 * cells.volume.unsqueeze(1) * (points.detach() - cells.centroid)
    torch.testing.assert_close(points.grad, expected, rtol=0, atol=1e-15)


def test_cvt_energy_gradcheck(device):
    points = separated_points(device).requires_grad_()
    box = unit_box_tensor(device=device)
    assert torch.autograd.gradcheck(lambda x: cvt_energy(x, box), (points,), eps=1e-6, atol=1e-5)


def test_box_gets_no_gradient(device):
    points = separated_points(device).requires_grad_()
    box = unit_box_tensor(device=device).requires_grad_()
    cvt_energy(points, box).backward()
    assert box.grad is None and points.grad is not None


def test_gradient_descent_on_cvt_energy_lowers_it():
    points = samples.white_noise(300, seed=17, dtype=torch.float64).requires_grad_()
    optimizer = torch.optim.SGD([points], lr=20.0)
    energies = []
    for _ in range(3):
        optimizer.zero_grad()
        energy = cvt_energy(points, UNIT_BOX)
        energy.backward()
        energies.append(energy.item())
        optimizer.step()
        with torch.no_grad():
            points.clamp_(0, 1)
    assert energies[2] < energies[1] < energies[0]


def test_cvt_energy_opcheck(device):
    points = separated_points(device).requires_grad_()
    box = unit_box_tensor(device=device)
    torch.library.opcheck(_cvt_energy_op, (points, box, None, 40))
    batch = torch.zeros(points.shape[0], dtype=torch.int64, device=device)
    torch.library.opcheck(_cvt_energy_op, (points.detach(), box, batch, 16))


@pytest.mark.parametrize("backend", ["aot_eager", "inductor"])
def test_cvt_energy_under_torch_compile_fullgraph(device, backend):
    torch._dynamo.reset()
    box = unit_box_tensor(device=device)
    compiled = torch.compile(lambda x: cvt_energy(x, box), fullgraph=True, backend=backend)
    points = separated_points(device).requires_grad_()
    energy = compiled(points)
    energy.backward()
    eager_points = points.detach().clone().requires_grad_()
    eager_energy = cvt_energy(eager_points, box)
    eager_energy.backward()
    torch.testing.assert_close(energy, eager_energy, rtol=1e-14, atol=0)
    torch.testing.assert_close(points.grad, eager_points.grad, rtol=1e-14, atol=1e-16)


def test_cvt_energy_compiles_with_dynamic_shapes_and_a_derived_box(device):
    torch._dynamo.reset()
    compiled = torch.compile(lambda x: cvt_energy(x), fullgraph=True, backend="aot_eager", dynamic=True)
    for n in (40, 70):
        points = samples.white_noise(n, seed=n, dtype=torch.float64, device=device).requires_grad_()
        energy = compiled(points)
        energy.backward()
        cells = torchvor.voronoi(points.detach())
        assert energy.item() == pytest.approx(float(cells.second_moment.sum()), rel=1e-14, abs=0)
        torch.testing.assert_close(points.grad, 2 * cells.volume.unsqueeze(1) * (points.detach() - cells.centroid),
                                   rtol=0, atol=1e-15)
