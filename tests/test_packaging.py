"""Packaging: one version, the console script, the sdist's contents, and the
messages of an import without the built extension and of a build that cannot
see torch. All offline, each in a few seconds."""
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import tarfile
import textwrap
from pathlib import Path

import pytest
import torch

import torchvor

ROOT = Path(__file__).resolve().parent.parent


def test_version_has_one_source():
    from torchvor import _version

    assert torchvor.__version__ == _version.__version__
    assert re.fullmatch(r"\d+\.\d+\.\d+([.-]?\w+)*", torchvor.__version__)
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert 'dynamic = ["version"]' in pyproject
    assert 'attr = "torchvor._version.__version__"' in pyproject
    assert not re.search(r"^version\s*=\s*\"", pyproject, re.MULTILINE), "a second, static version"


def test_pyproject_declares_console_script_and_license():
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert re.search(r'^\[project\.scripts\]\ntorchvor = "torchvor\.cli:main"$', pyproject, re.MULTILINE)
    assert 'license = "BSD-3-Clause"' in pyproject
    assert "BSD 3-Clause License" in (ROOT / "LICENSE").read_text()


def test_console_script_prints_the_version():
    script = Path(sys.executable).parent / "torchvor"
    if not script.exists():
        pytest.skip("the torchvor console script is not installed in this environment (an older install)")
    result = subprocess.run([str(script), "--version"], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith(f"torchvor {torchvor.__version__} ")


def test_sdist_carries_every_source_file(tmp_path):
    """Every header and CUDA source of csrc/ (a missing header broke sdist builds), the license and README."""
    tree = tmp_path / "tree"
    tree.mkdir()
    for name in ("setup.py", "pyproject.toml", "MANIFEST.in", "LICENSE", "README.md"):
        shutil.copy(ROOT / name, tree / name)
    ignore = shutil.ignore_patterns("__pycache__", "*.so", "*.pyc")
    for folder in ("csrc", "torchvor", "tests", "scripts"):
        shutil.copytree(ROOT / folder, tree / folder, ignore=ignore)
    result = subprocess.run([sys.executable, "setup.py", "-q", "sdist", "-d", str(tmp_path / "dist")],
                            cwd=tree, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    (sdist,) = (tmp_path / "dist").glob("torchvor-*.tar.gz")
    with tarfile.open(sdist) as archive:
        members = {name.split("/", 1)[1] for name in archive.getnames() if "/" in name}
    sources = {path.relative_to(tree).as_posix() for path in (tree / "csrc").rglob("*") if path.is_file()}
    assert sources and not sources - members, f"missing from the sdist: {sorted(sources - members)}"
    assert {"LICENSE", "README.md", "pyproject.toml", "setup.py", "torchvor/_version.py"} <= members


# ---- importing a tree without the built extension --------------------------------------


def _source_copy(tmp_path, source_tree=True):
    """torchvor's Python files without torchvor._C, in a directory laid out as a
    repository (setup.py, csrc/) or as a bare package."""
    package = tmp_path / "repo" / "torchvor"
    package.mkdir(parents=True)
    for path in (ROOT / "torchvor").glob("*.py"):
        shutil.copy(path, package / path.name)
    if source_tree:
        (tmp_path / "repo" / "setup.py").write_text("# stand-in\n")
        (tmp_path / "repo" / "csrc").mkdir()
    return package


def _run_in(directory, code):
    """Run code in a fresh Python whose import of torchvor finds the copy in ``directory``
    only (an editable install's finder would fill in the missing _C from the real tree)."""
    prelude = ("import sys\n"
               "sys.meta_path[:] = [f for f in sys.meta_path if 'editable' not in repr(f).lower()]\n")
    return subprocess.run([sys.executable, "-c", prelude + textwrap.dedent(code)], cwd=directory,
                          capture_output=True, text=True, timeout=120)


def test_import_from_an_unbuilt_source_tree_says_what_to_do(tmp_path):
    package = _source_copy(tmp_path)
    result = _run_in(package.parent, "import runpy\nsys.argv = ['torchvor', '--version']\n"
                                     "runpy.run_module('torchvor', run_name='__main__')")
    assert result.returncode != 0
    message = result.stderr.strip().splitlines()
    assert "partially initialized" not in result.stderr
    first = next(i for i, line in enumerate(message) if line.startswith("ImportError: "))
    text = "\n".join(message[first:])
    assert f"imported from {package}" in text and "no compiled extension torchvor._C" in text
    assert "pip install --no-build-isolation -e ." in text and "bash scripts/setup.sh" in text
    assert "outside the source tree" in text


def test_import_of_a_package_without_extension_outside_a_source_tree(tmp_path):
    package = _source_copy(tmp_path, source_tree=False)
    result = _run_in(package.parent, "import torchvor")
    assert result.returncode != 0
    assert f"imported from {package}, which has no compiled extension torchvor._C" in result.stderr
    assert "--no-build-isolation" in result.stderr and "partially initialized" not in result.stderr


def test_extension_that_fails_to_load_shows_the_original_error(tmp_path):
    package = _source_copy(tmp_path)
    (package / ("_C" + sysconfig.get_config_var("EXT_SUFFIX"))).write_bytes(b"not a shared library\n")
    result = _run_in(package.parent, "import torchvor")
    assert result.returncode != 0
    line = next(line for line in result.stderr.splitlines() if line.startswith("ImportError: torchvor:"))
    assert "failed to load" in line and str(package) in line
    assert re.search(r"invalid ELF header|file too short|not a valid|cannot open", line), line
    assert f"another torch than the {torch.__version__}" in result.stderr
    assert "pip install --no-build-isolation -e ." in result.stderr


def test_extension_built_from_older_sources_is_named_out_of_date(tmp_path):
    package = _source_copy(tmp_path)
    (package / "_C.py").write_text("# declares no op\n")
    result = _run_in(package.parent, "import torchvor")
    assert result.returncode != 0
    assert "is out of date" in result.stderr and "torchvor::cvt_energy" in result.stderr


# ---- setup.py without torch ------------------------------------------------------------


def _bare_python(path):
    """A virtual environment without packages (not even pip), like pip's isolated build env."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(path)], check=True, timeout=120)
    return str(path / "bin" / "python")


def _setup_py_under(parent_python, build_python, tmp_path):
    """Run setup.py with ``build_python`` as a child of ``parent_python``, as pip runs a build backend."""
    environment = {name: value for name, value in os.environ.items()
                   if name not in ("VIRTUAL_ENV", "PYTHONPATH", "PYTHONHOME")}
    launcher = (f"import subprocess, sys\n"
                f"sys.exit(subprocess.run([{build_python!r}, 'setup.py', '--version'], cwd={str(ROOT)!r}).returncode)")
    return subprocess.run([parent_python, "-c", launcher], capture_output=True, text=True, timeout=120,
                          env=environment, cwd=tmp_path)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the frontend is found through /proc")
def test_setup_py_names_the_torch_that_build_isolation_hides(tmp_path):
    isolated = _bare_python(tmp_path / "pip-build-env-test")
    result = _setup_py_under(sys.executable, isolated, tmp_path)
    assert result.returncode != 0
    assert "pip is building torchvor in an isolated environment" in result.stderr, result.stderr
    assert f"hides the torch {torch.__version__} installed in {sys.prefix}" in result.stderr
    assert "pip install --no-build-isolation ." in result.stderr
    assert "none was found" not in result.stderr


def test_setup_py_without_any_torch_says_how_to_install_it(tmp_path):
    isolated = _bare_python(tmp_path / "pip-build-env-test")
    outer = _bare_python(tmp_path / "no-torch")
    result = _setup_py_under(outer, isolated, tmp_path)
    assert result.returncode != 0
    assert "no torch is installed" in result.stderr, result.stderr
    assert "pip install torch==2.13.0" in result.stderr and "--no-build-isolation" in result.stderr
