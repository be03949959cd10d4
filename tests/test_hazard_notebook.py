"""notebooks/02_hazard.py executes end to end at small size (jupytext + nbclient)."""

from __future__ import annotations

import os

import jupytext
import pytest
from nbclient import NotebookClient
from test_hazard_fixtures import posterior_rows, write_calibration

NOTEBOOK = os.path.join("notebooks", "02_hazard.py")


@pytest.mark.slow  # the notebook end to end, 16 s; tests/test_hazard_cli.py runs the command
def test_hazard_notebook_runs_small(tmp_path, monkeypatch):
    cal = write_calibration(tmp_path, crsp_posterior=posterior_rows(20))
    out = tmp_path / "nb"
    monkeypatch.setenv("HAZARD_NOTEBOOK_SMALL", "1")
    monkeypatch.setenv("HAZARD_CALIBRATION", cal)
    monkeypatch.setenv("HAZARD_NOTEBOOK_OUT", str(out))
    nb = jupytext.read(NOTEBOOK)
    client = NotebookClient(nb, timeout=600, kernel_name="python3",
                            resources={"metadata": {"path": os.getcwd()}})
    client.execute()
    text = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code"
                   for o in c.get("outputs", []))
    assert "P(reach road)" in text
    assert "E p95 =" in text or "no simulated block reaches the road" in text
    for name in ("exceedance.png", "envelopes.png", "zoning.png"):
        assert (out / name).stat().st_size > 0, name
    errors = [o for c in nb.cells for o in c.get("outputs", []) if o.output_type == "error"]
    if errors:
        pytest.fail(str(errors[0]))
