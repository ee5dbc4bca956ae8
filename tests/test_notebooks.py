"""The notebooks in notebooks/ run top to bottom without errors (nbclient, this interpreter's kernel),
are committed without outputs, and draw their pictures inline."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))
KERNEL = "python3"


def _kernel_is_this_python(spec) -> bool:
    argv0 = spec.argv[0] if spec.argv else ""
    major, minor = sys.version_info[:2]
    if argv0 in ("python", f"python{major}", f"python{major}.{minor}"):
        return True  # jupyter_client launches these names as its own sys.executable
    try:
        return Path(argv0).resolve() == Path(sys.executable).resolve()
    except OSError:
        return False


@pytest.fixture(scope="module")
def kernel_name() -> str:
    """A kernelspec running this interpreter (the venv with tiger installed).

    ipykernel's wheel ships a ``python3`` spec with argv ``python``, which jupyter_client launches
    as its own ``sys.executable``; when the spec found first is another interpreter's (e.g. a
    system-wide one with an absolute path), install one of our own
    into this environment's prefix (``--sys-prefix``).
    """
    from jupyter_client.kernelspec import KernelSpecManager, NoSuchKernel

    ksm = KernelSpecManager()
    try:
        spec = ksm.get_kernel_spec(KERNEL)
        ok = _kernel_is_this_python(spec)
    except NoSuchKernel:
        ok = False
    if ok:
        return KERNEL
    # A name of our own, so a user-level "python3" spec cannot shadow it.
    name = "tiger-test-python"
    subprocess.run([sys.executable, "-m", "ipykernel", "install", "--sys-prefix", "--name", name,
                    "--display-name", "Python 3 (tiger tests)"], check=True, capture_output=True)
    spec = KernelSpecManager().get_kernel_spec(name)
    if not _kernel_is_this_python(spec):
        pytest.fail(f"kernelspec {name!r} runs {spec.argv[0]}, not {sys.executable} ({spec.resource_dir})")
    return name


def test_notebooks_exist():
    assert [p.name for p in NOTEBOOKS] == ["01_render_and_formats.ipynb", "02_language_retrieval.ipynb", "03_edit.ipynb"]


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_committed_without_outputs(path):
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert code and all(not c.outputs and c.execution_count is None for c in code), \
        f"{path.name} has outputs: clear them before committing"


@pytest.mark.timeout(300)
@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_runs(path, kernel_name, tmp_path):
    nb = nbformat.read(path, as_version=4)
    env_threads = os.environ.get("OMP_NUM_THREADS")
    os.environ.setdefault("OMP_NUM_THREADS", "2")  # the kernel inherits the environment
    try:
        client = nbclient.NotebookClient(nb, kernel_name=kernel_name, timeout=240,
                                         resources={"metadata": {"path": str(tmp_path)}})
        client.execute()  # raises CellExecutionError naming the cell and the traceback
    finally:
        if env_threads is None:
            os.environ.pop("OMP_NUM_THREADS", None)
    images = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs
              if o.get("output_type") == "display_data" and "image/png" in o.get("data", {})]
    assert len(images) >= 3, f"{path.name} shows {len(images)} pictures inline"
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs if o.get("output_type") == "error"]
    assert not errors
