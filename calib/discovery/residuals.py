"""Where a calibrated model disagrees with the observations, and how sure that is.

Quantile residuals (Dunn & Smyth 1996, "Randomized quantile residuals", J.
Comput. Graph. Stat. 5, 236-244): row i's predictive CDF at its observed value,
``PIT_i = P(Y_i <= y_i)`` under the posterior predictive (simulated runout plus
the row's measurement noise), mapped to ``q_i = Phi^-1(PIT_i)``. If the model
is right the q_i are independent N(0, 1) (up to the posterior's own
uncertainty); q > 0 means the blocks went further than the model predicts.
Interval rows use their midpoint with sd = width / sqrt(12) (a uniform).

Two covariates are tested:

* block size: per size class, ``z = sum q_i / sqrt(n)`` (N(0, 1) under the
  model), and Spearman's rank correlation of q with size over all rows;
* stop position (posterior predictive check by slope part): the profile is cut
  into parts (its segments, long ones split into pieces of at most 1/6 of the
  profile's extent); per part the observed number of stops O is compared with
  the expected ``E = sum_i P_i(part)`` with variance ``sum_i P_i (1 - P_i)``:
  ``z = (O - E) / sd`` (a normal approximation, rough when E is below ~5).

Every test gives a two-sided p-value and its Bonferroni adjustment over all
tests made (``p_adj``); a place is flagged when ``p_adj < 0.05``.

The predictive samples are NaN for unfinished blocks (``calib.model.unfinished``);
every probability here is over the finished ones.
"""

from __future__ import annotations

import numpy as np
from scipy import stats

__all__ = ["locate", "point_view", "quantile_residuals", "slope_parts"]

P_FLAG = 0.05


def point_view(obs):
    """(y, sd) of each row; intervals as midpoint and width / sqrt(12)."""
    y = np.where(obs.is_interval, 0.5 * (obs.runout_min_m + obs.runout_max_m), obs.runout_m)
    sd = np.where(obs.is_interval, (obs.runout_max_m - obs.runout_min_m) / np.sqrt(12.0),
                  obs.runout_sd_m)
    return y, np.maximum(sd, 1e-6)


def quantile_residuals(obs, row_entry: np.ndarray, samples: np.ndarray):
    """(PIT, q) of each row given predictive runout samples per entry (E, m), row
    i's being ``samples[row_entry[i]]`` (NaN: an unfinished block, left out; an
    entry with none finished gives PIT 0.5)."""
    y, sd = point_view(obs)
    pit = np.array([_mean_or(stats.norm.cdf((y[i] - _finite(samples[row_entry[i]])) / sd[i]),
                             0.5) for i in range(obs.n_obs)])
    q = stats.norm.ppf(np.clip(pit, 1e-6, 1 - 1e-6))
    return pit, q


def _finite(x: np.ndarray) -> np.ndarray:
    return x[np.isfinite(x)]


def _mean_or(x: np.ndarray, empty: float) -> float:
    return float(np.mean(x)) if x.size else empty


def slope_parts(profile) -> list[tuple[float, float, str]]:
    """(x_from, x_to, zone) pieces of the profile: segments split to <= extent / 6."""
    x = np.asarray(profile.x_m, float)
    max_len = (x[-1] - x[0]) / 6.0
    names = getattr(profile, "zone_names", None)
    zone_id = np.asarray(getattr(profile, "zone_id", np.zeros(x.size - 1, int)))
    out = []
    for s in range(x.size - 1):
        n = max(1, int(np.ceil((x[s + 1] - x[s]) / max_len - 1e-9)))
        edges = np.linspace(x[s], x[s + 1], n + 1)
        zone = str(names[zone_id[s]]) if names is not None else f"segment {s}"
        out += [(float(a), float(b), zone) for a, b in zip(edges[:-1], edges[1:])]
    return out


def locate(obs, row_class: np.ndarray, class_sizes_m: np.ndarray, samples: np.ndarray,
           profile, rng: np.random.Generator, release_x_m=None,
           row_entry: np.ndarray | None = None) -> dict:
    """Residual tests against block size and stop position.

    Args:
        obs: ``Observations``.
        row_class: (n_obs,) size class of each row.
        class_sizes_m: (C,) representative size of each class, m.
        samples: (E, m) posterior-predictive runouts per simulated entry (without
            noise), m; NaN for an unfinished block (left out). Row i's are
            ``samples[row_entry[i]]``.
        profile: the slope.
        rng: NumPy generator (measurement noise of the predictive stop positions).
        release_x_m: where the blocks were released, m: one for all rows, or
            (n_obs,) each row's own, or None (the profile's first vertex); stop
            positions are release + runout.
        row_entry: (n_obs,) entry of each row in ``samples``; None: the entries
            are the size classes (``row_class``).

    Returns:
        dict with ``by_size``, ``size_trend``, ``by_slope_part``, ``flagged`` (list of
        plain-text findings, most significant first) and ``summary``.
    """
    entry = row_class if row_entry is None else row_entry
    pit, q = quantile_residuals(obs, entry, samples)
    y, sd = point_view(obs)
    x0 = np.broadcast_to(np.asarray(profile.x_m[0] if release_x_m is None else release_x_m,
                                    float), (obs.n_obs,))
    by_size = _size_tests(q, row_class, class_sizes_m)
    trend = _size_trend(obs, q)
    by_part = _slope_part_tests(slope_parts(profile), x0, y, sd, samples, entry, rng)
    n_tests = len(by_size) + len(by_part) + (trend["p_value"] is not None)
    flagged = _bonferroni_findings(by_size, trend, by_part, n_tests)
    summary = ("; ".join(flagged) if flagged else
               f"no size class or slope part departs from the model at the 5 % level after "
               f"Bonferroni correction over {n_tests} tests")
    return {"pit": pit.tolist(), "quantile_residual": q.tolist(), "by_size": by_size,
            "size_trend": trend, "by_slope_part": by_part, "n_tests": n_tests,
            "flagged": flagged, "summary": summary}


