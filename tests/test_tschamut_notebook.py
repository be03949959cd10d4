"""notebooks/04_tschamut.py executes top to bottom with quick budgets: raster ->
profile -> observations -> calibration with a held-out check.

Slow (a quick Tschamut fit, about 2-3 minutes on 2 cores): run with -m slow."""

from __future__ import annotations

import os

import pytest


@pytest.mark.slow
def test_notebook_04_tschamut_runs_quick(tmp_path, monkeypatch):
    import jupytext
    import nbclient

    nb = jupytext.read("notebooks/04_tschamut.py")
    monkeypatch.setenv("NOTEBOOK_QUICK", "1")
    monkeypatch.setenv("NOTEBOOK_WORK", str(tmp_path))
    nbclient.NotebookClient(nb, timeout=900, kernel_name="python3",
                            resources={"metadata": {"path": os.getcwd()}}).execute()
    text = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code"
                   for o in c.get("outputs", []))
    assert "same profile as the shipped one: True" in text
    assert "held-out rows scored: 19" in text and "against climatology" in text
    assert "can the model fit these rows?" in text
    assert (tmp_path / "fit" / "validation" / "validation.json").is_file()
