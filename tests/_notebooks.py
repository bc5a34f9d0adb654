"""Run a notebook of ``notebooks/`` (stored without outputs) with nbclient.

Each notebook keeps its sizes (fleet sizes, records, rays, epochs, candidates) in one
code cell tagged ``parameters`` (the papermill convention); the tests run them on
smaller problems by passing ``overrides``, which are assigned in a new cell right
after that one (as papermill injects parameters), so the notebook's own defaults
stay what a user runs.

Every figure a notebook shows or saves is render-checked (``tests/_render_check.py``,
with the rules of ``tests/_figure_check.py``): a hidden first cell installs the check
in the kernel and a hidden last cell reports what it found; both are taken out of the
returned notebook again.
"""

from __future__ import annotations

import ast
import json
import os
import shutil
import sys
import tempfile
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
NOTEBOOKS = TESTS.parent / "notebooks"
RENDER_CHECK = "render-check"  # the tag of the hidden cells


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


def _render_check_cells(nbformat):
    """The hidden first and last cells of the render check (they show nothing)."""
    setup = f"__import__('sys').path.append({str(TESTS)!r}); __import__('_render_check').install()"
    tags = {"tags": [RENDER_CHECK]}
    return nbformat.v4.new_code_cell(setup, metadata=tags), nbformat.v4.new_code_cell(
        "__import__('_render_check').report()", metadata=tags
    )


def _figure_problems(nb, setup: dict, report: dict) -> list[str]:
    """The render check's findings, each naming its cell (index in the stored notebook)."""
    from _render_check import MARKER

    lines = [t for o in report.get("outputs", []) for t in o.get("text", "").splitlines() if t.startswith(MARKER)]
    assert len(lines) == 1, f"the render check reported nothing: {report.get('outputs')}"
    found = json.loads(lines[0][len(MARKER) :])
    shown = [o for c in nb.cells for o in c.get("outputs", []) if "image/png" in o.get("data", {})]
    figures = sum(1 for o in shown if o["data"].get("text/plain", "").startswith("<Figure"))
    assert found["figures_checked"] >= figures, f"{figures} figures shown, {found['figures_checked']} checked"
    stored = [c for c in nb.cells if "injected-parameters" not in c.get("metadata", {}).get("tags", [])]
    where = {c.get("execution_count"): (k, c) for k, c in enumerate(stored) if c.cell_type == "code"}
    problems = []
    for p in found["problems"]:
        k, cell = where.get(setup["execution_count"] + p["cells_after_install"], (None, None))
        if cell is None:
            problems.append(f"injected cell: {p['figure']}: {p['problem']}")
        else:
            first = next((line for line in cell.source.splitlines() if line.strip()), "")
            problems.append(f"cell {k} ({first[:50]!r}): {p['figure']}: {p['problem']}")
    return problems


def execute_notebook(path: Path, tmp_path: Path, monkeypatch, overrides: dict | None = None, timeout: int = 600):
    """Execute the notebook at ``path`` in ``tmp_path`` with this checkout's heliojax,
    with ``overrides`` of its ``parameters`` cell (see the module docstring).

    Returns ``(notebook, text_output, n_images, figure_problems)``. Skips when the
    ``python3`` kernel does not run this interpreter.
    """
    nbclient = pytest.importorskip("nbclient")
    nbformat = pytest.importorskip("nbformat")
    pytest.importorskip("ipykernel")
    nb = nbformat.read(path, as_version=4)
    assert all(not c.get("outputs") for c in nb.cells if c.cell_type == "code"), "store notebooks without outputs"
    parameters_cell(nb)  # every notebook declares its sizes in one place
    if overrides:
        inject_parameters(nb, overrides)
    if path.resolve() != (tmp_path / path.name).resolve():
        shutil.copy(path, tmp_path / path.name)
    root = str(NOTEBOOKS.parent)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")])))
    monkeypatch.delenv("MPLBACKEND", raising=False)  # let the kernel use its inline backend
    from jupyter_client.kernelspec import KernelSpecManager

    spec = KernelSpecManager().get_kernel_spec("python3")
    if Path(spec.argv[0]).resolve() != Path(sys.executable).resolve() and spec.argv[0] != "python":
        pytest.skip(f"kernel python3 runs {spec.argv[0]}, not {sys.executable}")
    setup, report = _render_check_cells(nbformat)
    nb.cells = [setup, *nb.cells, report]
    from traitlets.config import Config

    # IPC sockets, not TCP ports: kernels started at once by the xdist workers picked the same free
    # port now and then ("Address already in use", the kernel died before replying). nbclient still
    # creates, owns and closes the kernel manager and its client.
    sockets = tempfile.mkdtemp(prefix="hjk")  # short: a Unix socket path has ~100 characters
    config = Config({"KernelManager": {"transport": "ipc", "ip": os.path.join(sockets, "k")}})
    client = nbclient.NotebookClient(
        nb, kernel_name="python3", timeout=timeout, resources={"metadata": {"path": str(tmp_path)}}, config=config
    )
    try:
        client.execute()
    finally:
        shutil.rmtree(sockets, ignore_errors=True)
    assert not setup.get("outputs"), f"the render check's setup cell showed {setup.outputs}"
    nb.cells = nb.cells[1:-1]
    problems = _figure_problems(nb, setup, report)
    code = [c for c in nb.cells if c.cell_type == "code"]
    outputs = [o for c in code for o in c.get("outputs", [])]
    # a cell's stream output arrives in as many chunks as the kernel flushed (more under
    # load: one print's words in two): joined as written, the cells by a newline
    text = "\n".join("".join(o.get("text", "") for o in c.get("outputs", [])) for c in code)
    n_images = sum(1 for o in outputs if "image/png" in o.get("data", {}))
    return nb, text, n_images, problems


def run_notebook(name: str | Path, tmp_path: Path, monkeypatch, overrides: dict | None = None, timeout: int = 600):
    """Execute ``notebooks/<name>`` (or the notebook at the path ``name``; see
    :func:`execute_notebook`) and assert that every figure it shows or saves passes
    the render check.

    Returns ``(notebook, text_output, n_images)``.
    """
    path = name if isinstance(name, Path) else NOTEBOOKS / name
    nb, text, n_images, problems = execute_notebook(path, tmp_path, monkeypatch, overrides, timeout)
    assert not problems, f"figures of {path.name} fail the render check:\n" + "\n".join(problems)
    return nb, text, n_images
