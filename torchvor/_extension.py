"""Loads the compiled extension ``torchvor._C``, or says why it cannot and what to do.

``torchvor._C`` declares every ``torch.ops.torchvor`` schema and registers the
C++/CUDA kernels. It is missing where the package is imported from a source
tree that was never built in place (also when such a tree shadows an installed
copy, as ``python -m torchvor`` run from the repository root does), it fails to
load when it was built against another torch, and it lacks ops when it was
built from older sources. Each case raises an ImportError that names the
directory and the fix, instead of Python's "cannot import name '_C' from
partially initialized module".
"""
from __future__ import annotations

import importlib
import importlib.util
import os

import torch

# The ops the Python layer uses or registers kernels for; all are declared in csrc/registration.cpp.
REQUIRED_OPS = ("knn", "voronoi_cells", "voronoi_cells_grid_order", "lloyd_step",
                "drop_missing_edges", "cvt_energy")

PACKAGE_DIR = os.path.dirname(os.path.abspath(__file__))


def load_extension() -> None:
    """Import ``torchvor._C`` and check that it declares every op of :data:`REQUIRED_OPS`.

    Raises:
        ImportError: the extension is missing, fails to load, or is out of date;
            the message names the directory and the fix.
    """
    if importlib.util.find_spec("torchvor._C") is None:
        raise ImportError(_missing_message())
    try:
        extension = importlib.import_module("torchvor._C")
    except ImportError as error:
        raise ImportError(_broken_message(error)) from error
    missing = [name for name in REQUIRED_OPS if not hasattr(torch.ops.torchvor, name)]
    if missing:
        raise ImportError(
            f"torchvor: the compiled extension {getattr(extension, '__file__', 'torchvor._C')} is out of date: "
            f"it does not declare {', '.join('torchvor::' + name for name in missing)}.\n"
            + _rebuild_advice())


def _source_root():
    """The repository root when the package sits in a source tree, else None."""
    root = os.path.dirname(PACKAGE_DIR)
    if os.path.isfile(os.path.join(root, "setup.py")) and os.path.isdir(os.path.join(root, "csrc")):
        return root
    return None


def _installed_copy():
    """The directory of an installed torchvor other than this one, if pip knows of one."""
    try:
        from importlib import metadata

        distribution = metadata.distribution("torchvor")
    except Exception:  # no metadata, or a broken one: nothing to point at
        return None
    candidate = os.path.abspath(str(distribution.locate_file("torchvor")))
    if os.path.isfile(os.path.join(candidate, "__init__.py")) and candidate != PACKAGE_DIR:
        return candidate
    return None


def _rebuild_advice() -> str:
    root = _source_root()
    if root is None:
        return ("Reinstall torchvor with the torch you run it with:\n"
                "    pip install --no-build-isolation --force-reinstall <torchvor source or sdist>")
    return ("Build it in place against the installed torch, from the repository root:\n"
            f"    cd {root}\n"
            "    pip install --no-build-isolation -e .    (or: bash scripts/setup.sh, which makes .venv)")


def _missing_message() -> str:
    root = _source_root()
    lines = [f"torchvor was imported from {PACKAGE_DIR}, which has no compiled extension torchvor._C"]
    if root is not None:
        lines[0] += " (a source tree that was not built in place)."
        lines.append(_rebuild_advice())
        installed = _installed_copy()
        if installed is not None:
            lines.append(f"or run from outside the source tree to use the installed copy in {installed}.")
        else:
            lines.append("or, to use an installed copy, run from outside the source tree "
                         "(its torchvor/ directory shadows the installed package).")
    else:
        lines[0] += "."
        lines.append(_rebuild_advice())
    return "\n".join(lines)


def _broken_message(error: ImportError) -> str:
    path = getattr(error, "path", None) or os.path.join(PACKAGE_DIR, "_C*")
    return (f"torchvor: the compiled extension {path} failed to load: {error}\n"
            f"It was most likely built against another torch than the {torch.__version__} "
            "imported now (or another Python).\n" + _rebuild_advice())
