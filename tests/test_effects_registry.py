"""The effect registry: one declaration per effect, and the invariants
that tie its parts together (cheap: no simulation)."""

from __future__ import annotations

import numpy as np
import pytest

from calib.model.effects import (
    CRSP_EFFECTS,
    DEM_EFFECTS,
    EFFECTS,
    crsp_overrides,
    effect_box,
    full_box,
    truth,
)
from solvers import crsp
from solvers.profile import load_profile

PROFILE = load_profile("data/postignano_profile.csv")


def test_the_lists_of_effects_come_from_the_registry():
    assert CRSP_EFFECTS == tuple(EFFECTS) and CRSP_EFFECTS[0] == "none"
    assert DEM_EFFECTS == ("none", "size_dissipation", "fragmentation")
    for name in DEM_EFFECTS:
        assert len(EFFECTS[name].dem_grid) == effect_box(name, PROFILE, "dem").dim


@pytest.mark.parametrize("name", CRSP_EFFECTS)
@pytest.mark.parametrize("strength", [0.5, 1.0, 2.0])
def test_crsp_truth_lies_in_its_candidate_box_and_reaches_the_solver(name, strength):
    """Synthetic data's truth is a point of the candidate's own prior; its columns
    map onto fields that CRSP's Params has."""
    theta = truth(name, strength, PROFILE)
    box = full_box(name, PROFILE)
    assert theta.shape == (box.dim,) and box.contains(theta), (theta, box)
    fields = set(crsp.Params._fields)
    over = crsp_overrides(name, theta[None, 3:], PROFILE)
    assert set(over) <= fields
    assert all(np.shape(v) == (1,) for v in over.values())


@pytest.mark.parametrize("name", DEM_EFFECTS)
@pytest.mark.parametrize("strength", [0.5, 1.0])
def test_dem_truth_lies_in_its_candidate_box(name, strength):
    theta = truth(name, strength, PROFILE, "dem")
    assert effect_box(name, PROFILE, "dem").contains(theta)


def test_unknown_effects_and_models_are_refused_by_name():
    with pytest.raises(ValueError, match="unknown effect 'teleport'"):
        effect_box("teleport", PROFILE)
    with pytest.raises(ValueError, match="not available for the DEM"):
        effect_box("vegetation_belt", PROFILE, "dem")
    with pytest.raises(ValueError, match="strength"):
        truth("none", 0.0, PROFILE)


def test_a_forward_with_an_effect_keeps_the_base_box_it_was_given():
    """CrspForward(box=base, effect=E) fits base's ranges plus E's columns: a custom
    base box (here a narrower Kn range, and a narrower rolling angle) is not
    swapped for the stock CRSP_BOX or CRSP_ROLLING_BOX; dataclasses.replace keeps
    the one box (E's columns not added twice); a box that already ends with E's
    columns is taken as given (a custom range of the effect too)."""
    import dataclasses

    import jax

    from calib.model.forward import CrspForward
    from calib.model.priors import CRSP_BOX, CRSP_ROLLING_BOX, Box

    narrow = Box(CRSP_BOX.names, (0.30,) + CRSP_BOX.lower[1:], (0.50,) + CRSP_BOX.upper[1:])
    fw = CrspForward(PROFILE, np.array([1.0]), 4, jax.random.key(0), box=narrow,
                     effect="size_dissipation")
    assert fw.box == full_box("size_dissipation", PROFILE, base=narrow)
    assert (fw.box.lower[0], fw.box.upper[0]) == (0.30, 0.50)
    assert dataclasses.replace(fw, n_blocks=8).box == fw.box

    rolling = Box(CRSP_ROLLING_BOX.names, CRSP_ROLLING_BOX.lower[:3] + (10.0,),
                  CRSP_ROLLING_BOX.upper[:3] + (20.0,))
    fw = CrspForward(PROFILE, np.array([1.0]), 4, jax.random.key(0), box=rolling,
                     effect="vegetation_belt")
    assert fw.n_rolling == 1 and (fw.box.lower[3], fw.box.upper[3]) == (10.0, 20.0)
    assert fw.box.names == rolling.names + ("belt_start_m", "belt_loss")

    mine = Box(narrow.names + ("gamma",), narrow.lower + (-0.2,), narrow.upper + (0.2,))
    assert CrspForward(PROFILE, np.array([1.0]), 4, jax.random.key(0), box=mine,
                       effect="size_dissipation").box == mine
    with pytest.raises(ValueError, match="already has the size_dissipation effect's"):
        full_box("size_dissipation", PROFILE, base=mine)  # gamma would come twice
