"""PNG figures of a hazard run (matplotlib, Agg backend; no physics here).

* ``exceedance.png``: the slope profile with its zones and the road (top) and
  the runout exceedance curves P(x_stop > x), posterior mean with the 5-95 %
  band, per block size (bottom, log scale).
* ``envelopes.png``: energy p50/p95/p99 of the blocks passing x with the 30 and
  300 kJ class limits (top), and bounce-height p95 (bottom), per block size.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from solvers.profile import Profile

__all__ = ["plot_envelopes", "plot_exceedance"]

_ZONE_COLORS = ("#8c564b", "#bcbd22", "#17becf", "#7f7f7f", "#9467bd")


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _profile_axis(ax, profile: Profile, road_x_m: float, label: str) -> None:
    x, z = np.asarray(profile.x_m), np.asarray(profile.z_m)
    names = profile.segment_zone_names()
    seen = set()
    for i, name in enumerate(names):
        color = _ZONE_COLORS[profile.zone_names.index(name) % len(_ZONE_COLORS)]
        ax.plot(x[i:i + 2], z[i:i + 2], color=color, lw=2.5,
                label=name if name not in seen else None)
        seen.add(name)
    ax.fill_between(x, z, z.min() - 5.0, color="0.9")
    ax.axvline(road_x_m, color="k", ls="--", lw=1)
    ax.annotate(label, (road_x_m, float(np.interp(road_x_m, x, z))), xytext=(4, 12),
                textcoords="offset points", fontsize=8)
    ax.set_ylabel("z (m)")
    ax.legend(fontsize=7, title="zone", title_fontsize=7, loc="upper right")


def plot_exceedance(exc: pd.DataFrame, profile: Profile, road_x_m: float, path: str,
                    title: str = "", label: str = "road") -> None:
    """Exceedance curves with their posterior bands over the profile; the station
    of interest at ``road_x_m`` is marked and named ``label``."""
    plt = _pyplot()
    fig, (ax0, ax1) = plt.subplots(2, 1, figsize=(8, 6.5), sharex=True,
                                   gridspec_kw={"height_ratios": [1, 1.4]})
    _profile_axis(ax0, profile, road_x_m, label)
    ax0.set_title(title, fontsize=9)
    floor = 1e-6
    for i, (size, g) in enumerate(exc.groupby("block_size_m", sort=True)):
        color = f"C{i}"
        # zero (no simulated block beyond x) is not drawn on the log axis
        ax1.plot(g.x_m, np.where(g.p_exceed_mean > 0, g.p_exceed_mean, np.nan), color=color,
                 label=_name(size, g))
        ax1.fill_between(g.x_m, np.maximum(g.p_exceed_q05, floor),
                         np.maximum(g.p_exceed_q95, floor), color=color, alpha=0.25, lw=0)
    ax1.axvline(road_x_m, color="k", ls="--", lw=1)
    ax1.set_yscale("log")
    ax1.set_ylim(floor, 1.5)
    ax1.set_xlabel("x (m)")
    ax1.set_ylabel("P(runout beyond x)\n(band floored at 1e-6)")
    ax1.legend(fontsize=7, title="mean, 5-95 % band", title_fontsize=7)
    ax1.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _name(size: float, rows: pd.DataFrame) -> str:
    """A curve's legend: its size, or its volume class (``volume_class`` column)."""
    if "volume_class" in rows:
        return f"{rows.volume_class.iloc[0]} (D = {size:.3g} m)"
    return f"D = {size:g} m"


def plot_envelopes(table: pd.DataFrame, profile: Profile, road_x_m: float, path: str,
                   title: str = "") -> None:
    """Energy and bounce-height envelopes along the profile."""
    plt = _pyplot()
    fig, (ax0, ax1) = plt.subplots(2, 1, figsize=(8, 6.5), sharex=True)
    for i, (size, g) in enumerate(table.groupby("block_size_m", sort=True)):
        color = f"C{i}"
        ax0.plot(g.x_m, g.energy_p95_kJ, color=color, label=f"{_name(size, g)}: p95")
        ax0.fill_between(g.x_m, g.energy_p50_kJ, g.energy_p99_kJ, color=color, alpha=0.2,
                         lw=0)
        ax1.plot(g.x_m, g.bounce_height_p95_m, color=color, label=_name(size, g))
    for e in (30.0, 300.0):
        ax0.axhline(e, color="0.4", ls=":", lw=1)
        ax0.annotate(f"{e:g} kJ", (float(profile.x_m[0]), e), fontsize=7, va="bottom")
    for ax in (ax0, ax1):
        ax.axvline(road_x_m, color="k", ls="--", lw=1)
        ax.grid(alpha=0.3, which="both")
    ax0.set_yscale("log")
    ax0.set_ylabel("kinetic energy (kJ)\nline p95, band p50-p99")
    ax0.legend(fontsize=7)
    ax0.set_title(title, fontsize=9)
    ax1.set_ylabel("bounce height p95 (m)")
    ax1.set_xlabel("x (m)")
    ax1.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)

