"""The notebooks' render check (tests/_render_check.py): every figure a notebook
shows, at the end of a cell or by ``plt.show()`` inside one, is checked with the
rules of tests/_figure_check.py, and so is every figure it saves."""

import matplotlib.pyplot as plt
import pytest
from _figure_check import figure_problems
from _notebooks import execute_notebook, run_notebook

CELLS = [
    ("markdown", "# A tiny notebook"),
    ("parameters", "n = 10"),
    ("code", "%matplotlib inline\nimport matplotlib.pyplot as plt\nimport numpy as np"),
    (
        "code",
        'fig, ax = plt.subplots()\nax.plot(np.arange(n))\nax.set_xlabel("step")\nax.set_ylabel("height [m]")\n'
        'ax.set_title("good")',
    ),
    (
        "code",
        'fig, ax = plt.subplots()\nax.plot(np.arange(n))\nax.set_xlabel("step")\nax.set_title("shown")\n'
        'plt.show()\nprint("after show")',
    ),
    ("code", 'fig, ax = plt.subplots()\nax.plot(np.arange(n))\nax.set_xlabel("step")\nax.set_title("flushed")'),
    (
        "code",
        'good, ax = plt.subplots()\nax.plot([0, 1])\nax.set_xlabel("x [m]")\nax.set_ylabel("y [m]")\n'
        'good.savefig("good.png")\n'
        'bad, ax = plt.subplots()\nax.plot([0, 1])\nax.set_xlabel("x [m]")\n'
        'try:\n    bad.savefig("bad.png")\nexcept AssertionError as e:\n    print("savefig refused:", e)\n'
        'plt.close("all")',
    ),
]


def test_cut_off_counts_drawn_tick_labels_only():
    # the locator's ticks at -0.2 and 1.2 lie beyond the view limits (and the canvas):
    # their labels are not drawn; a drawn tick label beyond the canvas is cut off
    fig, ax = plt.subplots(figsize=(6.4, 4.8), dpi=100)
    ax.plot([0.0, 1.0])
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    assert "−0.2" in [t.get_text() for t in ax.get_yticklabels()]
    assert figure_problems(fig) == []
    ax.set_yticks([0.0, 1.0], ["0", "a tick label that is far too long for the left margin of this figure"])
    assert "axes 0 (untitled): text 'a tick label that is far too long for th' is cut off" in figure_problems(fig)
    plt.close(fig)


def _write_notebook(path, cells):
    nbformat = pytest.importorskip("nbformat")
    new = {
        "markdown": nbformat.v4.new_markdown_cell,
        "code": nbformat.v4.new_code_cell,
        "parameters": lambda s: nbformat.v4.new_code_cell(s, metadata={"tags": ["parameters"]}),
    }
    nbformat.write(nbformat.v4.new_notebook(cells=[new[kind](source) for kind, source in cells]), path)
    return path


def test_notebook_figures_are_render_checked(tmp_path, monkeypatch):
    path = _write_notebook(tmp_path / "tiny.ipynb", CELLS)
    nb, text, n_images, problems = execute_notebook(path, tmp_path, monkeypatch, overrides={"n": 5})
    # the figure shown (and closed) by plt.show() inside cell 4 and the one the inline
    # backend shows after cell 5 miss their y labels; cell 3's figure has both labels
    assert len(problems) == 2, problems
    assert problems[0].startswith("cell 4 ('fig, ax = plt.subplots()'): figure ")
    assert problems[0].endswith(": axes 0 (shown): no y label")
    assert problems[1].startswith("cell 5 ") and problems[1].endswith(": axes 0 (flushed): no y label")
    # a saved figure is checked in the kernel as in the test process
    assert "savefig refused: figure bad.png: axes 0 (untitled): no y label" in text
    assert (tmp_path / "good.png").exists() and not (tmp_path / "bad.png").exists()
    # and the outputs are the notebook's own: three figures shown, no hidden cells
    assert n_images == 3 and "after show" in text
    assert [c.source for c in nb.cells if "injected-parameters" not in c.metadata.get("tags", [])] == [
        source for _, source in CELLS
    ]


def test_run_notebook_fails_on_an_unreadable_figure(tmp_path, monkeypatch):
    cells = [*CELLS[:3], ("code", 'plt.imshow(np.eye(n))\nplt.xlabel("column")\nplt.ylabel("row")')]
    path = _write_notebook(tmp_path / "image.ipynb", cells)
    with pytest.raises(AssertionError, match=r"image.ipynb fail the render check:\ncell 3 .*without a colour bar"):
        run_notebook(path, tmp_path, monkeypatch)
