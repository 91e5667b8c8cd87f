"""Command line: ``torchvor lloyd|cells ...`` or ``python -m torchvor ...`` (--help for the usage).

Errors in the input (missing, unreadable or malformed files, NaN, points
outside --box, unavailable device, bad output suffix) print one line
``torchvor: error: ...`` to stderr and exit with status 2, as argparse does
for bad options. Progress goes to stderr, the final "wrote ..." lines to
stdout. matplotlib is optional: without it, --plot is skipped with a warning
on stderr after the results are written (exit status 0).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from typing import List, Optional, Tuple

import numpy as np
import torch

from . import io as point_io
from ._version import __version__

DEFAULT_N = 20000      # generated white-noise points without INPUT
DEFAULT_ITERS = 10
EXIT_USAGE = 2

DESCRIPTION = """\
Lloyd relaxation and Voronoi cell integrals of 3D point sets (torchvor).

Input files: .npy (N, 3 array), .xyz / .txt (3 columns separated by
whitespace or commas, '#' comments) or .ply (ascii or binary, vertex x y z).
Without INPUT, --n white-noise points in the unit cube are generated.
"""

LLOYD_EPILOG = """\
output: the relaxed points, in the format of --out's suffix (.npy, .ply
(binary little-endian), .xyz or .txt), in the computation dtype.

examples:
  python -m torchvor lloyd --n 20000 --iters 20 --out relaxed.npy --plot relaxed.png
  python -m torchvor lloyd scan.ply --iters 5 --box 0 0 0 1 1 1 --out scan_relaxed.ply
