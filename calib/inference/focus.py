"""Refocusing: the part of the prior box that the simulator's own likelihood does
not rule out, where the emulator is refitted and NUTS samples.

Why (measured on the Tschamut rows, ``python -m calib.fit
data/tschamut2014/observations.csv --holdout-fraction 0.3 --seed 1``): the
likelihood is peaked in a thin part of the box (roughness S of 0.05-0.1 m out
of 0.01-4 m), while over most of the box blocks crawl and every run of a
group stops at the same point. One GP per runout quantile over the whole box
cannot follow both regimes; NUTS on it settled where the emulator was wrong
(S about 2.5 m, phi_r about 8 deg), a region whose SIMULATED log-likelihood
was thousands of nats below the design's best point.

The rule (history matching's refocusing, Vernon, Goldstein & Bower 2010,
Bayesian Analysis 5, 619-670: later waves are designed and emulated only in
the region earlier waves have not ruled out; the thresholds are our own):

1. Keep the design points whose simulated summed log-likelihood is within
   ``NATS_PER_ROW`` x n_rows of the best one (at least ``2 d`` points, the
   best ones, so the region has a volume).
2. The focus box is their bounding box in the emulator's coordinates
   (``forward.to_input``), widened by ``MARGIN`` of the input box's width on
   each side; a face that then lies within another ``MARGIN`` of the input
   box's own face is moved onto it (so is one beyond it); its image in theta is again a box (every
   coordinate of ``to_input`` is monotone in its own parameter).
3. A third design fills the focus box: half of it scrambled Sobol, half
   drawn from the posterior of an emulator fitted on the points inside it so
   far (so the emulator learns where it wrongly put mass); the emulator is
   refitted on every design point inside it, and NUTS samples the prior
   restricted to it.

4. Where the posterior then piles against a face of the focus box that is
   not a prior bound (``cut_faces``), that face moves out by ``MARGIN``
   (``widen``), the slab it uncovers gets new design points, and the
   emulator and NUTS run again; at most ``MAX_WIDEN`` times, after which a
   face that still holds the posterior is reported.

This truncates the prior. The posterior mass it drops is that of points whose
likelihood is e^-(NATS_PER_ROW n_rows) of the best one's or less, as far as
the design resolves the box; where the posterior piles against a face of the
focus box that is not a prior bound, the truncation may have cut it, and
``face_problems`` says so (the command prints it with the failed diagnostics).

``FocusRegion`` is the region as the Bayesian stage (``calib.inference.bayes_stage``)
holds it: found around a design, widened, and recorded.
"""

from __future__ import annotations

import jax
import numpy as np

from calib.inference.adequacy import BOUND_BAND, bound_mass
from calib.model.priors import Box

__all__ = ["MARGIN", "MAX_WIDEN", "NATS_PER_ROW", "FocusRegion", "cut_faces", "face_problems",
           "focus_boxes", "region_record", "theta_box", "widen"]

NATS_PER_ROW = 3.0  # points this close to the best simulated log-likelihood are kept
MARGIN = 0.10  # widening of the kept points' bounding box, fraction of the input box
MAX_WIDEN = 3  # times a cut face is moved outward before the cut is reported


