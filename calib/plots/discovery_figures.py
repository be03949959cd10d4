"""Figures of the discrepancy workflow (matplotlib, Agg): where the baseline fails,
how the candidates score, and the gap before / after adding the named effect."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from calib.model.unfinished import nan_quantile  # noqa: E402

__all__ = ["before_after", "candidates", "discovery_figures", "residuals"]


def residuals(obs, where: dict, title: str):
    """Baseline quantile residuals against block size, and stops per slope part."""
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    q = np.asarray(where["quantile_residual"])
    a.scatter(obs.block_size_m, q, s=14, alpha=0.6, label="rows")
    for s in where["by_size"]:
        se = 1.0 / np.sqrt(s["n"])
        a.errorbar(s["size_m"], s["mean_q"], yerr=2 * se, fmt="o", color="C3" if s["flag"]
                   else "k", capsize=3)
    a.axhline(0, color="grey", lw=0.8)
    a.set_xlabel("block size d, m")
    a.set_ylabel("quantile residual (> 0: travelled further)")
    a.set_title("by size (class mean ± 2 se; red: flagged)")
    parts = where["by_slope_part"]
    mid = [0.5 * (p["x_from_m"] + p["x_to_m"]) for p in parts]
    width = [p["x_to_m"] - p["x_from_m"] for p in parts]
    b.bar(mid, [p["expected"] for p in parts], width=width, alpha=0.4, edgecolor="k",
          label="expected stops")
    b.scatter(mid, [p["observed"] for p in parts],
              c=["C3" if p["flag"] else "k" for p in parts], zorder=3, label="observed stops")
    b.set_xlabel("stop position x, m")
    b.set_ylabel("rows")
    b.set_title("by slope part (red: flagged)")
    b.legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


def candidates(table: list[dict], named: str, min_gain: float):
    """Held-out score gain over the baseline per candidate, ± 2 standard errors."""
    rows = [r for r in table if r["effect"] != "none"]
    fig, ax = plt.subplots(figsize=(7, 0.6 * len(rows) + 1.6))
    y = np.arange(len(rows))
    d = [r["delta_vs_none"] for r in rows]
    se = [0.0 if not np.isfinite(r["se_delta"]) else 2 * r["se_delta"] for r in rows]
    ax.barh(y, d, xerr=se, color=["C2" if r["effect"] == named else "C0" for r in rows],
            capsize=3)
    ax.axvline(0, color="k", lw=0.8)
    ax.axvline(min_gain, color="grey", ls="--", lw=0.8, label=f"minimum gain {min_gain:g}")
    ax.set_yticks(y, [r["effect"] for r in rows])
    ax.set_xlabel("held-out log score gain over the baseline (nats), ± 2 se")
    ax.set_title(f"named effect: {named}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def before_after(obs, class_sizes, row_class, before, after, named: str, gaps):
    """Observed runouts per size class with the 5-95 % predictive bands of the
    baseline and of the model with the named effect (finished blocks)."""
    fig, ax = plt.subplots(figsize=(8, 5.2))
    x = np.asarray(class_sizes)
    for samples, label, color, off in ((before, f"baseline (gap {gaps[0]:.1f} m)", "C0", -0.02),
                                       (after, f"with {named} (gap {gaps[1]:.1f} m)", "C2",
                                        0.02)):
        if samples is None:
            continue
        lo, med, hi = nan_quantile(samples, [0.05, 0.5, 0.95], axis=1)  # finished blocks
        ax.errorbar(x * (1 + off), med, yerr=[med - lo, hi - med], fmt="s", color=color,
                    capsize=4, label=label + ", median and 5-95 %")
    y = np.where(obs.is_interval, 0.5 * (obs.runout_min_m + obs.runout_max_m), obs.runout_m)
    ax.scatter(x[row_class], y, s=12, color="k", alpha=0.5, zorder=3, label="observed")
    ax.set_xscale("log")
    ax.set_xlabel("block size d, m")
    ax.set_ylabel("runout, m")
    # below the axes: inside, it can hide observations
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2)
    ax.set_title("gap before / after adding the named effect")
    fig.tight_layout()
    return fig


def discovery_figures(obs, d, model: str) -> dict:
    """The three figures of one discovery run ``d`` (``calib.discovery.discrepancy.
    Discovery``) on rows ``obs`` of ``model``: {"residuals.png": where the baseline
    disagrees, "candidates.png": the first step's scores, "before_after.png":
    the gap per size class before and after the named effects}."""
    from calib.discovery.scores import ELPD_MIN

    base, final = d.fits["none"], d.fits[d.final_model]
    return {
        "residuals.png": residuals(obs, d.where_before,
                                   f"where the baseline ({model}) disagrees: "
                                   f"{len(d.where_before['flagged'])} flagged"),
        "candidates.png": candidates(d.table, d.named_effect, ELPD_MIN),
        "before_after.png": before_after(
            obs, d.class_sizes_m, d.row_class, base.class_samples,
            None if not d.named_effects else final.class_samples, d.final_model,
            (d.gap_before, d.gap_after)),
    }
