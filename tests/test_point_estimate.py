"""The fit's point estimate (``calib.inference.calibrate.point_estimate``): the
gradient stage's end point, unless the simulator scores the posterior's mode
clearly higher, and the calibration reports the point it checked."""

from __future__ import annotations

from types import SimpleNamespace

import jax
import numpy as np
import pytest

import calib.inference.calibrate as calibrate_module
from calib.files.observations import Observations
from calib.inference.calibrate import Budget, calibrate, point_estimate
from calib.inference.likelihood import RowLikelihood
from calib.model.forward import CrspForward
from calib.model.priors import CRSP_BOX
from solvers.profile import load_profile

PROFILE = load_profile("data/postignano_profile.csv")
# 1 m blocks from the profile's top: the paper's parameters stop them near 110 m
# (README, "Simulate one parameter set"); at the box's corner of little loss on a smooth
# slope they run on to 180-300 m
PAPER = np.array([0.41, 0.87, 2.0])
FAST = np.array([0.60, 0.98, 0.25])


def _setup():
    obs = Observations.points([1.0, 1.0], [108.0, 112.0], 5.0)
    fw = CrspForward(PROFILE, obs.sizes_m, 64, jax.random.key(3), box=CRSP_BOX)
    return obs, fw, RowLikelihood(obs)


def test_the_posterior_mode_replaces_a_gradient_point_the_simulator_scores_clearly_lower(
        monkeypatch):
    """calibrate with both stages: the gradient stage ends at the fast corner,
    the posterior's mode sits at the paper's; the estimate, its source, the
    check and the record are the mode's. (Before this rule the estimate was
    the gradient stage's point whenever that stage ran.)"""
    obs, fw, _ = _setup()
    monkeypatch.setattr(calibrate_module, "bayes_stage",
                        lambda *a, **k: (SimpleNamespace(map=PAPER), None, None, None, None))
    monkeypatch.setattr(calibrate_module, "gradient_stage",
                        lambda *a, **k: SimpleNamespace(theta=FAST))
    monkeypatch.setattr(calibrate_module, "fit_adequacy", lambda *a, **k: None)
    fit = calibrate(fw, obs, jax.random.key(4), ("gradient", "bayes"),
                    Budget(n_check=64))
    assert fit.estimate_source == "posterior_mode"
    np.testing.assert_array_equal(fit.estimate, PAPER)
    choice = fit.estimate_choice
    assert choice["chosen"] == "posterior_mode"
    gain = choice["posterior_mode"]["loglik"] - choice["gradient"]["loglik"]
    assert gain > choice["margin_nats"] > 0
    # the check simulated the mode: its median runout lies near the rows'
    assert all(abs(q["sim_median_m"] - 110.0) < 15.0 for q in fit.quality), fit.quality


def test_the_gradient_point_stays_unless_the_mode_is_clearly_better():
    """The reverse order keeps the gradient point, and so does a mode within
    the Monte Carlo margin of it (the same point nudged)."""
    _, fw, rows = _setup()
    theta, source, choice = point_estimate(fw, rows, SimpleNamespace(theta=PAPER),
                                           SimpleNamespace(map=FAST))
    assert source == "gradient" and choice["chosen"] == "gradient"
    np.testing.assert_array_equal(theta, PAPER)
    nudged = PAPER + np.array([1e-4, 0.0, 0.0])
    theta, source, choice = point_estimate(fw, rows, SimpleNamespace(theta=PAPER),
                                           SimpleNamespace(map=nudged))
    assert source == "gradient"
    assert abs(choice["posterior_mode"]["loglik"] - choice["gradient"]["loglik"]) \
        <= choice["margin_nats"]


def test_one_stage_gives_its_own_point_and_no_record():
    _, fw, rows = _setup()
    theta, source, choice = point_estimate(fw, rows, None, SimpleNamespace(map=PAPER))
    assert (source, choice) == ("posterior_mode", None)
    np.testing.assert_array_equal(theta, PAPER)
    theta, source, choice = point_estimate(fw, rows, SimpleNamespace(theta=FAST), None)
    assert (source, choice) == ("gradient", None)
    np.testing.assert_array_equal(theta, FAST)


@pytest.mark.parametrize("bad", [-np.inf])
def test_a_mode_with_no_finished_block_never_wins(monkeypatch, bad):
    """A point where a row got no finished block scores -inf: it is never chosen."""
    _, fw, rows = _setup()
    real = rows.summed
    monkeypatch.setattr(rows, "summed", lambda *a: np.array([real(*a)[0], bad]))
    _, source, choice = point_estimate(fw, rows, SimpleNamespace(theta=FAST),
                                       SimpleNamespace(map=PAPER))
    assert source == "gradient" and choice["posterior_mode"]["loglik"] is None


def _summary(kn_map: float, chosen: str) -> dict:
    def p(m, q05, q95):
        return {"map": m, "mean": 0.5 * (q05 + q95), "q05": q05, "q95": q95}
    return {"crsp": {"parameters": ["Kn", "Kt"], "Kn": p(kn_map, 0.396, 0.569),
                     "Kt": p(0.966, 0.940, 0.976), "prior": {},
                     "estimate_choice": {"chosen": chosen, "margin_nats": 4.9,
                                         "gradient": {"loglik": -294.6},
                                         "posterior_mode": {"loglik": -295.5}}}}


def test_the_summary_says_why_a_kept_gradient_point_lies_outside_an_interval(capsys):
    """Tschamut, seed 3: the gradient point (Kn 0.576) lies outside Kn's 90 % interval
    (0.396-0.569) and the simulator scores it as well as the posterior's mode. The
    summary says so, and that the posterior's draws carry the free combination; inside
    every interval it adds nothing."""
    from calib.fit import _print_parameters

    _print_parameters(_summary(0.576, "gradient"), ["crsp"])
    out = capsys.readouterr().out
    assert "outside the 90 % interval of Kn;" in out and "-294.6" in out and "-295.5" in out
    assert "posterior's draws" in out
    _print_parameters(_summary(0.480, "gradient"), ["crsp"])
    assert "outside the 90 % interval" not in capsys.readouterr().out


def test_the_summary_says_when_a_kept_gradient_point_beats_the_mode(capsys):
    from calib.fit import _print_parameters

    r = _summary(0.576, "gradient")
    r["crsp"]["estimate_choice"]["posterior_mode"]["loglik"] = -320.0
    _print_parameters(r, ["crsp"])
    out = capsys.readouterr().out
    assert "outside the 90 % interval of Kn;" in out and "may have missed the best region" in out
    assert "about as well" not in out
