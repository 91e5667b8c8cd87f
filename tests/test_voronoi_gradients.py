"""Gradients of voronoi's volume, centroid and second moment with respect to the
points: gradcheck (finite differences in float64), and the CVT energy's closed form."""
from __future__ import annotations

import pytest
import torch

import torchvor

UNIT = ([0.0, 0.0, 0.0], [1.0, 1.0, 1.0])


def rand(n, gen, dtype, device, lo=0.0, hi=1.0):
    return (lo + (hi - lo) * torch.rand(n, 3, generator=gen, dtype=torch.float64)).to(dtype).to(device)


@pytest.mark.parametrize("output", ["volume", "centroid", "second_moment"])
def test_gradcheck(device, gen, output):
    """Finite differences of each output against the face formulas (random
    points: the faces do not change under the small steps)."""
    points = rand(40, gen, torch.float64, device).requires_grad_()
    torch.autograd.gradcheck(lambda x: getattr(torchvor.voronoi(x, UNIT), output), (points,),
                             eps=1e-7, atol=1e-6, rtol=1e-4)


def test_gradcheck_batch_and_box(device, gen):
    """Two clouds in an offset anisotropic box each: every output at once."""
    box = torch.tensor([[[10.0, -2.0, 0.5], [12.0, -1.5, 3.5]]] * 2, dtype=torch.float64, device=device)
    lo, hi = box[0, 0].cpu(), box[0, 1].cpu()
    points = (lo + (hi - lo) * torch.rand(50, 3, generator=gen, dtype=torch.float64)).to(device).requires_grad_()
    batch = torch.repeat_interleave(torch.arange(2), torch.tensor([30, 20])).to(device)

    def outputs(x):
        cells = torchvor.voronoi(x, box, batch=batch)
        return cells.volume, cells.centroid, cells.second_moment

    torch.autograd.gradcheck(outputs, (points,), eps=1e-8, atol=1e-6, rtol=1e-4)


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


def edge_formula_gradients(points, box, batch, output_grads):
    """The backward by another route: voronoi_graph's symmetric faces (area,
    centroid, moments u u^T and |u|^2 u) and GRADIENTS.md's formulas as tensor
    operations over the edges j -> i, float64. `output_grads` are the
    gradients of volume, centroid and second moment (None: zero)."""
    x = points.double()
    n = x.shape[0]
    out = torch.ops.torchvor.voronoi_graph.default(x, box.double(), batch, None, 1 << 30, True)
    volume, centroid = out[0], out[1]
    (j, i), area, face_centroid, moments = out[6], out[7], out[8], out[10]
    g_m, g_c, g_i = (g.double() if g is not None else x.new_zeros(shape)
                     for g, shape in zip(output_grads, [(n,), (n, 3), (n,)]))
    filled = volume > 0
    m = torch.where(filled, volume, torch.ones_like(volume))
    offset = centroid - x
    G = torch.where(filled[:, None], g_c / m[:, None], torch.zeros_like(g_c))
    g_m = g_m - torch.where(filled, (g_c * offset).sum(1) / m, torch.zeros_like(g_m))
    grad = -(2 * g_i * torch.where(filled, volume, torch.zeros_like(volume)))[:, None] * offset
    d = (x[j] - x[i]).norm(dim=1)[:, None]
    w_i, w_j = face_centroid - x[i], face_centroid - x[j]
    S = torch.stack([moments[:, [0, 3, 4]], moments[:, [3, 1, 5]], moments[:, [4, 5, 2]]], 1)  # (E, 3, 3)
    T = moments[:, 6:9]
    a = area[:, None]
    SG = (S @ G[i][:, :, None])[:, :, 0]
    Gw = (G[i] * w_i).sum(1, keepdim=True)
    Q = S.diagonal(dim1=1, dim2=2).sum(1, keepdim=True) + a * (w_i * w_i).sum(1, keepdim=True)
    R = T + 2 * (S @ w_i[:, :, None])[:, :, 0]
    gm, gi = g_m[i][:, None], g_i[i][:, None]
    to_j = -(gm * a * w_j + SG + a * Gw * w_j + gi * (R + Q * w_j)) / d
    to_i = (gm * a * w_i + SG + a * Gw * w_i + gi * (R + Q * w_i)) / d
    return grad.index_add(0, j, to_j).index_add(0, i, to_i)


