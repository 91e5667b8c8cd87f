"""Pictures of Voronoi diagrams and Lloyd runs (optional; needs matplotlib).

The diagram is shown as a planar slice (like Fig. 16 of Ray et al. 2018):
every pixel of the plane z = const gets the colour of its nearest point
(:func:`torchvor.knn` with k = 1), which is exactly the slice of the 3D
Voronoi diagram. Colours come from a hash of the point index, so a cell
keeps its colour from picture to picture.

matplotlib is imported only when a picture is drawn, through its object
API (no pyplot, so no global backend is switched); without it
:func:`require_matplotlib` raises ImportError with the install command.
"""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np
import torch

from .ops import knn

MISSING_MATPLOTLIB = "matplotlib is needed for plots: pip install matplotlib (or torchvor[plot])"


def require_matplotlib() -> None:
    """Raise ImportError with the install command when matplotlib is missing."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise ImportError(MISSING_MATPLOTLIB) from None


def index_colors(index: np.ndarray) -> np.ndarray:
    """RGB colours in [0.2, 1] (never near black) for integer indices, any shape -> shape + (3,).

    splitmix64's finaliser: neighbouring indices get unrelated colours.
    """
    with np.errstate(over="ignore"):
        h = index.astype(np.uint64) + np.uint64(0x9E3779B97F4A7C15)
        h = (h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        h = (h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        h = h ^ (h >> np.uint64(31))
    channels = [(h >> np.uint64(shift)) & np.uint64(255) for shift in (0, 8, 16)]
    return 0.2 + 0.8 * np.stack(channels, axis=-1).astype(np.float64) / 255.0


def slice_cells(points: torch.Tensor, box: torch.Tensor, *, resolution: int = 512,
                z: Optional[float] = None) -> np.ndarray:
    """Index of the nearest point of every pixel of the plane ``z`` (default: the box's mid-plane).

    Args:
        points: (N, 3) float32/float64 on any device.
        box: (2, 3) or (1, 2, 3) tensor (lo, hi), the points' dtype and device.
        resolution: pixels along the longer of the box's x and y sides.

    Returns:
        (H, W) int64 NumPy array, row 0 at the box's low y.
    """
    lower, upper = box.reshape(2, 3).to(points.dtype).unbind(0)
    extent = (upper - lower).tolist()
    scale = resolution / max(extent[0], extent[1], 1e-30)
    width = max(1, round(extent[0] * scale))
    height = max(1, round(extent[1] * scale))
    level = float((lower[2] + upper[2]) / 2) if z is None else float(z)
    # Pixel centres, so the picture is symmetric for a symmetric diagram.
    xs = lower[0] + (torch.arange(width, dtype=points.dtype, device=points.device) + 0.5) * (extent[0] / width)
    ys = lower[1] + (torch.arange(height, dtype=points.dtype, device=points.device) + 0.5) * (extent[1] / height)
    grid_y, grid_x = torch.meshgrid(ys, xs, indexing="ij")
    queries = torch.stack([grid_x.reshape(-1), grid_y.reshape(-1), torch.full_like(grid_x.reshape(-1), level)], 1)
    nearest = knn(points, 1, queries).idx[:, 0]
    return nearest.reshape(height, width).cpu().numpy()


def _draw_slice(axes, points: torch.Tensor, box: torch.Tensor, resolution: int) -> None:
    lower, upper = box.reshape(2, 3).double().cpu().numpy()
    cells = slice_cells(points, box, resolution=resolution)
    axes.imshow(index_colors(cells), origin="lower", interpolation="nearest",
                extent=(lower[0], upper[0], lower[1], upper[1]))
    # Seeds within half a typical spacing of the plane: most cells cut by it show their point.
    level = (lower[2] + upper[2]) / 2
    spacing = (np.prod(upper - lower) / max(points.shape[0], 1)) ** (1.0 / 3.0)
    array = points.detach().cpu().double().numpy()
    near = np.abs(array[:, 2] - level) < spacing / 2
    if 0 < near.sum() <= 20000:
        axes.scatter(array[near, 0], array[near, 1], s=1.5, c="black", linewidths=0)
    axes.set_xlim(lower[0], upper[0])
    axes.set_ylim(lower[1], upper[1])
    axes.set_aspect("equal")
    axes.set_xlabel("x")
    axes.set_ylabel("y")
    axes.set_title(f"Voronoi slice z = {level:.4g} ({points.shape[0]} points)")


def _new_figure():
    require_matplotlib()
    from matplotlib.figure import Figure

    return Figure(figsize=(12, 5.5), layout="constrained")


def plot_lloyd(path: str, points: torch.Tensor, box: torch.Tensor, energies: Sequence[float],
               *, resolution: int = 512) -> None:
    """Save a picture: left, the slice of the final diagram; right, energy per iteration.

    Args:
        path: output file; the format follows the suffix (.png, .pdf, .svg, ...).
        points: (N, 3) relaxed points; box: (2, 3) or (1, 2, 3), same dtype/device.
        energies: CVT energy of each iteration (before its move).

    Raises:
        ImportError: matplotlib is missing. OSError/ValueError from saving.
    """
    figure = _new_figure()
    left, right = figure.subplots(1, 2)
    _draw_slice(left, points, box, resolution)
    iterations = np.arange(1, len(energies) + 1)
    from matplotlib.ticker import MaxNLocator

    right.plot(iterations, energies, marker="o", markersize=3)
    right.xaxis.set_major_locator(MaxNLocator(integer=True))
    right.set_xlabel("iteration")
    right.set_ylabel("CVT energy (sum of cell second moments)")
    right.set_title("Lloyd relaxation")
    right.grid(True, alpha=0.3)
    figure.savefig(path, dpi=100)


def plot_cells(path: str, points: torch.Tensor, box: torch.Tensor, volume: torch.Tensor,
               *, resolution: int = 512) -> None:
    """Save a picture: left, the slice of the diagram; right, the histogram of cell volumes.

    Raises:
        ImportError: matplotlib is missing. OSError/ValueError from saving.
    """
    figure = _new_figure()
    left, right = figure.subplots(1, 2)
    _draw_slice(left, points, box, resolution)
    volumes = volume.detach().cpu().double().numpy()
    volumes = volumes[np.isfinite(volumes)]
    right.hist(volumes, bins=60)
    right.set_xlabel("cell volume")
    right.set_ylabel("cells")
    right.set_title("Cell volumes")
    figure.savefig(path, dpi=100)


__all__ = ["require_matplotlib", "index_colors", "slice_cells", "plot_lloyd", "plot_cells"]