"""

CELLS_EPILOG = """\
output: .npz with arrays points (N,3), volume (N,), centroid (N,3),
second_moment (N,) (integral over the cell of |x - point|^2), status (N,)
int8 (0 = success, 5 = duplicate point, others = failure, see
torchvor.CellStatus) and neighbors_needed (N,) int32 (nearest neighbours
the cell needed); or .npy holding one structured array with fields point,
volume, centroid, second_moment, status, neighbors_needed.
"""


GRAPH_EPILOG = """\
output: .npz with arrays points (N,3), edge_index (2,E) int64 (row 0 the
neighbour j, row 1 the cell i, sorted by i then j, every face both ways),
area (E,) and centroid (E,3) of each face, wall_area (N,6) (each cell's area
on the box walls -x, +x, -y, +y, -z, +z), volume (N,) and status (N,) int8
(as in the cells command); with --periodic also shift (E,3) int8, the image
of j that cell i meets: points[j] + shift * (box edge).
"""


class CliError(Exception):
    """A user-facing error: printed as one line, exit status 2."""


# ---- arguments ------------------------------------------------------------------------


def build_parser(prog: Optional[str] = None) -> argparse.ArgumentParser:
    """The parser; ``prog`` defaults to ``torchvor`` for the console script, else ``python -m torchvor``."""
    if prog is None:
        prog = "torchvor" if os.path.basename(sys.argv[0]) == "torchvor" else "python -m torchvor"
    parser = argparse.ArgumentParser(prog=prog, description=DESCRIPTION,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"torchvor {__version__} (torch {torch.__version__})")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")
    commands.required = True

    lloyd = commands.add_parser("lloyd", help="relax points by Lloyd iterations",
                                description="Move every point to its Voronoi cell's centroid, --iters times.",
                                epilog=LLOYD_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_common_arguments(lloyd, out_help="relaxed points: .npy, .ply, .xyz or .txt")
    lloyd.add_argument("--iters", type=_non_negative_int, default=DEFAULT_ITERS, metavar="K",
                       help=f"Lloyd iterations (default {DEFAULT_ITERS})")
    lloyd.add_argument("--tol", type=float, default=None, metavar="T",
                       help="stop early when no point moves more than T times the box diagonal")
    lloyd.set_defaults(run=run_lloyd)

    cells = commands.add_parser("cells", help="volume, centroid, second moment of every Voronoi cell",
                                description="Compute the Voronoi cell integrals of the points.",
                                epilog=CELLS_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_common_arguments(cells, out_help="cell table: .npz or .npy (structured array)")
    cells.set_defaults(run=run_cells)

    graph = commands.add_parser("graph", help="the Voronoi graph: neighbours, face areas and centroids",
                                description="Compute every face between two Voronoi cells of the points.",
                                epilog=GRAPH_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_common_arguments(graph, out_help="graph arrays: .npz")
    graph.set_defaults(run=run_graph)
    return parser


def _add_common_arguments(parser: argparse.ArgumentParser, out_help: str) -> None:
    parser.add_argument("input", nargs="?", metavar="INPUT",
                        help="point file (.npy, .xyz, .txt, .ply); omitted: generate white noise")
    parser.add_argument("--out", required=True, metavar="FILE", help=out_help)
    parser.add_argument("--n", type=_positive_int, default=DEFAULT_N, metavar="N",
                        help=f"number of generated points without INPUT (default {DEFAULT_N})")
    parser.add_argument("--seed", type=int, default=0, metavar="S",
                        help="seed of the generated points (default 0)")
    parser.add_argument("--box", type=float, nargs=6, default=None, metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"),
                        help="box of the diagram (default: bounding box of INPUT, unit cube for generated points)")
    parser.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto",
                        help="auto (default) = cuda if available, else cpu")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32",
                        help="computation and output dtype (default float32)")
    parser.add_argument("--plot", default=None, metavar="PNG",
                        help="also draw a picture (needs matplotlib, else skipped with a warning): a z "
                             "mid-plane slice of the diagram and the energy curve (lloyd) or volume "
                             "histogram (cells)")
    parser.add_argument("--periodic", default=None, metavar="AXES",
                        help="periodic box along AXES (xyz, or a subset such as xz): cells wrap around, and "
                             "points outside the box along those axes are taken at their image (needs --box "
                             "with an INPUT file)")
    parser.add_argument("--quiet", action="store_true", help="no progress lines on stderr")


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _non_negative_int(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be at least 0, got {value}")
    return value


# ---- shared steps ---------------------------------------------------------------------


def _check_output_suffix(path: str, allowed: Tuple[str, ...], what: str) -> None:
    if point_io.suffix(path) not in allowed:
        raise CliError(f"--out {path}: {what} must end with {', '.join(allowed)}")


def _check_output_directory(option: str, path: str) -> None:
    # Checked before computing, so a typo does not cost a whole run.
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        raise CliError(f"{option} {path}: directory {directory} does not exist")


def _check_plot_available(args) -> None:
    """Fail fast on a bad --plot path; without matplotlib, note in ``args.plot_skipped`` why it will be skipped."""
    args.plot_skipped = None
    if args.plot is None:
        return
    _check_output_directory("--plot", args.plot)
    from .plot import require_matplotlib

    try:
        require_matplotlib()
    except ImportError as error:
        # The results are still computed and written; only the picture is skipped.
        args.plot_skipped = str(error)
        return
    from matplotlib.backend_bases import FigureCanvasBase

    formats = FigureCanvasBase.get_supported_filetypes()
    kind = point_io.suffix(args.plot).lstrip(".")
    if kind not in formats:
        raise CliError(f"--plot {args.plot}: unsupported picture type; use one of "
                       f"{', '.join('.' + name for name in sorted(formats))}")


def _cuda_usable() -> bool:
    """CUDA present and torchvor built with its CUDA kernels (a CPU-only build has none)."""
    return torch.cuda.is_available() and torch._C._dispatch_has_kernel_for_dispatch_key(
        "torchvor::voronoi_cells", "CUDA")


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if _cuda_usable() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise CliError("--device cuda: CUDA is not available (torch "
                       f"{torch.__version__}{'' if torch.version.cuda else ', a CPU-only build'})")
    if name == "cuda" and not _cuda_usable():
        raise CliError("--device cuda: torchvor was built without its CUDA kernels; rebuild it "
                       "with nvcc available (TORCHVOR_FORCE_CUDA=1) or use --device cpu")
    return torch.device(name)


def _load_points(args, dtype: torch.dtype, device: torch.device) -> Tuple[torch.Tensor, str]:
    """(points, description) from INPUT or generated white noise."""
    if args.input is None:
        from .samples import white_noise

        # Drawn on the CPU so a seed gives the same points on every device.
        points = white_noise(args.n, seed=args.seed, dtype=dtype).to(device)
        return points, f"{args.n} white-noise points (seed {args.seed})"
    array = point_io.read_points(args.input)
    points = torch.from_numpy(array).to(device=device, dtype=dtype)
    if not torch.isfinite(points).all():
        raise CliError(f"{args.input}: coordinates overflow {args.dtype}")
    return points, f"{points.shape[0]} points from {args.input}"


def _periodic_axes(args):
    """--periodic as three bools, or False."""
    if args.periodic is None:
        return False
    text = args.periodic.lower()
    if not text or any(c not in "xyz" for c in text) or len(set(text)) != len(text):
        raise CliError(f"--periodic: name the periodic axes as letters of xyz (e.g. xyz or xz), got {args.periodic!r}")
    return tuple(axis in text for axis in "xyz")


def _box(args, points: torch.Tensor) -> torch.Tensor:
    """The (1, 2, 3) box: --box, the unit cube for generated points, else the bounding box."""
    periodic = _periodic_axes(args)
    if periodic and args.box is None and args.input is not None:
        raise CliError("--periodic needs --box (its edges are the periods)")
    if args.box is not None:
        box = torch.tensor(args.box, dtype=points.dtype).reshape(2, 3)
        flat = [axis for axis, (lo, hi) in zip("xyz", box.T.tolist()) if not lo < hi]
        if flat:
            raise CliError(f"--box: needs X0 < X1, Y0 < Y1 and Z0 < Z1 (violated along {', '.join(flat)})")
        box = box.to(points.device)
        bounded = ~torch.tensor(periodic or (False, False, False), device=points.device)  # periodic axes wrap
        outside = int((~((points >= box[0]) & (points <= box[1]) | ~bounded).all(1)).sum())
        if outside:
            raise CliError(f"{outside} of {points.shape[0]} points lie outside --box {_box_text(box)}")
        return box.unsqueeze(0)
    if args.input is None:
        return torch.tensor([[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]], dtype=points.dtype, device=points.device)
    box = torch.stack([points.amin(0), points.amax(0)])
    flat = [axis for axis, (lo, hi) in zip("xyz", box.T.tolist()) if not lo < hi]
    if flat:
        raise CliError(f"the points' bounding box is flat along {', '.join(flat)}; give a --box with volume")
    return box.unsqueeze(0)


def _box_text(box: torch.Tensor) -> str:
    lower, upper = box.reshape(2, 3).tolist()
    return f"[{' '.join(f'{v:g}' for v in lower)}] - [{' '.join(f'{v:g}' for v in upper)}]"


def _say(args, message: str) -> None:
    if not args.quiet:
        print(message, file=sys.stderr, flush=True)


def _prepare(args, out_suffixes: Tuple[str, ...], what: str):
    """Checks that need no computation first (fail fast), then points, box and device."""
    _check_output_suffix(args.out, out_suffixes, what)
    _check_output_directory("--out", args.out)
    _check_plot_available(args)
    device = _device(args.device)
    dtype = getattr(torch, args.dtype)
    points, description = _load_points(args, dtype, device)
    box = _box(args, points)
    _say(args, f"torchvor {args.command}: {description}, {args.dtype} on {device}, box {_box_text(box)}")
    if args.plot_skipped:
        _say(args, f"torchvor {args.command}: the picture {args.plot} will be skipped: {args.plot_skipped}")
    return points, box


def _plot_wanted(args) -> bool:
    """Whether to draw --plot; says on stderr why not when matplotlib is missing."""
    if args.plot is None:
        return False
    if args.plot_skipped:
        print(f"torchvor: warning: skipped the picture {args.plot}: {args.plot_skipped}", file=sys.stderr)
        return False
    return True


def _write(path: str, writer, *values) -> None:
    try:
        writer(path, *values)
    except OSError as error:
        raise CliError(f"cannot write {path}: {error.strerror or error}") from None


# ---- commands -------------------------------------------------------------------------


def run_lloyd(args) -> int:
    from .lloyd import lloyd

    points, box = _prepare(args, (".npy", ".ply", ".xyz", ".txt"), "the relaxed points file")
    start = time.perf_counter()
    relaxed, history = lloyd(points, box, iters=args.iters, tol=args.tol, progress=not args.quiet,
                             return_history=True, periodic=_periodic_axes(args))
    elapsed = time.perf_counter() - start
    if history and history[-1].iteration + 1 < args.iters:
        _say(args, f"torchvor lloyd: converged after {len(history)} iterations (--tol {args.tol:g})")
    _say(args, f"torchvor lloyd: {len(history)} iterations in {elapsed:.2f} s")
    _write(args.out, point_io.write_points, relaxed)
    print(f"torchvor: wrote {relaxed.shape[0]} relaxed points to {args.out}")
    if _plot_wanted(args):
        from .plot import plot_lloyd

        _write(args.plot, plot_lloyd, relaxed, box, [step.energy for step in history])
        print(f"torchvor: wrote the picture to {args.plot}")
    return 0


def run_cells(args) -> int:
    from .ops import CellStatus, voronoi

    points, box = _prepare(args, point_io.CELL_SUFFIXES, "the cell table")
    start = time.perf_counter()
    cells = voronoi(points, box, on_failure="flag", periodic=_periodic_axes(args))
    total_volume = float(cells.volume.sum(dtype=torch.float64))
    elapsed = time.perf_counter() - start
    failed = int(((cells.status != CellStatus.SUCCESS) & (cells.status != CellStatus.DUPLICATE)).sum())
    duplicates = int((cells.status == CellStatus.DUPLICATE).sum())
    box_volume = float((box[0, 1] - box[0, 0]).double().prod())
    _say(args, f"torchvor cells: {points.shape[0]} cells in {elapsed:.2f} s, total volume {total_volume:.6g} "
               f"(box {box_volume:.6g}), energy {float(cells.second_moment.sum(dtype=torch.float64)):.6e}")
    if duplicates:
        _say(args, f"torchvor cells: {duplicates} duplicate point(s) (status 5, volume 0)")
    if failed:
        # Not an input error: the file is still written, with NaN rows flagged by status.
        print(f"torchvor: warning: {failed} cell(s) could not be computed (NaN, non-zero status)",
              file=sys.stderr)
    _write(args.out, point_io.write_cells, points, cells)
    print(f"torchvor: wrote {points.shape[0]} cells to {args.out}")
    if _plot_wanted(args):
        from .plot import plot_cells

        _write(args.plot, plot_cells, points, box, cells.volume)
        print(f"torchvor: wrote the picture to {args.plot}")
    return 0


def run_graph(args) -> int:
    from .graph import voronoi_graph
    from .ops import CellStatus

    points, box = _prepare(args, (".npz",), "the graph")
    start = time.perf_counter()
    graph = voronoi_graph(points, box, on_failure="flag", periodic=_periodic_axes(args))
    edges = graph.edge_index.shape[1]
    elapsed = time.perf_counter() - start
    status = graph.cells.status
    failed = int(((status != CellStatus.SUCCESS) & (status != CellStatus.DUPLICATE)).sum())
    _say(args, f"torchvor graph: {points.shape[0]} cells, {edges // 2} faces between them in {elapsed:.2f} s")
    if failed:
        print(f"torchvor: warning: {failed} cell(s) could not be computed (no faces, non-zero status)",
              file=sys.stderr)

    def write(path):
        extra = {} if graph.shift is None else {"shift": graph.shift.cpu().numpy()}
        np.savez(path, points=points.cpu().numpy(), edge_index=graph.edge_index.cpu().numpy(),
                 area=graph.area.cpu().numpy(), centroid=graph.centroid.cpu().numpy(),
                 wall_area=graph.wall_area.cpu().numpy(), volume=graph.cells.volume.cpu().numpy(),
                 status=status.cpu().numpy(), **extra)

    _write(args.out, write)
    print(f"torchvor: wrote {edges} edges ({edges // 2} faces) to {args.out}")
    if _plot_wanted(args):
        from .plot import plot_cells

        _write(args.plot, plot_cells, points, box, graph.cells.volume)
        print(f"torchvor: wrote the picture to {args.plot}")
    return 0


def main(argv: Optional[List[str]] = None) -> int:
    """Run the command line; returns the exit status (0, or 2 for input errors)."""
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except (CliError, point_io.PointFileError) as error:
        return _fail(str(error))
    except ValueError as error:
        # torchvor's own input checks (points outside the box, ...): the first
        # line names the problem; the rest would be a C++ backtrace.
        return _fail(str(error).splitlines()[0] if str(error) else type(error).__name__)
    except KeyboardInterrupt:
        print("torchvor: interrupted", file=sys.stderr)
        return 130


def _fail(message: str) -> int:
    print(f"torchvor: error: {message}", file=sys.stderr)
    return EXIT_USAGE


__all__ = ["main", "build_parser"]