@pytest.mark.parametrize("kind", ["white", "float32", "clusters", "slab", "close_pairs", "batch"])
def test_backward_equals_the_edge_formula(device, gen, kind):
    """The backward, which sums each cell's faces as it computes them, against
    the same formulas over voronoi_graph's edges, for each output alone and
    all three at once (thousands of cells: recovery, clusters, batches)."""
    n = 3000
    box = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]], dtype=torch.float64)
    batch = None
    if kind in ("white", "float32"):
        points = torch.rand(n, 3, generator=gen, dtype=torch.float64)
    elif kind == "clusters":
        centres = torch.rand(12, 3, generator=gen, dtype=torch.float64)
        points = centres[torch.randint(0, 12, (n,), generator=gen)] + 0.01 * torch.randn(n, 3, generator=gen,
                                                                                          dtype=torch.float64)
        points = torch.unique(points.clamp(0.0, 1.0), dim=0)  # no exact copies
    elif kind == "slab":  # needle-like cells between planes 1e-3 apart
        points = torch.rand(n, 3, generator=gen, dtype=torch.float64) * torch.tensor([1.0, 1.0, 1e-3],
                                                                                       dtype=torch.float64)
    elif kind == "close_pairs":  # faces between points 1e-7 apart
        half = torch.rand(n // 2, 3, generator=gen, dtype=torch.float64) * 0.999
        points = torch.cat([half, half + 1e-7 * torch.rand(n // 2, 3, generator=gen, dtype=torch.float64)])
    else:
        box = torch.tensor([[[10.0, -2.0, 0.5], [12.0, -1.5, 3.5]], [[0.0, 0.0, 0.0], [1.0, 2.0, 1.0]]],
                           dtype=torch.float64)
        counts = torch.tensor([1800, 1200])
        batch = torch.repeat_interleave(torch.arange(2), counts)
        lo, hi = box[batch, 0], box[batch, 1]
        points = lo + (hi - lo) * torch.rand(n, 3, generator=gen, dtype=torch.float64)
    n = points.shape[0]
    points, box = points.to(device), box.to(device)
    batch = batch.to(device) if batch is not None else None
    weights = [torch.randn(n, generator=gen, dtype=torch.float64).to(device),
               torch.randn(n, 3, generator=gen, dtype=torch.float64).to(device),
               torch.randn(n, generator=gen, dtype=torch.float64).to(device)]
    if kind == "float32":  # computed as float64 from the float32 coordinates, rounded back
        points, box = points.float(), box.float()
    for used in ([0], [1], [2], [0, 1, 2]):
        x = points.clone().requires_grad_()
        cells = torchvor.voronoi(x, box, batch=batch)
        outputs = [cells.volume, cells.centroid, cells.second_moment]
        sum(((outputs[o].double() * weights[o]).sum() for o in used)).backward()
        expected = edge_formula_gradients(points, box, batch, [weights[o] if o in used else None for o in range(3)])
        scale = expected.abs().max().item()
        assert torch.isfinite(x.grad).all()
        # float32: the chain rule reads the forward's float32 volumes and
        # centroids (c - x loses ~eps32 |c| / |c - x|, about 1e-6 here), which
        # the backend rounds its own way.
        tol = 1e-5 if kind == "float32" else 1e-9
        assert (x.grad.double() - expected).abs().max().item() <= tol * scale, used


def test_backward_with_and_without_moments_agree(device, gen):
    """The volumes' backward without the faces' moments (kernels of their own
    on the GPU) and with them (zero centroid and second-moment gradients)
    sum the same terms: equal to rounding."""
    n = 3000
    points = rand(n, gen, torch.float64, device)
    box = torch.tensor([UNIT], dtype=torch.float64, device=device)
    upstream = torch.zeros(n, 5, dtype=torch.float64)
    upstream[:, 0] = torch.randn(n, generator=gen, dtype=torch.float64)
    upstream = upstream.to(device)
    backward = torch.ops.torchvor.voronoi_cells_backward.default
    without = backward(points, box, None, None, 1 << 30, upstream, False)
    with_moments = backward(points, box, None, None, 1 << 30, upstream, True)
    assert torch.isfinite(without).all()
    torch.testing.assert_close(without, with_moments, rtol=0, atol=1e-12 * without.abs().max().item())


def test_backward_is_deterministic(device, gen):
    """Each point's gradient is summed by its own cell (no atomic adds): two
    backward passes agree bit for bit."""
    points = rand(5000, gen, torch.float64, device)
    weights = torch.randn(5000, 3, generator=gen, dtype=torch.float64).to(device)
    grads = []
    for _ in range(2):
        x = points.clone().requires_grad_()
        cells = torchvor.voronoi(x, UNIT)
        ((cells.centroid * weights).sum() + cells.volume.sum() + (cells.second_moment * weights[:, 0]).sum()).backward()
        grads.append(x.grad)
    assert torch.equal(grads[0], grads[1])
