"""Figures of the design sheet (matplotlib, Agg backend; no computation beyond
reading the results Dataset and the design record).

* ``profile_figure``: the profile with the release, the barrier (the kit's height)
  and the road; below, P(reach x) of the design size with its 5-95 % band.
* ``distributions_figure``: at the barrier, P(E > e) and P(h > y) of the passers
  of the design size (all draws pooled; E scaled to the design block, h the block's
  top), with the characteristic and design values and every kit's line.
* ``exceedance_figure``: P(runout > x) along the slope with its band per size, the
  barrier and the road marked, and the run with the barrier where given.
* ``scan_figure``: E_sd and the design height along a scan of positions with the kits.
"""

from __future__ import annotations

import numpy as np

from calib.design._values import station_index

__all__ = ["distributions_figure", "exceedance_figure", "profile_figure", "scan_figure"]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _ground(ds, x):
    return float(np.interp(x, ds["profile_x_m"].values, ds["profile_z_m"].values))


def profile_figure(ds, r: dict):
    """Profile, release, barrier, road; P(reach) of the design size below."""
    plt = _plt()
    fig, (ax0, ax1) = plt.subplots(2, 1, figsize=(8, 6.5), sharex=True,
                                   gridspec_kw={"height_ratios": [1.3, 1]})
    x, z = ds["profile_x_m"].values, ds["profile_z_m"].values
    ax0.plot(x, z, color="0.3", lw=2)
    ax0.fill_between(x, z, z.min() - 5.0, color="0.9")
    rel = float(ds.attrs["release_x_m"])
    ax0.plot([rel], [_ground(ds, rel)], "v", color="C3", ms=9, label="release")
    xb = r["barrier_x_m"]
    kit = r.get("kit_checked")
    height = kit["nominal_height_m"] if kit else r["design"]["design_height_m"]
    zb = _ground(ds, xb)
    ax0.plot([xb, xb], [zb, zb + height], color="C2", lw=4,
             label=f"barrier ({kit['kit'] if kit else 'no kit passes'}, {height:.3g} m)")
    road = r["run"].get("road_x_m")
    if road is not None:
        ax0.plot([road], [_ground(ds, road)], "s", color="k", ms=7,
                 label=r["run"].get("road_label") or "station of interest")
    ax0.set_ylabel("z (m)")
    ax0.legend(fontsize=7)
    ax0.set_title(f"barrier at x = {xb:g} m, design block D = "
                  f"{r['design_block']['size_m']:g} m", fontsize=9)
    reach = ds["n_reach"].sel(block_size_m=r["design_block"]["size_m"]).values
    p = reach / float(ds.attrs["n_blocks_per_draw"])
    xs = ds["x_m"].values
    down = xs > rel
    q05, q95 = np.quantile(p, [0.05, 0.95], axis=0)
    ax1.plot(xs[down], p.mean(axis=0)[down], color="C0", label="P(reach x), mean over draws")
    ax1.fill_between(xs[down], q05[down], q95[down], color="C0", alpha=0.25, lw=0,
                     label="5-95 % over draws")
    for ax in (ax0, ax1):
        ax.axvline(xb, color="C2", ls="--", lw=1)
        if road is not None:
            ax.axvline(road, color="k", ls=":", lw=1)
    ax1.set_ylim(0, 1.05)
    ax1.set_xlabel("x (m)")
    ax1.set_ylabel("P(reach x)")
    ax1.legend(fontsize=7)
    fig.tight_layout()
    return fig


def _survival(counts: np.ndarray, lower_edges: np.ndarray):
    """(v, P(value > v)) at the bins' edges, from just below the smallest value to
    the largest."""
    n = counts.sum()
    if n == 0:
        return np.zeros(0), np.zeros(0)
    cum = np.cumsum(counts)
    first = max(int(np.argmax(cum > 0)) - 1, 0)
    last = min(int(np.argmax(cum >= n)), len(counts) - 2)
    k = np.arange(first, last + 1)
    return lower_edges[k + 1], (n - cum[k]) / n


