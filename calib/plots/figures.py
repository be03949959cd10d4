"""Figures of a calibration (matplotlib, Agg backend; each returns a Figure).

* ``runout_vs_size``: observed runouts (points with +-1 sd, or intervals)
  against block size, with each model's simulated median and 5-95 % band at
  the point estimate (over the finished blocks).
* ``alpha_law``: the fitted damping law alpha(L) with its 90 % posterior band,
  with the site's published values where its site file gives them
  (``calib.files.site``; Postignano: the paper's Table 1).
* ``validation_figures``: the predictive check's PIT histogram and intervals.
* ``pairs``: posterior pair plot (scatter below the diagonal, histograms on it).
* ``fit_figures``: the figures ``python -m calib.fit`` writes.
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from calib.files.observations import Observations  # noqa: E402
from calib.model.unfinished import nan_quantile  # noqa: E402

__all__ = ["alpha_law", "fit_figures", "pairs", "runout_vs_size", "validation_figures"]

_COLORS = {"crsp": "tab:blue", "dem": "tab:red"}


def runout_vs_size(obs: Observations, predictive: dict) -> plt.Figure:
    """predictive: model -> (sizes_m (S,), runouts (S, n)) at the point estimate."""
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for model, (sizes, runs) in predictive.items():
        q05, q50, q95 = nan_quantile(runs, [0.05, 0.5, 0.95], axis=1)  # finished blocks
        c = _COLORS.get(model, "k")
        ax.fill_between(sizes, q05, q95, color=c, alpha=0.2, label=f"{model.upper()} 5-95 %")
        ax.plot(sizes, q50, "o-", color=c, label=f"{model.upper()} median")
    pts = ~obs.is_interval
    ax.errorbar(obs.block_size_m[pts], obs.runout_m[pts], yerr=obs.runout_sd_m[pts], fmt="ks",
                capsize=4, label="observed (±1 sd)")
    if obs.is_interval.any():
        iv = obs.is_interval
        ax.vlines(obs.block_size_m[iv], obs.runout_min_m[iv], obs.runout_max_m[iv], colors="k",
                  lw=3, label="observed interval")
    ax.set_xlabel("block size (average diameter), m")
    ax.set_ylabel("runout (horizontal travel), m")
    ax.set_title("Observed vs simulated runout at the calibrated parameters")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def alpha_law(sizes_m: np.ndarray, alpha_map: np.ndarray, alpha_samples: np.ndarray | None,
              form: str, reference=(), reference_label: str = "reference") -> plt.Figure:
    """alpha_samples: (n_draws, len(sizes_m)) or None; reference: ((L, alpha), ...)
    published values of the site (``calib.files.site``), drawn only where given."""
    fig, ax = plt.subplots(figsize=(5.5, 4.0))
    if alpha_samples is not None:
        lo, hi = np.quantile(alpha_samples, [0.05, 0.95], axis=0)
        ax.fill_between(sizes_m, lo, hi, color="tab:red", alpha=0.2, label="90 % posterior")
    ax.plot(sizes_m, alpha_map, "-", color="tab:red", label=f"fitted ({form} law)")
    if len(reference):
        ref = np.asarray(reference, float)
        ax.plot(ref[:, 0], ref[:, 1], "ks", label=reference_label)
    ax.set_xlabel("square side L, m")
    ax.set_ylabel("local damping alpha")
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def fitted_alpha_law(form: str, fit, site, sizes_m) -> plt.Figure:
    """``alpha_law`` of a DEM fit (``calib.inference.calibrate.ModelFit``) over the
    fitted sizes and the site's reference sides (or the default sides of
    ``calib.files.fit_record.ALPHA_AT_L``), 25 % beyond both ends."""
    from calib.files.fit_record import ALPHA_AT_L
    from calib.model.alpha_law import alpha_of

    ls = np.asarray(sorted(dict(site.alpha_reference)) or ALPHA_AT_L, float)
    sizes = np.asarray(sizes_m, float)
    grid = np.geomspace(0.75 * min(ls.min(), sizes.min()), 1.25 * max(ls.max(), sizes.max()), 60)
    post = fit.posterior
    return alpha_law(grid, np.asarray(alpha_of(form, fit.estimate, grid)),
                     None if post is None else np.asarray(alpha_of(form, post.samples, grid)),
                     form, reference=site.alpha_reference,
                     reference_label=site.alpha_reference_label)


def pairs(samples: np.ndarray, names: tuple[str, ...], truth=None, title: str = ""
          ) -> plt.Figure:
    """Pair plot of posterior draws (n, d)."""
    d = samples.shape[1]
    fig, axes = plt.subplots(d, d, figsize=(2.3 * d + 0.5, 2.3 * d + 0.5), squeeze=False)
    for i in range(d):
        for j in range(d):
            ax = axes[i, j]
            if j > i:
                ax.axis("off")
                continue
            if i == j:
                ax.hist(samples[:, i], bins=30, color="tab:gray")
                if truth is not None:
                    ax.axvline(truth[i], color="k", ls="--")
            else:
                ax.plot(samples[:, j], samples[:, i], ".", ms=1.5, alpha=0.3, color="tab:blue")
                if truth is not None:
                    ax.plot(truth[j], truth[i], "k+", ms=10)
            if i == d - 1:
                ax.set_xlabel(names[j])
            if j == 0 and i > 0:
                ax.set_ylabel(names[i])
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


def fit_figures(fits: dict, inputs) -> dict:
    """The figures of one ``calib.fit`` run, file name -> Figure: each model's
    posterior ``pairs`` (``<model>_pairs.png``), the DEM's ``fitted_alpha_law``
    (``alpha_law.png``) and ``runout_vs_size`` of every model's check.

    Args:
        fits: model -> (``ModelFit``, forward model, alpha-law form or None).
        inputs: the data set fitted (``calib.files.inputs.Inputs``: rows and site).
    """
    figs = {}
    for model, (fit, _, form) in fits.items():
        post = fit.posterior
        if post is not None:
            figs[f"{model}_pairs.png"] = pairs(
                post.samples, fit.names, title=f"{model.upper()} posterior "
                f"({post.samples.shape[0]} draws{'' if post.ok else ', DIAGNOSTICS FAILED'})")
        if form is not None:
            figs["alpha_law.png"] = fitted_alpha_law(form, fit, inputs.site,
                                                     inputs.obs.sizes_m)
    figs["runout_vs_size.png"] = runout_vs_size(
        inputs.obs, {m: (r.fit.check_sizes_m, r.fit.check_runouts) for m, r in fits.items()})
    return figs


def validation_figures(check) -> dict:
    """The predictive check's figures (``calib.inference.predictive_check.PredictiveCheck``):
    the PIT histogram and the held-out rows' observed values against their
    predicted 50 and 90 % intervals; name -> Figure."""
    rows = check.rows
    figs = {}
    fig, ax = plt.subplots(figsize=(5, 3.5))
    pit = rows["pit"].dropna().to_numpy() if "pit" in rows else np.array([])
    ax.hist(pit, bins=np.linspace(0, 1, 11), color="0.6", edgecolor="k")
    if pit.size:
        ax.axhline(pit.size / 10, color="C3", ls="--", label="uniform (calibrated)")
        ax.legend(loc="upper center")
    ax.set(xlabel="PIT = P(predicted <= observed)", ylabel="held-out rows",
           title=f"PIT histogram ({pit.size} rows)")
    fig.tight_layout()
    figs["pit_histogram.png"] = fig

    scored = (rows.dropna(subset=["pred_median_m"]) if "pred_median_m" in rows
              else rows.iloc[:0])
    if len(scored):
        scored = scored.sort_values("observed_m")
    fig, ax = plt.subplots(figsize=(7, 0.25 * max(len(scored), 8) + 1.0))
    if len(scored):
        yy = np.arange(len(scored))
        ax.hlines(yy, scored["pred_q05_m"], scored["pred_q95_m"], color="C0", lw=1.5,
                  label="predicted 90 %")
        ax.hlines(yy, scored["pred_q25_m"], scored["pred_q75_m"], color="C0", lw=4,
                  label="predicted 50 %")
        ax.plot(scored["observed_m"], yy, "k.", label="observed")
        ax.set_yticks(yy, [f"row {r} ({d:g} m)" for r, d in zip(scored["row"],
                                                                 scored["block_size_m"])],
                      fontsize=6)
        ax.legend(loc="lower right", fontsize=7)
    else:
        ax.text(0.5, 0.5, "no scored point rows", ha="center", transform=ax.transAxes)
    ax.set(xlabel="runout, m", title="held-out rows: observed against predicted intervals")
    fig.tight_layout()
    figs["intervals.png"] = fig
    return figs
