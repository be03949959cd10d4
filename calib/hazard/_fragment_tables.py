"""The fragment tables of a hazard run: the ``frag_*`` variables added to
``hazard.nc``, ``fragments.csv`` (``FRAGMENT_COLUMNS``) and the summary's lines
(``calib.hazard._fragments`` runs and counts the fragments)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from calib.hazard._fragments import VARIABLES, FragmentCounts

__all__ = ["FRAGMENT_COLUMNS", "add_variables", "fragment_outputs", "fragment_summary",
           "fragment_table"]

FRAGMENT_COLUMNS = {
    "fragmentation": "how the blocks broke (hazard.nc attribute fragmentation)",
    "block_size_m": "parent block size D, m",
    "fragment_size_m": "fragment size, m (frag_size_m)",
    "n_fragments_per_break": "fragments per broken block",
    "x_m": "station, m",
    "p_break_mean": "fraction of blocks that broke, mean over draws",
    "p_exceed_parent_mean": "fraction of blocks with a piece beyond x (a parent exceeds x "
                            "when any of its fragments does), mean over draws",
    "p_exceed_parent_q05": "its 5 % quantile over draws",
    "p_exceed_parent_q95": "its 95 % quantile over draws",
    "p_exceed_fragment": "fraction of the fragments that end beyond x, all draws pooled",
    "fragments_beyond_per_block_mean": "fragments beyond x per released block, mean over "
                                       "draws",
    "mass_fraction_beyond_mean": "fraction of the released mass that ends beyond x "
                                 "(whole blocks and fragments), mean over draws; over a "
                                 "volume class, each block's fraction of its own mass, "
                                 "averaged over the class's blocks (not weighted by volume)",
    "fragments_reach_per_block_mean": "fragments passing x per released block, mean over "
                                      "draws",
    "p_E_gt_30kJ_given_fragment_reach": "of the fragments passing x, the fraction with "
                                        "E > 30 kJ, pooled",
    "p_E_gt_300kJ_given_fragment_reach": "the same with E > 300 kJ",
    "p_fragment_unfinished": "fraction of the fragments that did not finish, pooled",
}


PER_PARENT = ("per parent block: n_exceed, n_reach, the energy / speed / clearance variables "
              "and the tables built from them count released blocks; a block exceeds "
              "(reaches) x when any of its pieces ends beyond (passes) x, and its values at x "
              "are the largest among its pieces that pass x (calib.hazard._fragments)")
_ENERGY = {"crsp": "kJ per fragment (mass rho^3 m)",
           "dem": "the 2D DEM's kJ per metre of width times the block's side D: kJ per "
                  "fragment taken as a prism D wide (a slice of the block's cube)"}


def add_variables(ds, counts: FragmentCounts) -> None:
    """Add the ``VARIABLES`` and the fragmentation attributes to a results Dataset
    (in place): ``fragmentation`` (how the blocks broke), ``fragmentation_what_if``
    (1 where not the calibration's break), ``fragmentation_per_parent``,
    ``fragment_energy_basis``."""
    import xarray as xr

    values = counts.variables()
    for name, (dims, units, meaning) in VARIABLES.items():
        ds[name] = xr.Variable(dims, np.asarray(values[name]),
                               attrs={"units": units, "long_name": meaning})
    spec = counts.spec
    ds.attrs.update(fragmentation=spec.description, fragmentation_what_if=int(spec.what_if),
                    fragmentation_per_parent=PER_PARENT,
                    fragment_energy_basis=_ENERGY[spec.model])


def fragment_table(ds) -> pd.DataFrame:
    """``fragments.csv``: one row per block size (or volume class) and station, ``FRAGMENT_COLUMNS``
    (from a results Dataset with ``add_variables``' variables)."""
    n = int(ds.attrs["n_blocks_per_draw"])
    x = ds["x_m"].values
    c = {k: ds[k].values.astype(np.float64) for k in VARIABLES if k.startswith("frag_n")}
    p_parent = ds["n_exceed"].values / n                      # (D, T, S)
    q = np.quantile(p_parent, [0.05, 0.95], axis=0)
    per = c["frag_n_per_break"][None, :, None]
    mass = (c["frag_n_exceed_whole"] + c["frag_n_exceed"] / per) / n
    with np.errstate(invalid="ignore", divide="ignore"):
        pooled_frag = c["frag_n_fragments"].sum(axis=0)[:, None]
        p_frag = c["frag_n_exceed"].sum(axis=0) / pooled_frag
        reach = c["frag_n_reach"].sum(axis=0)
        p30 = c["frag_n_reach_E_gt_30kJ"].sum(axis=0) / reach
        p300 = c["frag_n_reach_E_gt_300kJ"].sum(axis=0) / reach
        unfinished = c["frag_n_unfinished"].sum(axis=0) / c["frag_n_fragments"].sum(axis=0)
    rows = []
    for t, size in enumerate(ds["block_size_m"].values):
        for s, xs in enumerate(x):
            rows.append({
                "model": str(ds.attrs["model"]),
                "fragmentation": str(ds.attrs["fragmentation"]),
                "block_size_m": float(size),
                "fragment_size_m": float(ds["frag_size_m"].values[t]),
                "n_fragments_per_break": int(ds["frag_n_per_break"].values[t]),
                "x_m": float(xs),
                "p_break_mean": float(np.mean(c["frag_n_broken"][:, t]) / n),
                "p_exceed_parent_mean": float(p_parent[:, t, s].mean()),
                "p_exceed_parent_q05": float(q[0, t, s]),
                "p_exceed_parent_q95": float(q[1, t, s]),
                "p_exceed_fragment": float(p_frag[t, s]),
                "fragments_beyond_per_block_mean": float(c["frag_n_exceed"][:, t, s].mean()
                                                         / n),
                "mass_fraction_beyond_mean": float(mass[:, t, s].mean()),
                "fragments_reach_per_block_mean": float(c["frag_n_reach"][:, t, s].mean() / n),
                "p_E_gt_30kJ_given_fragment_reach": float(p30[t, s]),
                "p_E_gt_300kJ_given_fragment_reach": float(p300[t, s]),
                "p_fragment_unfinished": float(unfinished[t]),
            })
    return pd.DataFrame(rows, columns=["model"] + list(FRAGMENT_COLUMNS))


def fragment_summary(ds, table: pd.DataFrame, road_x_m: float, label: str = "road") -> str:
    """The summary's fragmentation lines: how the blocks broke, and at the station of
    interest per size: P(break), the parent exceedance, fragments and mass beyond."""
    lines = [f"fragmentation: {ds.attrs['fragmentation']}",
             "  the lines above, exceedance.csv and hazard_table.csv are per parent block: a "
             "block exceeds (reaches) x when any of its pieces ends beyond (passes) x "
             "(hazard.nc attribute fragmentation_per_parent)",
             f"  per fragment (fragments.csv, frag_* of hazard.nc), energies "
             f"{ds.attrs['fragment_energy_basis']}:"]
    at = table[np.isclose(table["x_m"], road_x_m)]
    classes = ds["class_label"].values if "class_label" in ds else None
    for t, r in enumerate(at.itertuples()):
        if classes is None:
            what = (f"D = {r.block_size_m:g} m ({r.n_fragments_per_break} fragments of "
                    f"{r.fragment_size_m:.3g} m)")
        else:  # each block of a class breaks into fragments of its own diameter
            ratio = r.fragment_size_m / r.block_size_m
            what = (f"class {classes[t]} (D = {r.block_size_m:.3g} m; "
                    f"{r.n_fragments_per_break} fragments of {ratio:.3g} x each block's "
                    "diameter)")
        line = (f"  {what}: P(break) = {r.p_break_mean:.3g}; P(a piece "
                f"beyond the {label} at x = {road_x_m:g} m) = {r.p_exceed_parent_mean:.3g} "
                f"[5-95 %: {r.p_exceed_parent_q05:.3g}-{r.p_exceed_parent_q95:.3g}]; "
                f"fragments beyond it per block {r.fragments_beyond_per_block_mean:.3g}")
        if np.isfinite(r.p_exceed_fragment):
            line += f" ({r.p_exceed_fragment:.3g} of the fragments)"
        line += (f"; share of the released mass beyond it {r.mass_fraction_beyond_mean:.3g}"
                 if classes is None else "; mean share of a block's mass beyond it "
                 f"{r.mass_fraction_beyond_mean:.3g}")
        if r.p_fragment_unfinished > 0:
            line += (f"; {r.p_fragment_unfinished:.2%} of the fragments unfinished, not "
                     "counted as runouts")
        lines.append(line)
    return "\n".join(lines)


def fragment_outputs(counts: FragmentCounts | None, results, writers: dict, text: str,
                     road_x_m: float, label: str = "road") -> str:
    """A fragment run's outputs (the command's one call): ``add_variables`` on
    ``results`` (written as ``hazard.nc``), ``fragments.csv`` added to ``writers``,
    the summary ``text`` with ``fragment_summary``'s lines. Without fragments
    (``counts`` None) nothing changes."""
    if counts is None:
        return text
    add_variables(results, counts)
    table = fragment_table(results)
    writers["fragments.csv"] = lambda p: table.to_csv(p, index=False)
    return text + "\n" + fragment_summary(results, table, road_x_m, label)
