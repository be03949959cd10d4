"""notebooks/05_protection.py executes end to end at small size (jupytext + nbclient),
from calibration files written here (no fit), and imports no private module."""

from __future__ import annotations

import ast
import json
import os

import jupytext
import numpy as np
import pytest
from nbclient import NotebookClient
from test_hazard_fixtures import posterior_rows, write_calibration

NOTEBOOK = os.path.join("notebooks", "05_protection.py")


def test_protection_notebook_imports_only_public_modules():
    with open(NOTEBOOK) as fh:
        tree = ast.parse(fh.read())
    names = [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    names += [n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    assert not [m for m in names if any(p.startswith("_") for p in m.split("."))]
    calls = [n.func for n in ast.walk(tree) if isinstance(n, ast.Call)]
    # the design and hazard are called as a library, not as commands
    assert "main" not in {getattr(f, "id", None) for f in calls}


def _tschamut_calibration(folder) -> str:
    """A CRSP calibration on the Tschamut profile at the site's density (2650 kg/m^3)."""
    rng = np.random.default_rng(2)
    rows = np.column_stack([rng.uniform(0.46, 0.56, 10), rng.uniform(0.92, 0.96, 10),
                            rng.uniform(0.10, 0.12, 10), rng.uniform(30.0, 35.0, 10)])
    path = write_calibration(folder, crsp=(0.51, 0.94, 0.11, 32.0), dem=None,
                             profile=os.path.abspath("data/tschamut2014/profile.csv"),
                             crsp_posterior=rows)
    with open(path) as fh:
        doc = json.load(fh)
    doc.update(rock_density_kg_m3=2650.0, release_x_m=41.0,
               data_csv=os.path.abspath("data/tschamut2014/observations.csv"))
    # a posterior that failed its diagnostics: the notebook must say so beside the design
    doc["crsp"]["bayes"] = {"ok": False, "problems": ["the GP realisation check failed"]}
    with open(path, "w") as fh:
        json.dump(doc, fh)
    return path


# slow: the notebook end to end at its small budget, 50 s; the default run keeps its import check
# and tests/test_design.py
@pytest.mark.slow
def test_protection_notebook_runs_small(tmp_path, monkeypatch):
    (tmp_path / "p").mkdir()
    (tmp_path / "t").mkdir()
    out = tmp_path / "nb"
    monkeypatch.setenv("PROTECTION_NOTEBOOK_SMALL", "1")
    monkeypatch.setenv("PROTECTION_CALIBRATION",
                       write_calibration(tmp_path / "p", crsp_posterior=posterior_rows(20)))
    monkeypatch.setenv("PROTECTION_TSCHAMUT_CALIBRATION", _tschamut_calibration(tmp_path / "t"))
    monkeypatch.setenv("PROTECTION_NOTEBOOK_OUT", str(out))
    nb = jupytext.read(NOTEBOOK)
    client = NotebookClient(nb, timeout=600, kernel_name="python3",
                            resources={"metadata": {"path": os.getcwd()}})
    client.execute()
    errors = [o for c in nb.cells for o in c.get("outputs", []) if o.output_type == "error"]
    if errors:
        pytest.fail(str(errors[0]))
    text = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code"
                   for o in c.get("outputs", []))
    for needle in ("road at x = 230 m, foot of the talus at x = 110 m", "barrier at x = ",
                   "gamma_Tr = 1.02", "crossings: below the horizontal",
                   "p_exceed_mean_with_barrier", "rock density 2650 kg/m^3",
                   "St. Leonard", "design block: Most heavy, 79 kg",
                   "THE CALIBRATION'S POSTERIOR FAILED ITS DIAGNOSTICS",
                   "the GP realisation check failed"):
        assert needle in text, needle
    for name in ("postignano_scan.png", "postignano_profile.png",
                 "postignano_distributions.png", "postignano_exceedance.png"):
        assert (out / name).stat().st_size > 0, name
