"""Temporaries of the atomic writers: a signal at any point leaves none behind, and
each carries its writer in its name (a hostile-input round's kill loop left
``.results.<host>-<pid>.<random>.heliojax-tmp.h5`` once in 10 SIGTERMs: the signal
came between ``tempfile.mkstemp`` making the file and the writer recording it)."""

from __future__ import annotations

import os

import pytest

import heliojax._io as io


def _interrupted_right_after_making(monkeypatch):
    made = []
    real = io.make_temporary

    def make_then_signal(path):
        real(path)
        made.append(path)
        raise KeyboardInterrupt  # what the CLI's SIGTERM handler raises, at the worst moment

    monkeypatch.setattr(io, "make_temporary", make_then_signal)
    return made


@pytest.mark.parametrize("writer", ["atomic_write", "atomic_path", "staged_paths"])
def test_a_signal_right_after_a_temporary_is_made_leaves_nothing(tmp_path, monkeypatch, writer):
    made = _interrupted_right_after_making(monkeypatch)
    out = tmp_path / "results.h5"
    with pytest.raises(KeyboardInterrupt):
        if writer == "atomic_write":
            with io.atomic_write(out) as f:
                f.write("x")
        elif writer == "atomic_path":
            with io.atomic_path(out) as p:
                p.write_text("x")
        else:
            with io.staged_paths([out, tmp_path / "summary.json"]) as paths:
                paths[0].write_text("x")
    assert len(made) == 1 and not made[0].exists()  # it was made, and it was removed
    assert list(tmp_path.iterdir()) == []


def test_a_temporary_names_its_writer_so_a_killed_ones_is_removed_at_once(tmp_path):
    """The writable-folder probe of the CLI too (``.probe.<host>-<pid>.…``): one left by
    ``kill -9`` had no owner in its name and was kept for an hour."""
    from heliojax.cli._common import _check_a_file_can_be_made

    path = io.new_temporary(tmp_path, "probe")
    owner = io._OWNER.search(path.name)
    assert owner is not None and int(owner["pid"]) == os.getpid()
    _check_a_file_can_be_made("--out", tmp_path / "x.h5", tmp_path)
    assert list(tmp_path.iterdir()) == []  # the probe is gone
    io.make_temporary(path)
    with pytest.raises(FileExistsError):
        io.make_temporary(path)
    assert oct(path.stat().st_mode & 0o777) == oct(0o600)  # the owner's until published
