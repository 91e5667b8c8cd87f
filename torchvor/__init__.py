"""torchvor: k-nearest neighbours and 3D Voronoi cell integrals for PyTorch.

Meshless Voronoi on the GPU (Ray et al. 2018): grid kNN, then every cell clipped
on its own from its nearest neighbours, with integrals taken on the fly.
"""
from ._version import __version__
from .ops import KNN, CellStatus, VoronoiCells, knn, knn_graph, voronoi  # loads torchvor._C

from .graph import VoronoiGraph, voronoi_graph, voronoi_laplacian
from .radius import Radius, radius, radius_graph
from .transport import PowerWeights, power_lloyd, power_weights

__all__ = ["KNN", "CellStatus", "Radius", "VoronoiCells", "VoronoiGraph", "knn", "knn_graph", "radius", "radius_graph",
           "voronoi", "voronoi_graph", "voronoi_laplacian", "PowerWeights", "power_lloyd", "power_weights"]
# Lloyd relaxation layer. Note: the function torchvor.lloyd shadows the module
# attribute of the same name; import module contents with `from torchvor.lloyd import ...`.
from .cvt import cvt_energy
from .lloyd import LloydStep, lloyd
from .nn import LloydRelaxation

__all__ += ["cvt_energy", "lloyd", "LloydStep", "LloydRelaxation"]
