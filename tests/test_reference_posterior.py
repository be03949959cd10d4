"""``scripts/reference_posterior.py`` (docs/studies.md): the importance weights of
a mixture of uniform sub-boxes give the posterior of a known likelihood, and the
command refuses a malformed sub-box before it simulates anything."""

from __future__ import annotations

import numpy as np
import pytest
from cli_run import load_script
from scipy.stats import norm, qmc

from calib.model.priors import CRSP_ROLLING_BOX


@pytest.fixture(scope="module")
def script():
    return load_script("reference_posterior")


def test_mixture_weights_recover_a_known_posterior(script):
    """A Gaussian log-likelihood inside the box, scored on two overlapping sub-boxes
    with different point counts: the weighted 5/50/95 % quantiles are the
    Gaussian's, and they are not when the mixture density is left out (the
    points of the smaller box, denser, would count twice)."""
    box = CRSP_ROLLING_BOX
    mu = np.array([0.40, 0.90, 0.11, 30.0])
    sd = np.array([0.03, 0.01, 0.006, 1.0])
    boxes = [(mu - 4 * sd, mu + 4 * sd), (mu, mu + 3 * sd)]
    counts = [1 << 13, 1 << 13]
    thetas = np.concatenate([lo + qmc.Sobol(4, seed=k).random(n) * (hi - lo)
                             for k, ((lo, hi), n) in enumerate(zip(boxes, counts))])
    ll = norm.logpdf(thetas, mu, sd).sum(1)
    log_q = script.mixture_log_density(thetas, boxes, counts)
    # q integrates to one over the union: the density of the points drawn
    inner = np.all((thetas >= boxes[1][0]) & (thetas <= boxes[1][1]), axis=1)
    vol = [np.prod(hi - lo) for lo, hi in boxes]
    np.testing.assert_allclose(np.exp(log_q[inner]), (1 / vol[0] + 1 / vol[1]) / 2)
    np.testing.assert_allclose(np.exp(log_q[~inner]), 1 / vol[0] / 2)
    s = script.summarise(thetas, ll, log_q, box, boxes)
    want = mu + sd * norm.ppf([[0.05], [0.5], [0.95]])  # (3, d)
    got = np.array(s["quantiles"]).T
    np.testing.assert_allclose((got - want) / sd, 0.0, atol=0.12)  # in units of sd
    assert s["ess"] > 200  # about 8,192 x 0.44^4 from the outer box alone
    assert not any(b["flagged"] for b in s["bound_mass"].values())
    wrong = script.summarise(thetas, ll, np.zeros_like(ll), box, boxes)
    assert abs(wrong["quantiles"][0][1] - mu[0]) > 0.2 * sd[0]


def test_a_posterior_at_a_bound_is_flagged_by_the_main_jobs_rule(script):
    """Kt's likelihood rising to the box's upper bound 0.98: its mass there is
    flagged by ``calib.inference.adequacy.bound_mass``, as the main job flags it."""
    box = CRSP_ROLLING_BOX
    lo = np.array([0.3, 0.90, 0.09, 34.0])
    hi = np.array([0.5, 0.98, 0.13, 38.0])
    thetas = lo + qmc.Sobol(4, seed=3).random(1 << 13) * (hi - lo)
    ll = 200.0 * thetas[:, 1]  # rising in Kt, flat elsewhere
    log_q = script.mixture_log_density(thetas, [(lo, hi)], [len(thetas)])
    s = script.summarise(thetas, ll, log_q, box, [(lo, hi)])
    assert s["bound_mass"]["Kt"]["upper_flagged"]
    assert not s["bound_mass"]["Kn"]["flagged"]


def test_a_malformed_start_box_is_refused_before_simulating(script, capsys):
    from cli_run import run_cli

    for bad in ("0.3,0.9,0.1:0.5,0.98,0.13,38", "a,b,c,d:1,2,3,4",
                "0.5,0.9,0.1,34:0.3,0.98,0.13,38"):
        rc, _, err = run_cli(script.main, ["data/tschamut2014/observations.csv",
                                           "--start-box", bad], capsys)
        assert rc == 2 and "--start-box" in err
    for bad in (["--coarse-share", "1.5"], ["--fine-blocks", "1"], ["--budget-s", "0"]):
        rc, _, err = run_cli(script.main, ["data/tschamut2014/observations.csv", *bad], capsys)
        assert rc == 2 and bad[0] in err


def test_one_point_within_the_kept_nats_still_spans_a_box(script):
    """A single best point (or points on a line) gives a sub-box of positive
    volume inside the prior box, so the mixture density stays finite."""
    lo, hi = np.asarray(CRSP_ROLLING_BOX.lower), np.asarray(CRSP_ROLLING_BOX.upper)
    thetas = np.array([[0.40, 0.93, 0.165, 34.4], [0.20, 0.70, 2.0, 10.0]])
    b_lo, b_hi = script.sub_box(thetas, np.array([-300.0, -400.0]), 15.0, 0.15, lo, hi)
    assert np.all(b_hi > b_lo) and np.all(b_lo >= lo) and np.all(b_hi <= hi)
    assert np.all((thetas[0] > b_lo) & (thetas[0] < b_hi))
    assert np.isfinite(script.mixture_log_density(thetas[:1], [(b_lo, b_hi)], [1])).all()


def test_a_block_set_with_no_finite_score_is_reported_not_raised(script):
    thetas = np.array([[0.4, 0.9, 0.1, 30.0], [0.41, 0.91, 0.11, 31.0]])
    box = (thetas.min(0) - 0.01, thetas.max(0) + 0.01)
    log_q = script.mixture_log_density(thetas, [box], [2])
    assert script.summarise(thetas, np.full(2, -np.inf), log_q, CRSP_ROLLING_BOX,
                            [box]) is None
