"""A full disk during a sweep, a notebook run or a batch: the error names the file."""

import errno
import os

import numpy as np
import pytest

import leglib as lg
from leglib.files import atomic

REAL = {name: getattr(os, name) for name in ("write", "link", "replace")}


def _full(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")   # as the kernel says it: no file


@pytest.mark.parametrize("call", ["write", "link"])
def test_a_sweep_on_a_full_disk_names_the_file(tmp_path, monkeypatch, call):
    with lg.connect("virtual", seed=3) as dev:
        lg.configure(dev)
        lg.calibrate(dev)
        monkeypatch.setattr(atomic.os, call, _full)
        with pytest.raises(OSError) as err:
            lg.sweep(dev, [(20.0, 0.02, 0.02)], tmp_path / "sweep", duration=0.2, progress=False)
        monkeypatch.undo()
    assert err.value.errno == errno.ENOSPC
    assert str(tmp_path / "sweep") in str(err.value) and "No space left on device" in str(err.value)


def test_a_figure_on_a_full_disk_names_the_file(tmp_path, monkeypatch):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from leglib.notebook.setup import save_figure
    fig, ax = plt.subplots()
    ax.plot(np.arange(3))
    monkeypatch.setattr(atomic.os, "write", _full)
    with pytest.raises(OSError, match=f"writing {tmp_path / 'figs' / 'fig_step.png'}: No space left"):
        save_figure(fig, tmp_path / "figs", "fig_step")
    monkeypatch.undo()
    assert not (tmp_path / "figs" / "fig_step.png").exists()
    path = save_figure(fig, tmp_path / "figs", "fig_step")
    assert path.read_bytes().startswith(b"\x89PNG")
    plt.close(fig)


def test_a_notebook_report_on_a_full_disk_names_the_file(tmp_path, monkeypatch):
    import nbformat
    import papermill as pm

    from leglib.notebook import run
    nb = nbformat.v4.new_notebook(cells=[nbformat.v4.new_markdown_cell("# x")])
    executed = tmp_path / "04_pid_sweeps.ipynb"
    nbformat.write(nb, str(executed))
    monkeypatch.setattr(atomic.os, "write", _full)
    with pytest.raises(OSError, match=f"writing {executed.with_suffix('.html')}: No space left"):
        run.to_html(executed)
    monkeypatch.undo()

    def papermill_on_a_full_disk(*args, **kwargs):   # papermill writing the executed copy
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(pm, "execute_notebook", papermill_on_a_full_disk)
    with pytest.raises(OSError, match=f"writing {tmp_path / 'out' / '04_pid_sweeps.ipynb'}: No space left"):
        run.execute(run.NOTEBOOK_DIR / "04_pid_sweeps.ipynb", tmp_path / "out")


def test_a_batch_index_on_a_full_disk_names_the_file(tmp_path, monkeypatch):
    from leglib.notebook import batch
    runs = [{"id": "run", "params": {}, "grid": {}}]
    monkeypatch.setattr(atomic.os, "write", _full)
    with pytest.raises(OSError, match=f"writing {tmp_path / 'index.html'}: No space left"):
        batch.write_index(tmp_path, runs, {"run": {"status": "done"}}, [])
