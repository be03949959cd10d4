"""2D slope profile: a height-field polyline with a material zone per segment.

A profile is a list of vertices ``(x_m, z_m)`` with strictly increasing ``x_m``
(a height field: overhangs cannot be represented and are rejected) and, for each
segment between consecutive vertices, the name of its material zone. Each zone
carries the material constants both solvers read:

* ``Kn``, ``Kt``: CRSP normal and tangential restitution (velocity) coefficients,
  in (0, 1] (Pfeiffer & Bowen 1989; Jones et al. 2000, CRSP 4.0 manual).
* ``roughness_m``: CRSP slope roughness S (m), the largest deviation perpendicular
  to the mean slope within a slope distance equal to the rock radius.
* ``rolling_friction_deg``: Coulomb resistance angle phi_r of the rolling phase
  of the lumped-mass model; ``mu = tan(phi_r)`` is the rolling-resistance
  coefficient (``solvers.crsp._contact``). A site parameter, to calibrate or to
  take from published values: tan(phi_r) = 0.30 for carbonate rock, lava and
  intrusive rock, 0.35-0.40 for clastic deposits, marl, flysch and schists,
  0.65 for anthropic, landslide and glacial deposits, 0.80 for alluvial and
  colluvial deposits (STONE, Guzzetti et al. 2002, Computers & Geosciences
  28, 1079-1093, its table as given in the r.stone documentation); PlatRock's
  default rolling coefficient is 0.2; RocFall's lumped-mass method offers
  phi = arctan((1 - Rt) / Rt), 8.5 deg at Rt = 0.87. That is, about 8-40 deg.
* ``phi_deg``: Mohr-Coulomb friction angle of DEM block-wall contacts.

File formats (CSV, header row required):

* profile: ``x_m,z_m,zone``. The ``zone`` on row i names the segment from vertex
  i to vertex i+1; the last row's zone is ignored and may be empty. Other
  columns are ignored; a profile cut from a raster (below) carries
  ``east_m,north_m``, each vertex's plan position in the raster's coordinates.
* materials: ``zone,Kn,Kt,roughness_m,rolling_friction_deg,phi_deg``.

Loading validates everything before any array reaches jitted code, and every
error names the file, the line and the column (``ProfileError``).

A profile can be cut from a digital elevation model along a line in plan:
``python -m terrain.cut RASTER --line LINE --out P.csv`` (package ``terrain``).
``python -m solvers.profile cut ...`` still runs that command, after a warning
line, for one release.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import os
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from solvers.csv_rows import cell_float

__all__ = [
    "MATERIAL_COLUMNS",
    "Profile",
    "ProfileError",
    "default_materials_path",
    "ground_z",
    "load_materials",
    "load_profile",
    "make_profile",
    "refine",
    "segment_angles_rad",
    "segment_index",
]

MATERIAL_COLUMNS = ("Kn", "Kt", "roughness_m", "rolling_friction_deg", "phi_deg")
_PROFILE_COLUMNS = ("x_m", "z_m", "zone")


class ProfileError(ValueError):
    """A profile or material file, or array, that cannot be used. The message names
    the file, the line and the column where that is known."""


@dataclasses.dataclass(frozen=True)
class Profile:
    """A validated slope profile (a JAX pytree; ``zone_names`` is static).

    Attributes:
        x_m: (V,) vertex abscissae, strictly increasing, m.
        z_m: (V,) vertex elevations, m.
        zone_id: (V-1,) int32 index into the zone table, one per segment.
        Kn, Kt: (Z,) CRSP restitution coefficients per zone, in (0, 1].
        roughness_m: (Z,) CRSP roughness S per zone, m, >= 0.
        rolling_friction_deg: (Z,) rolling-resistance angle per zone, degrees.
        phi_deg: (Z,) DEM contact friction angle per zone, degrees.
        zone_names: tuple of Z zone names (static metadata).
    """

    x_m: jax.Array
    z_m: jax.Array
    zone_id: jax.Array
    Kn: jax.Array
    Kt: jax.Array
    roughness_m: jax.Array
    rolling_friction_deg: jax.Array
    phi_deg: jax.Array
    zone_names: tuple[str, ...] = ()

    @property
    def n_segments(self) -> int:
        return int(self.x_m.shape[0]) - 1

    @property
    def x_range_m(self) -> tuple[float, float]:
        return float(self.x_m[0]), float(self.x_m[-1])

    def segment_zone_names(self) -> list[str]:
        return [self.zone_names[int(i)] for i in np.asarray(self.zone_id)]

    def with_materials(self, **values: float | Sequence[float]) -> Profile:
        """Return a copy with material columns replaced (scalar: every zone).

        Example: ``profile.with_materials(Kn=0.41, Kt=0.87, roughness_m=2.0)``.
        Values are validated like file values.
        """
        new = {}
        n_zones = len(self.zone_names)
        for name, value in values.items():
            if name not in MATERIAL_COLUMNS:
                raise ProfileError(f"unknown material column {name!r}; expected one of "
                                   f"{', '.join(MATERIAL_COLUMNS)}")
            arr = np.broadcast_to(np.asarray(value, dtype=np.float64), (n_zones,))
            for zi, v in enumerate(arr):
                _check_material_value(name, float(v), f"override for zone "
                                      f"{self.zone_names[zi]!r}")
            new[name] = jnp.asarray(arr)
        return dataclasses.replace(self, **new)


jax.tree_util.register_dataclass(
    Profile,
    data_fields=["x_m", "z_m", "zone_id", "Kn", "Kt", "roughness_m",
                 "rolling_friction_deg", "phi_deg"],
    meta_fields=["zone_names"],
)


def _check_material_value(column: str, value: float, where: str) -> None:
    if not math.isfinite(value):
        raise ProfileError(f"{where}: column '{column}': expected a finite number, got {value}")
    if column in ("Kn", "Kt") and not (0.0 < value <= 1.0):
        raise ProfileError(f"{where}: column '{column}': restitution must lie in (0, 1], "
                           f"got {value}")
    if column == "roughness_m" and value < 0.0:
        raise ProfileError(f"{where}: column '{column}': roughness must be >= 0 m, got {value}")
    if column in ("rolling_friction_deg", "phi_deg") and not (0.0 <= value < 90.0):
        raise ProfileError(f"{where}: column '{column}': angle must lie in [0, 90) degrees, "
                           f"got {value}")


def make_profile(
    x_m: Sequence[float],
    z_m: Sequence[float],
    segment_zones: Sequence[str],
    materials: dict[str, dict[str, float]],
    *,
    source: str = "<arrays>",
) -> Profile:
    """Build and validate a profile from arrays.

    Args:
        x_m: (V,) vertex abscissae, strictly increasing, m.
        z_m: (V,) vertex elevations, m.
        segment_zones: V-1 zone names, one per segment.
        materials: zone name -> {column: value} for every column of
            ``MATERIAL_COLUMNS``.
        source: name used in error messages.

    Returns:
        A ``Profile``.

    Raises:
        ProfileError: on fewer than 2 vertices, non-finite or non-increasing x,
            non-finite z, unknown zone, or out-of-range material values.
    """
    x = np.asarray(x_m, dtype=np.float64)
    z = np.asarray(z_m, dtype=np.float64)
    if x.ndim != 1 or z.shape != x.shape:
        raise ProfileError(f"{source}: x_m and z_m must be 1-D arrays of equal length")
    if x.shape[0] < 2:
        raise ProfileError(f"{source}: a profile needs at least 2 vertices, got {x.shape[0]}")
    for name, arr in (("x_m", x), ("z_m", z)):
        bad = np.flatnonzero(~np.isfinite(arr))
        if bad.size:
            raise ProfileError(f"{source}: vertex {bad[0]}: column '{name}': expected a finite "
                               f"number, got {arr[bad[0]]}")
    dx = np.diff(x)
    bad = np.flatnonzero(dx <= 0.0)
    if bad.size:
        i = int(bad[0])
        raise ProfileError(
            f"{source}: vertex {i + 1}: column 'x_m': x must increase strictly along the "
            f"profile (got {x[i + 1]} after {x[i]}); vertical steps and overhangs cannot be "
            "represented by a height-field profile and are out of scope")
    if len(segment_zones) != x.shape[0] - 1:
        raise ProfileError(f"{source}: expected {x.shape[0] - 1} segment zones, "
                           f"got {len(segment_zones)}")
    names = tuple(materials)
    for seg, zone in enumerate(segment_zones):
        if zone not in materials:
            raise ProfileError(f"{source}: segment {seg}: column 'zone': unknown zone {zone!r}; "
                               f"known zones: {', '.join(names) or '(none)'}")
    cols = {}
    for col in MATERIAL_COLUMNS:
        vals = []
        for zone in names:
            if col not in materials[zone]:
                raise ProfileError(f"{source}: zone {zone!r}: missing material column '{col}'")
            v = float(materials[zone][col])
            _check_material_value(col, v, f"{source}: zone {zone!r}")
            vals.append(v)
        cols[col] = jnp.asarray(np.array(vals, dtype=np.float64))
    zone_id = np.array([names.index(zn) for zn in segment_zones], dtype=np.int32)
    return Profile(x_m=jnp.asarray(x), z_m=jnp.asarray(z), zone_id=jnp.asarray(zone_id),
                   zone_names=names, **cols)


def _read_csv(path: str, required: Sequence[str]) -> list[tuple[int, dict[str, str]]]:
    if not os.path.isfile(path):
        raise ProfileError(f"{path}: file not found")
    with open(path, newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        header = reader.fieldnames
        if not header:
            raise ProfileError(f"{path}: line 1: empty file; expected a header with columns "
                               f"{', '.join(required)}")
        header = [h.strip() for h in header]
        missing = [c for c in required if c not in header]
        if missing:
            raise ProfileError(f"{path}: line 1: missing column(s) {', '.join(missing)}; "
                               f"expected {', '.join(required)}, found {', '.join(header)}")
        rows = []
        for raw in reader:
            row = {k.strip(): (v or "").strip() for k, v in raw.items() if k is not None}
            if not any(row.values()):
                continue
            rows.append((reader.line_num, row))
    return rows


def _float(path: str, line: int, row: dict[str, str], col: str) -> float:
    return cell_float(path, line, row, col, ProfileError)


def default_materials_path(profile_path: str) -> str:
    """``data/site_profile.csv`` -> ``data/site_materials.csv``."""
    head, tail = os.path.split(profile_path)
    stem = tail[:-4] if tail.endswith(".csv") else tail
    if stem.endswith("_profile"):
        stem = stem[: -len("_profile")]
    return os.path.join(head, f"{stem}_materials.csv")


def load_materials(path: str) -> dict[str, dict[str, float]]:
    """Load and validate a materials CSV ``zone,Kn,Kt,roughness_m,rolling_friction_deg,phi_deg``.

    Args:
        path: the materials CSV (other columns are ignored).

    Returns:
        zone name -> {column: value} for every column of ``MATERIAL_COLUMNS``,
        in file order.

    Raises:
        ProfileError: naming file, line and column of the first problem.
    """
    rows = _read_csv(path, ("zone",) + MATERIAL_COLUMNS)
    materials: dict[str, dict[str, float]] = {}
    for line, row in rows:
        name = row["zone"]
        if not name:
            raise ProfileError(f"{path}: line {line}: column 'zone': empty zone name")
        if name in materials:
            raise ProfileError(f"{path}: line {line}: column 'zone': duplicate zone {name!r}")
        vals = {}
        for col in MATERIAL_COLUMNS:
            vals[col] = _float(path, line, row, col)
            _check_material_value(col, vals[col], f"{path}: line {line}")
        materials[name] = vals
    return materials


def load_profile(path: str, materials_path: str | None = None) -> Profile:
    """Load and validate a profile CSV and its materials CSV.

    Args:
        path: profile CSV with columns ``x_m,z_m,zone``; other columns (such as
            the ``east_m,north_m`` plan position that ``cut`` writes) are ignored.
        materials_path: materials CSV; by default ``<site>_materials.csv`` next to
            ``<site>_profile.csv``.

    Returns:
        A validated ``Profile``.

    Raises:
        ProfileError: naming file, line and column of the first problem.
    """
    materials_path = materials_path or default_materials_path(path)
    rows = _read_csv(path, _PROFILE_COLUMNS)
    if len(rows) < 2:
        raise ProfileError(f"{path}: a profile needs at least 2 vertices, got {len(rows)}")
    x, z, zones = [], [], []
    for i, (line, row) in enumerate(rows):
        x.append(_float(path, line, row, "x_m"))
        z.append(_float(path, line, row, "z_m"))
        if i > 0 and x[-1] <= x[-2]:
            raise ProfileError(
                f"{path}: line {line}: column 'x_m': x must increase strictly along the profile "
                f"(got {x[-1]} after {x[-2]}); vertical steps and overhangs cannot be "
                "represented by a height-field profile and are out of scope")
        if i < len(rows) - 1:
            if not row["zone"]:
                raise ProfileError(f"{path}: line {line}: column 'zone': empty; every segment "
                                   "but the last vertex needs a zone name")
            zones.append((line, row["zone"]))

    materials = load_materials(materials_path)
    for line, zone in zones:
        if zone not in materials:
            raise ProfileError(f"{path}: line {line}: column 'zone': unknown zone {zone!r}; "
                               f"{materials_path} defines {', '.join(materials) or '(none)'}")
    return make_profile(x, z, [zn for _, zn in zones], materials, source=path)


def refine(profile: Profile, step_m: float, z_noise_m: float = 0.0,
           seed: int = 0) -> Profile:
    """The same slope with extra vertices every ``step_m`` (collinear with the
    segment they split), each keeping its segment's zone.

    A surveyed profile is the same ground sampled more finely: the solvers'
    results must not depend on it, which the tests check with this.
    ``z_noise_m`` adds Gaussian noise of that standard deviation to the new
    and old inner vertices (seeded), to mimic survey noise; the end vertices
    stay put.

    Args:
        profile: the slope.
        step_m: spacing of the inserted vertices, m (> 0).
        z_noise_m: standard deviation of the vertical noise, m (>= 0).
        seed: NumPy seed of the noise.

    Returns:
        A new ``Profile`` with the same materials.
    """
    if not (math.isfinite(step_m) and step_m > 0):
        raise ProfileError(f"refine: step must be a positive number of metres, got {step_m}")
    x = np.asarray(profile.x_m)
    z = np.asarray(profile.z_m)
    xs = np.unique(np.concatenate([x, np.arange(x[0], x[-1], step_m)]))
    zs = np.interp(xs, x, z)
    if z_noise_m > 0:
        noise = np.random.default_rng(seed).normal(0.0, z_noise_m, xs.shape)
        noise[0] = noise[-1] = 0.0
        zs = zs + noise
    zone = profile.segment_zone_names()
    seg = np.clip(np.searchsorted(x, xs[:-1], side="right") - 1, 0, len(zone) - 1)
    mats = {zn: {c: float(getattr(profile, c)[i]) for c in MATERIAL_COLUMNS}
            for i, zn in enumerate(profile.zone_names)}
    return make_profile(xs, zs, [zone[i] for i in seg], mats, source="refine")


def segment_index(profile: Profile, x_m: jax.Array) -> jax.Array:
    """Index of the segment under abscissa ``x_m`` (clipped to the profile ends).

    Args:
        profile: the slope.
        x_m: any shape, m.

    Returns:
        int32 array of the shape of ``x_m`` in [0, V-2].
    """
    idx = jnp.searchsorted(profile.x_m, x_m, side="right") - 1
    return jnp.clip(idx, 0, profile.x_m.shape[0] - 2).astype(jnp.int32)


def segment_angles_rad(profile: Profile) -> jax.Array:
    """(V-1,) angle of each segment above the horizontal, rad (positive where
    the ground rises towards +x, the direction blocks travel; jit-able)."""
    return jnp.arctan2(jnp.diff(profile.z_m), jnp.diff(profile.x_m))


def ground_z(profile: Profile, x_m: jax.Array) -> jax.Array:
    """Ground elevation z(x) by linear interpolation (extrapolated past the ends).

    Args:
        profile: the slope.
        x_m: any shape, m.

    Returns:
        Elevation in m, shape of ``x_m``.
    """
    i = segment_index(profile, x_m)
    xa, xb = profile.x_m[i], profile.x_m[i + 1]
    za, zb = profile.z_m[i], profile.z_m[i + 1]
    return za + (zb - za) * (x_m - xa) / (xb - xa)


# ``python -m solvers.profile cut ...``: the deprecated name of ``python -m
# terrain.cut`` (kept one release). The one import of ``terrain`` from
# ``solvers``, and only here, at run time: the alias goes with the next release.
_ALIAS_PROG = "python -m solvers.profile"


def main(argv: list[str] | None = None) -> int:
    """``python -m solvers.profile cut ARGS``: one warning line on stderr, then
    ``python -m terrain.cut ARGS``; anything else: one line, exit status 2."""
    import sys

    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] != "cut":
        sys.stderr.write(f"{_ALIAS_PROG}: error: the profile cut is now python -m terrain.cut "
                         "RASTER --line LINE --out P.csv (see its --help)\n")
        raise SystemExit(2)
    sys.stderr.write(f"{_ALIAS_PROG}: warning: '{_ALIAS_PROG} cut' is deprecated and goes in "
                     "the next release; use 'python -m terrain.cut' (same arguments)\n")
    from terrain.cut import main as cut

    return cut(argv[1:])


if __name__ == "__main__":
    import sys

    sys.exit(main())
