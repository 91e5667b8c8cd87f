"""Gradients of voronoi's volume, centroid and second moment with respect to the
points: gradcheck (finite differences in float64), and the CVT energy's closed form."""
from __future__ import annotations

import pytest
import torch

import torchvor

UNIT = ([0.0, 0.0, 0.0], [1.0, 1.0, 1.0])


def rand(n, gen, dtype, device, lo=0.0, hi=1.0):
    return (lo + (hi - lo) * torch.rand(n, 3, generator=gen, dtype=torch.float64)).to(dtype).to(device)


# On CUDA the backward sums the faces' terms with atomic adds (index_add): two
# runs may differ in the last bits.
NONDETERMINISM = {"cpu": 0.0, "cuda": 1e-12}


@pytest.mark.parametrize("output", ["volume", "centroid", "second_moment"])
def test_gradcheck(device, gen, output):
    """Finite differences of each output against the face formulas (random
    points: the faces do not change under the small steps)."""
    points = rand(40, gen, torch.float64, device).requires_grad_()
    torch.autograd.gradcheck(lambda x: getattr(torchvor.voronoi(x, UNIT), output), (points,),
                             eps=1e-7, atol=1e-6, rtol=1e-4, nondet_tol=NONDETERMINISM[device.type])


def test_gradcheck_batch_and_box(device, gen):
    """Two clouds in an offset anisotropic box each: every output at once."""
    box = torch.tensor([[[10.0, -2.0, 0.5], [12.0, -1.5, 3.5]]] * 2, dtype=torch.float64, device=device)
    lo, hi = box[0, 0].cpu(), box[0, 1].cpu()
    points = (lo + (hi - lo) * torch.rand(50, 3, generator=gen, dtype=torch.float64)).to(device).requires_grad_()
    batch = torch.repeat_interleave(torch.arange(2), torch.tensor([30, 20])).to(device)

    def outputs(x):
        cells = torchvor.voronoi(x, box, batch=batch)
        return cells.volume, cells.centroid, cells.second_moment

    torch.autograd.gradcheck(outputs, (points,), eps=1e-8, atol=1e-6, rtol=1e-4,
                             nondet_tol=NONDETERMINISM[device.type])


def test_energy_gradient_has_the_closed_form(device, dtype, gen):
    """d/dx_i of the CVT energy (the sum of second moments) is 2 m_i (x_i - c_i):
    the faces' terms cancel between neighbours."""
    points = rand(300, gen, dtype, device).requires_grad_()
    cells = torchvor.voronoi(points, UNIT)
    cells.second_moment.sum().backward()
    expected = 2 * cells.volume.detach()[:, None] * (points.detach() - cells.centroid.detach())
    tol = 1e-4 if dtype == torch.float32 else 1e-10
    scale = expected.abs().max().item()
    assert (points.grad - expected).abs().max().item() <= tol * scale
    assert points.grad.dtype == dtype


def test_volumes_sum_to_the_box_whatever_the_points(device, dtype, gen):
    """The volumes sum to the box's volume for any points: the sum's gradient is zero."""
    points = rand(200, gen, dtype, device).requires_grad_()
    torchvor.voronoi(points, UNIT).volume.sum().backward()
    assert points.grad.abs().max().item() <= (1e-5 if dtype == torch.float32 else 1e-12)


def test_float32_gradients_follow_float64(device, gen):
    points = rand(200, gen, torch.float64, device)
    grads = []
    for dtype in (torch.float64, torch.float32):
        x = points.to(dtype).detach().clone().requires_grad_()
        cells = torchvor.voronoi(x, UNIT)
        weights = torch.linspace(-1, 1, 200, dtype=dtype, device=device)
        (cells.volume * weights).sum().add((cells.centroid.sum(1) * weights).sum()).backward()
        grads.append(x.grad.double())
    assert (grads[1] - grads[0]).abs().max().item() <= 1e-3 * grads[0].abs().max().item()


def test_status_and_neighbours_are_not_differentiable(device, gen):
    points = rand(30, gen, torch.float64, device).requires_grad_()
    cells = torchvor.voronoi(points, UNIT)
    assert cells.volume.requires_grad and cells.centroid.requires_grad and cells.second_moment.requires_grad
    assert not cells.status.requires_grad and not cells.neighbors_needed.requires_grad


def test_compiled_backward(device, gen):
    """The backward traces under torch.compile(fullgraph=True) and gives the eager gradient."""
    torch._dynamo.reset()
    weights = torch.linspace(-1, 1, 100, dtype=torch.float64, device=device)

    def loss(x):
        cells = torchvor.voronoi(x, UNIT, on_failure="flag")
        return (cells.volume * weights).sum() + (cells.centroid.sum(1) * weights).sum() + cells.second_moment.sum()

    points = rand(100, gen, torch.float64, device)
    x = points.clone().requires_grad_()
    (expected,) = torch.autograd.grad(loss(x), x)
    y = points.clone().requires_grad_()
    (got,) = torch.autograd.grad(torch.compile(loss, fullgraph=True)(y), y)
    torch.testing.assert_close(got, expected)
