"""torchvor.pyg transforms: with PyTorch Geometric where it is installed, and on
any object with `pos` (and `batch`) without it."""
from __future__ import annotations

import types

import pytest
import torch

import torchvor
from torchvor.pyg import KNNGraph, RadiusGraph, VoronoiGraph


def rand(n, gen, dtype, device):
    return torch.rand(n, 3, generator=gen, dtype=torch.float64).to(dtype).to(device)


def lengths(pos, edge_index):
    return (pos[edge_index[0]] - pos[edge_index[1]]).norm(dim=-1, keepdim=True)


@pytest.mark.parametrize("transform", [KNNGraph(k=5), RadiusGraph(r=0.25), KNNGraph(k=3, loop=True),
                                       RadiusGraph(r=0.25, max_num_neighbors=4)], ids=repr)
def test_transform_on_plain_object(device, dtype, gen, transform):
    pos = rand(200, gen, dtype, device)
    data = types.SimpleNamespace(pos=pos)
    out = transform(data)
    if isinstance(transform, KNNGraph):
        expected = torchvor.knn_graph(pos, transform.k, loop=transform.loop)
    else:
        expected = torchvor.radius_graph(pos, transform.r, max_num_neighbors=transform.max_num_neighbors)
    assert torch.equal(out.edge_index, expected)
    assert out.edge_attr.shape == (expected.shape[1], 1) and out.edge_attr.dtype == dtype
    torch.testing.assert_close(out.edge_attr, lengths(pos, expected))
    assert not hasattr(data, "edge_index"), "the transform changed the caller's object"


def test_edge_attr_is_differentiable(gen):
    pos = rand(50, gen, torch.float64, "cpu").requires_grad_()
    out = KNNGraph(k=4)(types.SimpleNamespace(pos=pos))
    out.edge_attr.sum().backward()
    assert pos.grad is not None and torch.isfinite(pos.grad).all()


def test_needs_positions():
    with pytest.raises(ValueError, match="needs 3D positions `pos`"):
        KNNGraph(k=3)(types.SimpleNamespace(x=torch.rand(5, 3)))
    with pytest.raises(ValueError, match="needs 3D positions `pos`"):
        RadiusGraph(r=0.1)(types.SimpleNamespace(pos=torch.rand(5, 2)))


def test_pyg_data_and_batch(device, gen):
    pyg = pytest.importorskip("torch_geometric")
    from torch_geometric.data import Batch, Data
    from torch_geometric.transforms import BaseTransform, Compose

    assert isinstance(KNNGraph(k=4), BaseTransform) and isinstance(RadiusGraph(0.2), BaseTransform)
    clouds = [Data(pos=rand(n, gen, torch.float32, device)) for n in (60, 3, 90)]
    one = KNNGraph(k=4)(clouds[0])
    assert torch.equal(one.edge_index, torchvor.knn_graph(clouds[0].pos, 4))
    assert one.edge_attr.shape == (60 * 4, 1)
    batch = Batch.from_data_list(clouds)
    assert isinstance(VoronoiGraph(), BaseTransform)
    for transform in (KNNGraph(k=4), RadiusGraph(r=0.3), Compose([RadiusGraph(r=0.3)]), VoronoiGraph()):
        out = transform(batch)
        src, dst = out.edge_index
        assert torch.equal(out.batch[src], out.batch[dst]), "an edge joins two clouds"
        # each cloud's edges are those of the cloud alone, offset by its first node
        start = 0
        for cloud in clouds:
            alone = transform(cloud.clone())
            mine = (dst >= start) & (dst < start + cloud.num_nodes)
            assert torch.equal(out.edge_index[:, mine] - start, alone.edge_index)
            torch.testing.assert_close(out.edge_attr[mine], alone.edge_attr)
            start += cloud.num_nodes
    assert "KNNGraph(k=4, loop=False)" in repr(KNNGraph(k=4)) and pyg.__version__


def test_voronoi_graph_transform(device, dtype, gen):
    """VoronoiGraph: the Voronoi graph's edges, face areas and lengths; each
    cloud of a batch gets its own diagram."""
    pos = rand(150, gen, dtype, device)
    out = VoronoiGraph(box=([0, 0, 0], [1, 1, 1]))(types.SimpleNamespace(pos=pos))
    expected = torchvor.voronoi_graph(pos, ([0, 0, 0], [1, 1, 1]))
    assert torch.equal(out.edge_index, expected.edge_index)
    assert out.edge_attr.shape == (expected.edge_index.shape[1], 2) and out.edge_attr.dtype == dtype
    torch.testing.assert_close(out.edge_attr[:, 0], expected.area)
    torch.testing.assert_close(out.edge_attr[:, 1:], lengths(pos, expected.edge_index))
    batch = torch.repeat_interleave(torch.arange(2), torch.tensor([100, 50])).to(device)
    both = VoronoiGraph()(types.SimpleNamespace(pos=pos, batch=batch))
    src, dst = both.edge_index
    assert torch.equal(batch[src], batch[dst])
    assert "VoronoiGraph(box=None)" in repr(VoronoiGraph())