class FocusRegion:
    """The focus region of one fit (module docstring): its box in the emulator's
    coordinates (``input_box``, where the GP is fitted) and in theta (``box``,
    the prior restricted to it, where NUTS samples), widened while the
    posterior piles against one of its faces (at most ``MAX_WIDEN`` times).

    Attributes:
        input_box, box: the focus box in both coordinates.
        prior: the prior box, theta.
        record: its ``bayes.focus`` record (``focus_boxes``; ``widened``: the
            faces moved, one list per widening).
        n_widened: how often it was widened.
    """

    def __init__(self, forward, input_box: Box, box: Box, record: dict):
        self.forward, self.input_box, self.box, self.record = forward, input_box, box, record
        self.prior = forward.box
        self.n_widened = 0
        record.update(widened=[])

    @classmethod
    def around(cls, forward, design, n_rows: int) -> FocusRegion | None:
        """The region ``focus_boxes`` draws around the simulated ``design``
        (``calib.inference.design_waves.Design``); None where it draws none."""
        focus = focus_boxes(forward, design.theta, design.ll, n_rows)
        return None if focus is None else cls(forward, *focus)

    def narrow(self, design, threshold_nats: float) -> tuple[Box, Box]:
        """Refocus on the design points inside the region whose simulated
        log-likelihood lies within ``threshold_nats`` of the best one's
        (``focus_boxes``' rule with that band), the new box inside the old.
        Returns (input box, theta box) of the new region."""
        inside = design.inside(self.input_box)
        ibox, _, rec = focus_boxes(self.forward, design.theta[inside], design.ll[inside], 0,
                                   threshold_nats)
        lo = np.maximum(ibox.lo, self.input_box.lo)
        hi = np.minimum(ibox.hi, self.input_box.hi)
        self.input_box = Box(ibox.names, tuple(map(float, lo)), tuple(map(float, hi)))
        self.box = theta_box(self.forward, lo, hi)
        self.record.setdefault("narrowed", []).append(
            {k: rec[k] for k in ("rule", "best_loglik", "threshold_nats", "n_kept")}
            | region_record(self.box, self.prior))
        return self.input_box, self.box

    def faces_holding(self, samples: np.ndarray) -> list[tuple[int, str, float]]:
        """The faces that hold the posterior ``samples`` (``cut_faces``)."""
        return cut_faces(samples, self.box, self.prior)

    def widen_faces(self, faces, design, n: int, key: jax.Array) -> None:
        """Move ``faces`` outward (``widen``) and fill each slab they uncover with
        its share of ``n`` new design points, at least 2 (``Design.fill``; slab
        j with the key fold_in(key, 16 x widenings so far + j))."""
        self.input_box, self.box, slabs = widen(self.forward, self.input_box, faces)
        self.record["widened"].append([{"parameter": self.prior.names[i], "side": side,
                                        "posterior_mass_at_face": mass}
                                       for i, side, mass in faces])
        per = max(2, n // len(slabs))
        for j, slab in enumerate(slabs):
            design.fill(slab, self.box, per, jax.random.fold_in(key, 16 * self.n_widened + j))
        self.n_widened += 1

    def finish(self, samples: np.ndarray, design) -> list[str]:
        """Complete the record (the design points inside the region, its bounds
        after any widening) and say which faces hold the posterior
        (``face_problems``)."""
        self.record["n_emulator_points"] = int(design.inside(self.input_box).sum())
        self.record.update(region_record(self.box, self.prior))
        return face_problems(samples, self.box, self.prior)


def focus_boxes(forward, design_theta: np.ndarray, design_ll: np.ndarray, n_rows: int,
                threshold_nats: float | None = None) -> tuple[Box, Box, dict] | None:
    """The focus box in the emulator's coordinates and in theta, and its record.

    Args:
        forward: a forward model with ``to_input``/``from_input`` and ``box``,
            ``input_box`` (``CrspForward``).
        design_theta: (D, d) design points in theta.
        design_ll: (D,) their simulated summed log-likelihood (-inf: a row got
            no finished block).
        n_rows: observation rows in the likelihood.
        threshold_nats: the band below the best point that is kept (default
            ``NATS_PER_ROW`` x ``n_rows``).

    Returns:
        (input box, theta box, record) or None where no design point has a
        finite log-likelihood.
    """
    ll = np.asarray(design_ll, float)
    if not np.isfinite(ll).any():
        return None
    ibox, box = forward.input_box, forward.box
    d = box.dim
    order = np.argsort(-np.where(np.isfinite(ll), ll, -np.inf))
    threshold = NATS_PER_ROW * n_rows if threshold_nats is None else threshold_nats
    keep = order[:max(2 * d, int(np.sum(ll >= ll[order[0]] - threshold)))]
    u = np.asarray(forward.to_input(np.asarray(design_theta, float)[keep]))
    span = ibox.hi - ibox.lo
    lo, hi = _to_bounds(ibox, u.min(0) - MARGIN * span, u.max(0) + MARGIN * span)
    fbox = theta_box(forward, lo, hi)
    record = {
        "rule": (f"design points within {threshold:.1f} nats of the best simulated "
                 f"log-likelihood (at least {2 * d}), their bounding box in the emulator's "
                 f"coordinates widened by {MARGIN:.0%} of the input box on each side "
                 "(history matching's refocusing, Vernon et al. 2010)"),
        "best_loglik": float(ll[order[0]]), "threshold_nats": float(threshold),
        "n_kept": int(len(keep)), "n_design": int(len(ll)),
        **region_record(fbox, box),
    }
    return Box(ibox.names, tuple(map(float, lo)), tuple(map(float, hi))), fbox, record


def region_record(focus: Box, prior: Box) -> dict:
    """The focus box's bounds in theta and its share of the prior box's volume."""
    return {"lower": dict(zip(prior.names, map(float, focus.lo), strict=True)),
            "upper": dict(zip(prior.names, map(float, focus.hi), strict=True)),
            "prior_volume_fraction": float(np.prod((focus.hi - focus.lo)
                                                   / (prior.hi - prior.lo)))}


def _to_bounds(ibox: Box, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Faces within ``MARGIN`` of the input box's own faces (or beyond them) moved
    onto them: no sliver of the prior is left out next to a bound the posterior
    may want."""
    m = MARGIN * (ibox.hi - ibox.lo)
    return np.where(lo < ibox.lo + m, ibox.lo, lo), np.where(hi > ibox.hi - m, ibox.hi, hi)


def theta_box(forward, lo: np.ndarray, hi: np.ndarray) -> Box:
    """The image in theta of the input box [lo, hi] (every coordinate of
    ``to_input`` is monotone in its own parameter), with the prior's own bounds,
    exactly, where it reaches them."""
    box = forward.box
    t_lo, t_hi = np.asarray(forward.from_input(lo)), np.asarray(forward.from_input(hi))
    t_lo, t_hi = np.minimum(t_lo, t_hi), np.maximum(t_lo, t_hi)
    t_lo, t_hi = _snap(t_lo, box.lo, box.hi), _snap(t_hi, box.lo, box.hi)
    return Box(box.names, tuple(map(float, t_lo)), tuple(map(float, t_hi)))


def cut_faces(samples: np.ndarray, focus: Box, prior: Box) -> list[tuple[int, str, float]]:
    """(parameter index, "lower"/"upper", mass) of each face of the focus box (in
    theta) that is not a prior bound and holds more than ``BOUND_FLAG`` of the
    posterior within ``BOUND_BAND`` of the focus box's width, the posterior
    reaching it (``calib.inference.adequacy.bound_mass`` on the focus box)."""
    mass = bound_mass(samples, focus)
    out = []
    for i, name in enumerate(prior.names):
        for side, edge, bound in (("lower", focus.lo[i], prior.lo[i]),
                                  ("upper", focus.hi[i], prior.hi[i])):
            if edge != bound and mass[name][f"{side}_flagged"]:
                out.append((i, side, float(mass[name][side])))
    return out


def widen(forward, input_box: Box, faces) -> tuple[Box, Box, list[Box]]:
    """Move each cut face (``cut_faces``) outward by ``MARGIN`` of the prior's
    input box (onto the prior's bound when it comes within another margin of
    it: ``_to_bounds``).

    Returns:
        (input box, theta box, slabs): the widened focus box in both
        coordinates, and per face the slab between its old and new position
        (input coordinates), where the next design points go.
    """
    ibox, box = forward.input_box, forward.box
    rising = np.asarray(forward.to_input(box.hi)) > np.asarray(forward.to_input(box.lo))
    step = MARGIN * (ibox.hi - ibox.lo)
    lo, hi = input_box.lo.copy(), input_box.hi.copy()
    for i, side, _ in faces:  # a theta face is the same input face where to_input rises
        if (side == "upper") == bool(rising[i]):
            hi[i] += step[i]
        else:
            lo[i] -= step[i]
    lo, hi = _to_bounds(ibox, lo, hi)
    slabs = []
    for i, side, _ in faces:
        s_lo, s_hi = lo.copy(), hi.copy()
        if (side == "upper") == bool(rising[i]):
            s_lo[i] = input_box.hi[i]
        else:
            s_hi[i] = input_box.lo[i]
        slabs.append(Box(ibox.names, tuple(map(float, s_lo)), tuple(map(float, s_hi))))
    return (Box(ibox.names, tuple(map(float, lo)), tuple(map(float, hi))),
            theta_box(forward, lo, hi), slabs)


def _snap(t: np.ndarray, lo: np.ndarray, hi: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """theta clipped to the prior box, and set to its bound where round-off left it
    within ``tol`` of the box's width from it."""
    t = np.clip(t, lo, hi)
    w = hi - lo
    return np.where(np.abs(t - lo) <= tol * w, lo, np.where(np.abs(t - hi) <= tol * w, hi, t))


def face_problems(samples: np.ndarray, focus: Box, prior: Box) -> list[str]:
    """The ``cut_faces`` in words: the truncation may have cut the posterior there."""
    return [f"{mass:.0%} of the posterior of {prior.names[i]} lies within {BOUND_BAND:.0%} "
            f"of the focus region's {side} edge "
            f"{(focus.lo if side == 'lower' else focus.hi)[i]:.4g} (not a prior bound): the "
            "refocusing may have cut the posterior"
            for i, side, mass in cut_faces(samples, focus, prior)]
