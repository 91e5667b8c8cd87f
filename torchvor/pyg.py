"""PyTorch Geometric transforms (``torch_geometric.transforms`` style) built on torchvor's graphs.

``torch_geometric`` is optional: this module imports without it, and the
transforms take any object with ``pos`` (and ``batch`` for a batched
``Batch``) attributes. Where it is installed they are ``BaseTransform``s.

    from torchvor.pyg import KNNGraph, RadiusGraph, VoronoiGraph
    data = KNNGraph(k=8)(data)   # data.edge_index (2, E), data.edge_attr (E, 1) distances
    data = VoronoiGraph()(data)  # data.edge_attr (E, 2): face area, distance
"""
from __future__ import annotations

import copy
from typing import Optional

import torch

from .graph import voronoi_graph
from .ops import knn_graph
from .radius import radius_graph

try:  # the base class where PyG is installed, for its repr and isinstance checks
    from torch_geometric.transforms import BaseTransform as _Base
except ImportError:  # pragma: no cover - exercised where PyG is absent
    class _Base:
        def __call__(self, data):
            return self.forward(copy.copy(data))  # as PyG's: the caller's object keeps its attributes

        def __repr__(self) -> str:
            return f"{type(self).__name__}()"


def _with_edges(data, edge_index: torch.Tensor):
    """`data` with `edge_index` and its edges' lengths as `edge_attr` (E, 1)."""
    source, target = edge_index
    data.edge_index = edge_index
    data.edge_attr = (data.pos[source] - data.pos[target]).norm(dim=-1, keepdim=True)
    return data


def _positions(data) -> torch.Tensor:
    pos = getattr(data, "pos", None)
    if not isinstance(pos, torch.Tensor) or pos.dim() != 2 or pos.shape[-1] != 3:
        raise ValueError(f"torchvor.pyg: the data needs 3D positions `pos` of shape (N, 3), got "
                         f"{None if pos is None else tuple(getattr(pos, 'shape', ()))}")
    return pos


class KNNGraph(_Base):
    """Adds the k-nearest-neighbour graph of ``data.pos`` (torchvor.knn_graph).

    Sets ``data.edge_index`` (2, E) int64, PyG's layout (row 0 the neighbour,
    row 1 the centre, sorted by centre then distance), and ``data.edge_attr``
    (E, 1) the edges' lengths in ``pos``'s dtype, differentiable in ``pos``.
    A batched ``Batch``'s clouds (``data.batch``) never connect.

    Args:
        k: neighbours per node.
        loop: include the self-loops (they count among the k).
    """

    def __init__(self, k: int = 6, loop: bool = False):
        self.k = k
        self.loop = loop

    def forward(self, data):
        pos = _positions(data)
        batch: Optional[torch.Tensor] = getattr(data, "batch", None)
        return _with_edges(data, knn_graph(pos, self.k, batch=batch, loop=self.loop))

    def __repr__(self) -> str:
        return f"{type(self).__name__}(k={self.k}, loop={self.loop})"


class RadiusGraph(_Base):
    """Adds the radius graph of ``data.pos`` (torchvor.radius_graph): an edge
    for every pair within distance ``r``, with ``edge_index`` and ``edge_attr``
    (lengths) as :class:`KNNGraph` sets them.

    Args:
        r: the radius.
        loop: include the self-loops.
        max_num_neighbors: keep at most this many neighbours a node, its
            nearest; ``None`` (default) keeps every one.
    """

    def __init__(self, r: float, loop: bool = False, max_num_neighbors: Optional[int] = None):
        self.r = r
        self.loop = loop
        self.max_num_neighbors = max_num_neighbors

    def forward(self, data):
        pos = _positions(data)
        batch: Optional[torch.Tensor] = getattr(data, "batch", None)
        edges = radius_graph(pos, self.r, batch=batch, loop=self.loop, max_num_neighbors=self.max_num_neighbors)
        return _with_edges(data, edges)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(r={self.r}, loop={self.loop}, max_num_neighbors={self.max_num_neighbors})"


class VoronoiGraph(_Base):
    """Adds the Voronoi graph of ``data.pos`` (torchvor.voronoi_graph): an
    edge for every face between two cells, both ways, in PyG's layout (row 0
    the neighbour, row 1 the cell, sorted by cell then neighbour).

    Sets ``data.edge_index`` (2, E) int64 and ``data.edge_attr`` (E, 2): the
    face's area (not differentiable) and the edge's length (differentiable in
    ``pos``), in ``pos``'s dtype. A batched ``Batch``'s clouds
    (``data.batch``) each get their own diagram and never connect.

    Args:
        box: the box of the cells, as torchvor.voronoi takes it; ``None``
            (default) takes each cloud's bounding box.
    """

    def __init__(self, box=None):
        self.box = box

    def forward(self, data):
        pos = _positions(data)
        batch: Optional[torch.Tensor] = getattr(data, "batch", None)
        graph = voronoi_graph(pos, self.box, batch=batch)
        source, target = graph.edge_index
        data.edge_index = graph.edge_index
        length = (pos[source] - pos[target]).norm(dim=-1, keepdim=True)
        data.edge_attr = torch.cat([graph.area.unsqueeze(-1), length], dim=-1)
        return data

    def __repr__(self) -> str:
        return f"{type(self).__name__}(box={self.box})"
