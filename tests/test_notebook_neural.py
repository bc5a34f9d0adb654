"""Execute notebooks/neural.ipynb (stored without outputs) with nbclient."""

import os
import shutil
import sys
import time
from pathlib import Path

import nbformat
import pytest

NOTEBOOK = Path(__file__).resolve().parents[1] / "notebooks" / "neural.ipynb"


def test_notebook_neural_runs(tmp_path, monkeypatch):
    nbclient = pytest.importorskip("nbclient")
    pytest.importorskip("ipykernel")
    nb = nbformat.read(NOTEBOOK, as_version=4)
    assert all(not c.get("outputs") for c in nb.cells if c.cell_type == "code"), "store without outputs"
    shutil.copy(NOTEBOOK, tmp_path / NOTEBOOK.name)
    # the kernel must import this checkout's heliojax and use this interpreter's packages
    env_path = str(NOTEBOOK.parents[1])
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [env_path, os.environ.get("PYTHONPATH")])))
    from jupyter_client.kernelspec import KernelSpecManager

    ksm = KernelSpecManager()
    kernel = "python3"
    spec = ksm.get_kernel_spec(kernel)
    if Path(spec.argv[0]).resolve() != Path(sys.executable).resolve() and spec.argv[0] != "python":
        pytest.skip(f"kernel python3 runs {spec.argv[0]}, not {sys.executable}")
    client = nbclient.NotebookClient(nb, kernel_name=kernel, timeout=120,
                                     resources={"metadata": {"path": str(tmp_path)}})
    t0 = time.perf_counter()
    client.execute()
    assert time.perf_counter() - t0 < 90
    text = "\n".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []))
    assert "fleet held-out median LM+residual" in text
    assert "networks without the fallback rule" in text
    assert "notebook ran in" in text