def distributions_figure(ds, r: dict):
    """Energy and passing-height exceedance at the barrier with design and kit lines."""
    plt = _plt()
    s = station_index(ds, r["barrier_x_m"])
    size = r["design_block"]["size_m"]
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(10, 4.2))
    e = ds["hist_energy_kJ"].sel(block_size_m=size).values[s]
    ex, ep = _survival(e, ds["energy_kJ_bin"].values)
    ax0.step(ex * r["design_block"]["energy_scale"], ep, where="post", color="C0",
             label="passers, all draws (no factors)")
    h = ds["hist_bounce_height_m"].sel(block_size_m=size).values[s]
    hx, hp = _survival(h, ds["bounce_height_m_bin"].values)
    ax1.step(hx + size, hp, where="post", color="C0", label="passers, all draws (no factors)")
    pct = r["percentile"]
    ax0.axvline(r["characteristic"]["E_p_kJ"], color="C0", ls=":", label=f"E p{pct:g} total")
    ax0.axvline(r["design"]["E_sd_kJ"], color="C3", lw=2, label="E_sd design (translational)")
    ax1.axvline(r["characteristic"]["h_p_m"], color="C0", ls=":", label=f"h p{pct:g}")
    ax1.axvline(r["design"]["h_d_m"], color="C3", lw=1.5, label="h_d")
    ax1.axvline(r["design"]["design_height_m"], color="C3", lw=2, ls="--",
                label="h_d + free board")
    chosen = (r.get("kit_checked") or {}).get("kit")
    for k in r["kits"]:
        bold = k["kit"] == chosen
        style = {"color": "C2" if bold else "0.6", "lw": 2 if bold else 0.8}
        if np.isfinite(k["energy_limit_kJ"]):
            ax0.axvline(k["energy_limit_kJ"], **style)
            ax0.annotate(k["kit"], (k["energy_limit_kJ"], 0.5), rotation=90, fontsize=6,
                         color=style["color"], va="center")
        ax1.axvline(k["nominal_height_m"], **style)
    ax0.set_xscale("log")
    ax0.set_yscale("log")
    ax0.set_xlabel(f"energy of the design block (kJ); kit lines: {r['energy_level']}/gamma_E")
    ax0.set_ylabel("P(value > abscissa | reach)")
    ax1.set_yscale("log")
    ax1.set_xlabel("passing height of the block's top (m); kit lines: nominal height")
    for ax in (ax0, ax1):
        ax.legend(fontsize=6)
        ax.grid(alpha=0.3, which="both")
    fig.suptitle(f"at the barrier, x = {r['barrier_x_m']:g} m, D = {size:g} m "
                 f"({r['n_passers']} passers)", fontsize=9)
    fig.tight_layout()
    return fig


def exceedance_figure(table, r: dict):
    """P(runout > x) per size (design size bold), with the barrier run where given."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 4.5))
    floor = 1e-6
    size = r["design_block"]["size_m"]
    for i, (d, g) in enumerate(table.groupby("block_size_m", sort=True)):
        bold = np.isclose(d, size)
        ax.plot(g.x_m, np.where(g.p_exceed_mean > 0, g.p_exceed_mean, np.nan), color=f"C{i}",
                lw=2 if bold else 0.8, label=f"D = {d:g} m" + (" (design)" if bold else ""))
        if bold:
            ax.fill_between(g.x_m, np.maximum(g.p_exceed_q05, floor),
                            np.maximum(g.p_exceed_q95, floor), color=f"C{i}", alpha=0.25, lw=0)
            w = g.p_exceed_mean_with_barrier
            if np.any(np.isfinite(w)):
                ax.plot(g.x_m, np.where(w > 0, w, np.nan), color=f"C{i}", ls="--", lw=2,
                        label=f"D = {d:g} m with the barrier")
    ax.axvline(r["barrier_x_m"], color="C2", ls="--", lw=1.5, label="barrier")
    road = r["run"].get("road_x_m")
    if road is not None:
        ax.axvline(road, color="k", ls=":", lw=1, label=r["run"].get("road_label") or "road")
    ax.set_yscale("log")
    ax.set_ylim(floor, 1.5)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("P(runout beyond x) (band: 5-95 % over draws)")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    return fig


def scan_figure(scan: list[dict], kits: list[dict], energy_level: str):
    """Design energy and height along the scanned positions, with the kits."""
    plt = _plt()
    fig, (ax0, ax1) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    x = np.array([s["x_m"] for s in scan])
    ax0.plot(x, [s["E_sd_kJ"] for s in scan], "o-", color="C3", label="E_sd")
    ax1.plot(x, [s["design_height_m"] for s in scan], "o-", color="C3",
             label="h_d + free board")
    for k in kits:
        if np.isfinite(k["energy_limit_kJ"]):
            ax0.axhline(k["energy_limit_kJ"], color="0.6", lw=0.8)
            ax0.annotate(k["kit"], (x.min(), k["energy_limit_kJ"]), fontsize=6, va="bottom")
        ax1.axhline(k["nominal_height_m"], color="0.6", lw=0.8)
    ax0.set_yscale("log")
    ax0.set_ylabel(f"energy (kJ); lines: {energy_level}/gamma_E")
    ax1.set_ylabel("height (m); lines: nominal heights")
    ax1.set_xlabel("barrier position x (m)")
    for ax in (ax0, ax1):
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    return fig
