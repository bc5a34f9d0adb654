"""Run a notebook of ``notebooks/`` (stored without outputs) with nbclient.

Each notebook keeps its sizes (fleet sizes, records, rays, epochs, candidates) in one
code cell tagged ``parameters`` (the papermill convention); the tests run them on
smaller problems by passing ``overrides``, which are assigned in a new cell right
after that one (as papermill injects parameters), so the notebook's own defaults
stay what a user runs.
"""

from __future__ import annotations

import ast
import os
import shutil
import sys
from pathlib import Path

import pytest

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"


def parameters_cell(nb) -> int:
    """Index of the notebook's one code cell tagged ``parameters``."""
    found = [
        i
        for i, c in enumerate(nb.cells)
        if c.cell_type == "code" and "parameters" in c.get("metadata", {}).get("tags", [])
    ]
    assert len(found) == 1, f"expected one code cell tagged 'parameters', found {len(found)}"
    return found[0]


def parameter_names(nb) -> set[str]:
    """The names the ``parameters`` cell assigns."""
    tree = ast.parse(nb.cells[parameters_cell(nb)].source)
    targets = [t for node in tree.body if isinstance(node, ast.Assign) for t in node.targets]
    return {n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name)}


def inject_parameters(nb, overrides: dict):
    """Insert a cell assigning ``overrides`` (literals) right after the ``parameters`` cell."""
    import nbformat

    unknown = set(overrides) - parameter_names(nb)
    assert not unknown, f"not parameters of this notebook: {sorted(unknown)}"
    source = "# Injected parameters\n" + "\n".join(f"{k} = {v!r}" for k, v in overrides.items())
    for v in overrides.values():
        assert ast.literal_eval(repr(v)) == v, f"override {v!r} is not a literal"
    cell = nbformat.v4.new_code_cell(source, metadata={"tags": ["injected-parameters"]})
    nb.cells.insert(parameters_cell(nb) + 1, cell)
    return nb


def run_notebook(name: str, tmp_path: Path, monkeypatch, overrides: dict | None = None, timeout: int = 600):
    """Execute ``notebooks/<name>`` in ``tmp_path`` with this checkout's heliojax,
    with ``overrides`` of its ``parameters`` cell (see the module docstring).

    Returns ``(notebook, text_output, n_images)``. Skips when the ``python3``
    kernel does not run this interpreter.
    """
    nbclient = pytest.importorskip("nbclient")
    nbformat = pytest.importorskip("nbformat")
    pytest.importorskip("ipykernel")
    path = NOTEBOOKS / name
    nb = nbformat.read(path, as_version=4)
    assert all(not c.get("outputs") for c in nb.cells if c.cell_type == "code"), "store notebooks without outputs"
    parameters_cell(nb)  # every notebook declares its sizes in one place
    if overrides:
        inject_parameters(nb, overrides)
    shutil.copy(path, tmp_path / path.name)
    root = str(NOTEBOOKS.parent)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")])))
    monkeypatch.delenv("MPLBACKEND", raising=False)  # let the kernel use its inline backend
    from jupyter_client.kernelspec import KernelSpecManager

    spec = KernelSpecManager().get_kernel_spec("python3")
    if Path(spec.argv[0]).resolve() != Path(sys.executable).resolve() and spec.argv[0] != "python":
        pytest.skip(f"kernel python3 runs {spec.argv[0]}, not {sys.executable}")
    client = nbclient.NotebookClient(
        nb, kernel_name="python3", timeout=timeout, resources={"metadata": {"path": str(tmp_path)}}
    )
    client.execute()
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    text = "\n".join(o.get("text", "") for o in outputs)
    n_images = sum(1 for o in outputs if "image/png" in o.get("data", {}))
    return nb, text, n_images