def _size_tests(q: np.ndarray, row_class: np.ndarray, class_sizes_m: np.ndarray) -> list[dict]:
    """Per size class with rows: ``z = sum q_i / sqrt(n)`` (N(0, 1) under the
    model) and its two-sided p-value."""
    by_size = []
    for c, d in enumerate(class_sizes_m):
        rows = row_class == c
        n = int(rows.sum())
        if n == 0:
            continue
        z = float(q[rows].sum() / np.sqrt(n))
        by_size.append({"size_m": float(d), "n": n, "mean_q": float(q[rows].mean()), "z": z,
                        "p_value": float(2 * stats.norm.sf(abs(z)))})
    return by_size


def _size_trend(obs, q: np.ndarray) -> dict:
    """Spearman's rank correlation of q with block size over all rows and its
    p-value (both None with fewer than 3 rows or a single size)."""
    if obs.n_obs >= 3 and np.unique(obs.block_size_m).size > 1:
        rho, p_rho = stats.spearmanr(obs.block_size_m, q)
        return {"spearman_rho": float(rho), "p_value": float(p_rho)}
    return {"spearman_rho": None, "p_value": None}


def _slope_part_tests(parts, x0: np.ndarray, y: np.ndarray, sd: np.ndarray,
                      samples: np.ndarray, entry: np.ndarray,
                      rng: np.random.Generator) -> list[dict]:
    """Per slope part: observed stops O against the expected ``E = sum_i P_i(part)``,
    ``P_i`` row i's predictive stop positions (release + runout + its measurement
    noise, one normal draw per simulated block) in the part; ``z = (O - E) / sd``
    with variance ``sum_i P_i (1 - P_i)`` floored at a quarter of a count."""
    edges = np.array([a for a, _, _ in parts] + [parts[-1][1]])
    stop_obs = x0 + y
    by_part = []
    probs = np.zeros((y.size, len(parts)))
    for i in range(y.size):
        noise = sd[i] * rng.standard_normal(samples.shape[1])  # drawn for every block
        s = x0[i] + samples[entry[i]] + noise
        s = s[np.isfinite(s)]
        idx = np.clip(np.searchsorted(edges, s, side="right") - 1, 0, len(parts) - 1)
        probs[i] = np.bincount(idx, minlength=len(parts)) / max(s.size, 1)
    obs_idx = np.clip(np.searchsorted(edges, stop_obs, side="right") - 1, 0, len(parts) - 1)
    for b, (a, e, zone) in enumerate(parts):
        o = int(np.sum(obs_idx == b))
        ex = float(probs[:, b].sum())
        var = float(np.sum(probs[:, b] * (1 - probs[:, b])))
        z = (o - ex) / np.sqrt(max(var, 0.25))  # floor: at least a quarter of a count
        by_part.append({"x_from_m": a, "x_to_m": e, "zone": zone, "observed": o,
                        "expected": ex, "z": float(z),
                        "p_value": float(2 * stats.norm.sf(abs(z)))})
    return by_part


def _bonferroni_findings(by_size: list[dict], trend: dict, by_part: list[dict],
                         n_tests: int) -> list[str]:
    """Add ``p_adj = min(1, p n_tests)`` (Bonferroni) and ``flag`` (p_adj < P_FLAG)
    to every test; the plain-text findings of the flagged ones, most significant
    first."""
    findings = []
    for s in by_size:
        s["p_adj"] = min(1.0, s["p_value"] * n_tests)
        s["flag"] = s["p_adj"] < P_FLAG
        if s["flag"]:
            way = "further" if s["z"] > 0 else "shorter"
            findings.append((s["p_adj"], f"blocks of {s['size_m']:.2f} m travel {way} than "
                             f"the model predicts (mean quantile residual {s['mean_q']:+.2f}, "
                             f"z = {s['z']:+.1f}, n = {s['n']}, p_adj = {s['p_adj']:.2g})"))
    if trend["p_value"] is not None:
        trend["p_adj"] = min(1.0, trend["p_value"] * n_tests)
        trend["flag"] = trend["p_adj"] < P_FLAG
        if trend["flag"]:
            way = "larger blocks travel further" if trend["spearman_rho"] > 0 else \
                "larger blocks travel shorter"
            findings.append((trend["p_adj"], f"residuals trend with block size: {way} "
                             f"than the model predicts (Spearman rho = "
                             f"{trend['spearman_rho']:+.2f}, p_adj = {trend['p_adj']:.2g})"))
    for s in by_part:
        s["p_adj"] = min(1.0, s["p_value"] * n_tests)
        s["flag"] = s["p_adj"] < P_FLAG
        if s["flag"]:
            way = "more" if s["z"] > 0 else "fewer"
            findings.append((s["p_adj"], f"{way} stops than predicted at x = "
                             f"{s['x_from_m']:.0f}-{s['x_to_m']:.0f} m ({s['zone']}): "
                             f"observed {s['observed']}, expected {s['expected']:.1f} "
                             f"(z = {s['z']:+.1f}, p_adj = {s['p_adj']:.2g})"))
    findings.sort(key=lambda t: t[0])
    return [t for _, t in findings]
