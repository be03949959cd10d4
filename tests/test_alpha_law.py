"""The DEM damping law alpha(L) and its one clipping rule (``calib.model.alpha_law``)."""

from __future__ import annotations

import numpy as np
import pytest

from calib.model.alpha_law import ALPHA_MAX, alpha_of, check_law
from calib.model.priors import DEM_BOXES


def test_alpha_laws():
    L = np.array([0.2, 0.9, 1.8])
    np.testing.assert_allclose(alpha_of("power", np.array([0.4, 0.5]), L),
                               np.minimum(0.4 * L**-0.5, 0.95))
    np.testing.assert_allclose(alpha_of("constant", np.array([0.43]), L), 0.43)
    assert float(alpha_of("power", np.array([0.9, 1.5]), np.array([0.2]))[0]) == ALPHA_MAX
    with pytest.raises(ValueError):
        alpha_of("cubic", np.array([1.0]), L)


@pytest.mark.parametrize("form", ["power", "constant"])
def test_every_prior_point_gives_an_accepted_alpha_at_every_size(form):
    """The clip keeps alpha(L) in [0, ALPHA_MAX] over the whole prior box and for
    sizes far outside the calibrated ones (the hazard run's choice)."""
    box = DEM_BOXES[form]
    theta = box.from_unit(np.random.default_rng(0).uniform(size=(256, box.dim)))
    theta = np.concatenate([box.lo[None], box.hi[None], theta])
    sides = np.geomspace(1e-3, 1e2, 11)
    alpha = np.asarray(alpha_of(form, theta, sides))
    assert alpha.shape == (theta.shape[0], sides.size)
    assert np.all((alpha >= 0) & (alpha <= ALPHA_MAX))
    assert check_law(form, theta, sides) is None


def test_check_law_names_the_first_refused_row():
    ok = [0.4, 0.5]
    assert check_law("power", [ok, [0.0, 0.5]], [0.5]) == (1, "a = 0 outside (0, inf]")
    row, why = check_law("power", [ok, ok, [0.4, np.nan]], [0.5])
    assert row == 2 and why.startswith("b = nan")
    assert check_law("constant", [[1.5]], [0.5]) == (0, "alpha = 1.5 outside [0, 1]")
    with pytest.raises(ValueError, match="expected 2 parameter"):
        check_law("power", [[0.4]], [0.5])
