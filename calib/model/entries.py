"""Simulated entries: what the solvers run, once per parameter point.

An ENTRY is one simulated release: a block size, a release abscissa on a
profile, a release speed and height, and the rock's density. A forward model
(``calib.model.forward``) simulates ``n_blocks`` blocks per entry and
parameter point; the calibration, the discrepancy workflow, the predictive
check and the hazard run all describe what they simulate as ``Entries``.
Observed rows map onto entries through ``Entries.index`` (row -> entry).

Block-size rule (one place, used by every solver run):

* the block size d is the average block diameter, m (the paper's wording,
  Sect. 4.1; ``block_size_m`` of every input and output);
* CRSP: a block of mass rho pi d^3 / 6 (the volume of the sphere of diameter
  d) in the entry's CRSP shape class (``solvers.crsp.make_block``): a sphere of
  radius r = d / 2, or the cylinder or disc of that volume, radius s d / 2 with
  s the shape's radius scale (``solvers.crsp.shape_constants``: cylinder 0.874,
  disc 1.387). ``Entries.from_rows(..., row_shapes=True)`` gives each entry
  its rows' ``shape`` (``calib.files.observations``; empty: sphere; the fit's
  ``--row-shapes``), else every observed row is a sphere: a field run's d is
  the volume-equivalent diameter of its mass (``calib.files.field_runs``), so
  the simulated block has the rock's mass whatever its shape (our choice: the
  shape changes the radius the block rolls on and its moment of inertia, not
  its mass);
* DEM: a square of side L = d, mass rho L^2 per metre of width. The paper's
  UDEC squares were meant to match the CRSP masses, but its Table 1 sides
  (0.2, 0.9, 1.8 m) do not follow from its radii (``data/README.md``); we take
  the side equal to the average diameter, which reproduces Table 1's L for
  d = 0.2 and 1.8 m within 10 % (our choice).

Release state: a NaN release speed or height keeps the solver's own default
(CRSP: 1 m/s on the ground; DEM: ``solvers.dem.Params``' release rule). A
tracked release height is kept as measured, negative values included (a
release that a raster puts below its ground, ``calib.files.field_runs``), with
the sds of its error and of the tracked speed's (``release_height_sd_m``,
``release_speed_sd_m_s``: the site's, ``calib.files.site``; 0: exact): each
block draws its height and speed from truncated normals about them, CRSP's
(``solvers.crsp.init``) and the DEM's (``solvers.dem.Block``) alike. The
density is one per site (``calib.files.site``), the solvers' default
``solvers.material.ROCK_DENSITY_KG_M3`` where the site says nothing.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from solvers.crsp import SHAPES, make_block, shape_constants
from solvers.material import ROCK_DENSITY_KG_M3, check_density

__all__ = ["Entries", "crsp_radius_m", "dem_side_m", "entry_shapes", "sphere_diameter_m"]


def sphere_diameter_m(mass_kg, density_kg_m3: float) -> np.ndarray:
    """Volume-equivalent sphere diameter d = (6 m / (pi rho))^(1/3), m: the block
    size of a block of mass m (a volume V with rho = 1), the rule every input of
    masses or volumes follows (field runs, block surveys, volume laws).

    Args:
        mass_kg: any shape, kg.
        density_kg_m3: rock density rho, kg/m^3.
    """
    return np.cbrt(6.0 * np.asarray(mass_kg, float) / (np.pi * density_kg_m3))


def crsp_radius_m(block_size_m, shapes=None):
    """CRSP radius for an average block diameter d: r = s d / 2, s the radius
    scale of each block's shape class (``solvers.crsp.shape_constants``; None,
    or a sphere: s = 1, r = d / 2), so that the block has the sphere's volume."""
    d = np.asarray(block_size_m, dtype=float)
    if shapes is None:
        return 0.5 * d
    scale = np.array([shape_constants(f)[0] for f in np.broadcast_to(
        np.asarray(shapes, dtype=object), d.shape).reshape(-1)]).reshape(d.shape)
    return np.where(np.asarray(shapes, dtype=object) == "sphere", 0.5 * d, 0.5 * d * scale)


def entry_shapes(shapes, n: int) -> np.ndarray:
    """(n,) CRSP shape classes from None (all spheres) or one per entry; an empty
    one (a row that gives none) is a sphere.

    Raises:
        ValueError: a count other than n, or a name not in ``solvers.crsp.SHAPES``.
    """
    if shapes is None:
        return np.full(n, "sphere", dtype=object)
    out = np.array(["sphere" if not str(f) else str(f) for f in np.ravel(
        np.asarray(shapes, dtype=object))], dtype=object)
    if out.shape != (n,):
        raise ValueError(f"{out.size} shapes for {n} entries (one per entry)")
    bad = [f for f in out if f not in SHAPES]
    if bad:
        raise ValueError(f"unknown block shape {bad[0]!r}; expected one of {', '.join(SHAPES)}")
    return out


def dem_side_m(block_size_m):
    """DEM square side for an average block diameter d: L = d (module docstring)."""
    return np.asarray(block_size_m, dtype=float)


def _column(values, n: int) -> np.ndarray:
    """(n,) floats from None (all NaN), one value for all, or one per entry."""
    if values is None:
        return np.full(n, np.nan)
    v = np.asarray(values, float)
    if v.ndim > 0 and v.shape != (n,):
        raise ValueError(f"{v.size} values for {n} entries (one per entry, or one for all)")
    return np.broadcast_to(v, (n,)).copy()


@dataclasses.dataclass(frozen=True, eq=False)
class Entries:
    """What a forward model simulates: E entries (NumPy arrays of length E).

    Attributes:
        sizes_m: (E,) block size d (average diameter), m.
        release_x_m: (E,) release abscissa on the entry's profile, m.
        release_speed_m_s: (E,) release speed, m/s (NaN: the solver's default).
        release_height_m: (E,) release height above the ground, m (NaN: the
            solver's default, on the ground).
        profiles: (E,) the entry's own ``Profile``, or None for the forward
            model's profile: runs released from spots far apart, each along
            its own fall line (``Observations.profile``).
        profile_csv: (E,) the file of each entry's own profile ("" for the
            forward model's), for records.
        index: (n_obs,) the entry of each observed row, or None where the
            entries were not made from rows.
        density_kg_m3: rock density rho of every block, kg/m^3.
        release_height_sd_m: (E,) sd of the release height's error, m (0:
            exact, and where the entry has no height).
        release_speed_sd_m_s: (E,) sd of the release speed's error, m/s (0:
            exact, and where the entry has no speed).
        shapes: (E,) CRSP shape class of each entry's blocks (None: spheres;
            module docstring). The DEM's blocks are squares whatever it says.
    """

    sizes_m: np.ndarray
    release_x_m: np.ndarray
    release_speed_m_s: np.ndarray
    release_height_m: np.ndarray
    profiles: tuple
    profile_csv: np.ndarray
    index: np.ndarray | None = None
    density_kg_m3: float = ROCK_DENSITY_KG_M3
    release_height_sd_m: np.ndarray | float = 0.0
    release_speed_sd_m_s: np.ndarray | float = 0.0
    shapes: np.ndarray | None = None

    def __post_init__(self):
        n = np.asarray(self.sizes_m).shape[0]
        object.__setattr__(self, "sizes_m", np.asarray(self.sizes_m, float).reshape(n))
        for name in ("release_x_m", "release_speed_m_s", "release_height_m"):
            try:
                object.__setattr__(self, name, _column(getattr(self, name), n))
            except ValueError as e:
                raise ValueError(f"{name}: {e}") from None
        profiles = (None,) * n if self.profiles is None else tuple(self.profiles)
        if len(profiles) != n:
            raise ValueError(f"profiles: {len(profiles)} for {n} entries (one per entry)")
        object.__setattr__(self, "profiles", profiles)
        csv = np.full(n, "", dtype=object) if self.profile_csv is None else np.asarray(
            self.profile_csv, dtype=object)
        object.__setattr__(self, "profile_csv", csv)
        object.__setattr__(self, "density_kg_m3", check_density(self.density_kg_m3))
        if np.any(~np.isfinite(self.release_x_m)):
            raise ValueError("release_x_m: every entry needs a finite release abscissa")
        for name in ("release_height_sd_m", "release_speed_sd_m_s"):
            sd = _column(getattr(self, name), n)
            if np.any(~(np.isfinite(sd) & (sd >= 0))):
                raise ValueError(f"{name}: expected finite sds >= 0, got {sd}")
            object.__setattr__(self, name, sd)
        try:
            object.__setattr__(self, "shapes", entry_shapes(self.shapes, n))
        except ValueError as e:
            raise ValueError(f"shapes: {e}") from None

    @classmethod
    def at_sizes(cls, sizes_m, release_x_m: float, *, density_kg_m3: float = ROCK_DENSITY_KG_M3,
                 release_speed_m_s=None, release_height_m=None, shapes=None) -> Entries:
        """One entry per size of ``sizes_m``, all released at ``release_x_m`` (m;
        or one per size) on the forward model's profile, in CRSP shape classes
        ``shapes`` (one per size; None: spheres)."""
        sizes = np.atleast_1d(np.asarray(sizes_m, float))
        return cls(sizes, release_x_m, release_speed_m_s, release_height_m, None, None,
                   density_kg_m3=density_kg_m3, shapes=shapes)

    @classmethod
    def one_per_size(cls, obs, release_x_m: float, *,
                     density_kg_m3: float = ROCK_DENSITY_KG_M3) -> Entries:
        """The entries of a fit that releases every block from one point (the DEM
        fit, a CRSP fit of rows without ``release_x_m``): one per distinct size
        of the rows (``obs.sizes_m``), released at ``release_x_m`` at the
        solver's default speed, on the ground, on the command's profile, as
        spheres, whatever the rows' own releases and shapes say."""
        e = cls.at_sizes(obs.sizes_m, release_x_m, density_kg_m3=density_kg_m3)
        return dataclasses.replace(e, index=np.asarray(obs.size_index))

    @classmethod
    def from_rows(cls, obs, default_release_x_m: float, tol_m: float = 0.0, *,
                  profile_of: Callable[[str], object] | None = None,
                  density_kg_m3: float = ROCK_DENSITY_KG_M3,
                  row_shapes: bool = False) -> Entries:
        """Group the rows by (profile, block size, shape class, release point).

        Rows of one profile and one size whose release abscissae AND release
        heights lie within ``tol_m`` of those of the first (lowest) release of
        their group share one entry, released at the mean of their releases
        (greedy: rows in ascending order of release, each joining the first
        group it fits, else opening one); ``tol_m = 0`` groups only equal
        releases. Rows without a height match only each other. A row without
        ``release_x_m`` (NaN) is released at ``default_release_x_m``. An
        entry's release speed and height are the means of its rows'
        ``release_speed_m_s`` and ``release_height_m`` where given, its shape
        the rows' ``shape`` with ``row_shapes`` (empty or no column: sphere;
        without ``row_shapes`` every entry is a sphere): of the
        heights as measured, negative ones included (the mean of the rows'
        measurements, each the true height plus an error of one sd; a group
        that mixes heights below and above a raster's ground is released at
        their mean, not at the mean of the clipped heights). Our choice: the
        tolerance trades simulation cost (one simulated sample per entry)
        against the release error of a row, at most ``tol_m``. The entries
        carry no release errors (sds 0): ``with_release_errors`` adds them.

        Args:
            obs: the rows (``calib.files.observations.Observations``).
            default_release_x_m: release of rows that give none, m.
            tol_m: grouping tolerance, m (>= 0).
            profile_of: the ``Profile`` of a row's own profile file
                (``Observations.profile``); needed only where rows name one.
            density_kg_m3: the site's rock density.
            row_shapes: simulate each row in its ``shape`` column's CRSP class.
        """
        if not tol_m >= 0:
            raise ValueError(f"release grouping tolerance must be >= 0 m, got {tol_m!r}")
        n_obs = obs.n_obs
        rel = np.asarray(obs.release_x_m, float)
        rel = np.where(np.isfinite(rel), rel, float(default_release_x_m))
        size = np.asarray(obs.block_size_m, float)
        speed, height = (np.asarray(getattr(obs, name, None) if getattr(obs, name, None)
                                    is not None else np.full(n_obs, np.nan), float)
                         for name in ("release_speed_m_s", "release_height_m"))
        prof = getattr(obs, "profile", None)
        prof = np.full(n_obs, "", dtype=object) if prof is None else np.asarray(prof, object)
        form = entry_shapes(getattr(obs, "shape", None) if row_shapes else None, n_obs)
        sizes, releases, speeds, heights, csv, shapes = [], [], [], [], [], []
        index = np.empty(n_obs, int)
        for pf, d, f in sorted({(pf, d, f) for pf, d, f in zip(prof, size, form)},
                               key=lambda k: (k[1], k[0], k[2])):
            rows = np.flatnonzero((size == d) & (prof == pf) & (form == f))
            rows = rows[np.argsort(rel[rows], kind="stable")]
            for m in _greedy_groups(rows, rel, height, tol_m):
                index[m] = len(sizes)
                sizes.append(d)
                csv.append(pf)
                shapes.append(f)
                releases.append(float(np.mean(rel[m])))
                for values, out in ((speed, speeds), (height, heights)):
                    known = values[m][np.isfinite(values[m])]
                    out.append(float(np.mean(known)) if known.size else np.nan)
        if any(csv) and profile_of is None:
            raise ValueError("rows name their own profiles: give profile_of")
        profiles = tuple(profile_of(p) if p else None for p in csv)
        return cls(np.asarray(sizes, float), np.asarray(releases, float), speeds, heights,
                   profiles, np.asarray(csv, dtype=object), index, density_kg_m3,
                   shapes=np.asarray(shapes, dtype=object))

    @property
    def n(self) -> int:
        """Number of entries E."""
        return int(self.sizes_m.shape[0])

    @property
    def crsp_radius_m(self) -> np.ndarray:
        """(E,) CRSP radii s d / 2 of each entry's shape (a sphere's d / 2), m."""
        return crsp_radius_m(self.sizes_m, self.shapes)

    def crsp_blocks(self, idx=None) -> list:
        """The CRSP ``Block`` of each entry (of ``idx``: entry indices, repeats
        allowed): its shape class, radius ``crsp_radius_m`` and the site's density
        (``solvers.crsp.make_block``), as every CRSP run of entries makes it."""
        idx = range(self.n) if idx is None else np.asarray(idx, int)
        radius = self.crsp_radius_m
        return [make_block(float(radius[i]), self.shapes[i], density_kg_m3=self.density_kg_m3)
                for i in idx]

    @property
    def dem_side_m(self) -> np.ndarray:
        """(E,) DEM square sides L = d, m."""
        return dem_side_m(self.sizes_m)

    @property
    def mass_kg(self) -> np.ndarray:
        """(E,) CRSP mass rho pi d^3 / 6 (every shape class), kg."""
        return self.density_kg_m3 * np.pi * self.sizes_m**3 / 6.0

    @property
    def has_release_errors(self) -> bool:
        """True where some entry's release height or speed carries an error
        (a DEM program must then compile the draws: ``solvers.dem.Options``)."""
        return bool(np.any(self.release_height_sd_m > 0) or np.any(self.release_speed_sd_m_s > 0))

    @property
    def own_profiles(self) -> bool:
        """True where some entry runs on a profile of its own."""
        return any(p is not None for p in self.profiles)

    def take(self, idx) -> Entries:
        """The entries at ``idx`` (no row index: rows map onto the whole set)."""
        idx = np.atleast_1d(np.asarray(idx, int))
        return Entries(self.sizes_m[idx], self.release_x_m[idx], self.release_speed_m_s[idx],
                       self.release_height_m[idx], tuple(self.profiles[i] for i in idx),
                       self.profile_csv[idx], None, self.density_kg_m3,
                       self.release_height_sd_m[idx], self.release_speed_sd_m_s[idx],
                       self.shapes[idx])

    def with_speed_entries(self, sizes_m) -> tuple[Entries, np.ndarray]:
        """These entries followed by one per distinct size of ``sizes_m``, where
        the blocks of passage-speed rows are simulated: a speed row gives a
        size and a station, not a release, so its blocks start at the median
        of these entries' rows' releases (of all entries, without a row
        index), at the solver's default speed and height, on the command's
        profile (our choice). Returns (the entries, the rows' ``index`` kept;
        the entry of each of ``sizes_m``)."""
        rel = self.release_x_m if self.index is None else self.release_x_m[self.index]
        used, inv = np.unique(np.asarray(sizes_m, float), return_inverse=True)
        out = self.concat(Entries.at_sizes(used, float(np.median(rel)),
                                           density_kg_m3=self.density_kg_m3))
        return dataclasses.replace(out, index=self.index), self.n + inv

    def concat(self, other: Entries) -> Entries:
        """These entries followed by ``other``'s (same density; no row index)."""
        if other.density_kg_m3 != self.density_kg_m3:
            raise ValueError("entries of different rock densities cannot be simulated together")
        cat = np.concatenate
        return Entries(cat([self.sizes_m, other.sizes_m]),
                       cat([self.release_x_m, other.release_x_m]),
                       cat([self.release_speed_m_s, other.release_speed_m_s]),
                       cat([self.release_height_m, other.release_height_m]),
                       self.profiles + other.profiles,
                       cat([self.profile_csv, other.profile_csv]), None, self.density_kg_m3,
                       cat([self.release_height_sd_m, other.release_height_sd_m]),
                       cat([self.release_speed_sd_m_s, other.release_speed_sd_m_s]),
                       cat([self.shapes, other.shapes]))

    def with_release_state(self, release_speed_m_s=None, release_height_m=None) -> Entries:
        """The same entries at other release speeds and heights (None: NaN)."""
        return dataclasses.replace(self, release_speed_m_s=release_speed_m_s,
                                   release_height_m=release_height_m)

    def with_release_errors(self, height_sd_m: float = 0.0,
                            speed_sd_m_s: float = 0.0) -> Entries:
        """The same entries with release errors: sd ``height_sd_m`` (m) on every
        given release height, ``speed_sd_m_s`` (m/s) on every given release
        speed (a site's, ``calib.files.site``); 0 where the entry has none (a
        solver's default release is not a measurement)."""
        return dataclasses.replace(
            self,
            release_height_sd_m=np.where(np.isfinite(self.release_height_m),
                                         float(height_sd_m), 0.0),
            release_speed_sd_m_s=np.where(np.isfinite(self.release_speed_m_s),
                                          float(speed_sd_m_s), 0.0))

    def same_as(self, other: Entries) -> bool:
        """Same sizes, shapes, releases, release states and errors, profiles and
        density."""
        return (self.n == other.n and np.array_equal(self.sizes_m, other.sizes_m)
                and np.array_equal(self.shapes, other.shapes)
                and np.array_equal(self.release_x_m, other.release_x_m)
                and np.array_equal(self.release_speed_m_s, other.release_speed_m_s,
                                   equal_nan=True)
                and np.array_equal(self.release_height_m, other.release_height_m,
                                   equal_nan=True)
                and np.array_equal(self.release_height_sd_m, other.release_height_sd_m)
                and np.array_equal(self.release_speed_sd_m_s, other.release_speed_sd_m_s)
                and all(a is b for a, b in zip(self.profiles, other.profiles, strict=True))
                and self.density_kg_m3 == other.density_kg_m3)

    def by_profile(self, profile) -> list | None:
        """The entries split by the profile they run on: None where every entry
        runs on ``profile`` (its own is None or ``profile`` itself), else
        [(profile_k, entry indices), ...] in order of first appearance."""
        own = [profile if p is None else p for p in self.profiles]
        if all(p is profile for p in own):
            return None
        parts: list[tuple[object, list[int]]] = []
        for i, p in enumerate(own):
            for q, idx in parts:
                if q is p:
                    idx.append(i)
                    break
            else:
                parts.append((p, [i]))
        return [(p, np.asarray(idx)) for p, idx in parts]

    def record(self, command_profile_csv: str) -> list[dict]:
        """One JSON-ready dict per entry (calibration and discovery files)."""
        def num(v):
            return None if not np.isfinite(v) else float(v)

        counts = (np.bincount(self.index, minlength=self.n) if self.index is not None
                  else np.zeros(self.n, int))
        return [{"block_size_m": float(d), "shape": str(f), "release_x_m": float(x),
                 "release_speed_m_s": num(v), "release_height_m": num(h),
                 "release_speed_sd_m_s": float(sv), "release_height_sd_m": float(sh),
                 "profile_csv": pf or command_profile_csv, "n_rows": int(k)}
                for d, f, x, v, h, sv, sh, pf, k in zip(
                    self.sizes_m, self.shapes, self.release_x_m, self.release_speed_m_s,
                    self.release_height_m, self.release_speed_sd_m_s, self.release_height_sd_m,
                    self.profile_csv, counts, strict=True)]


def _greedy_groups(rows: np.ndarray, rel: np.ndarray, height: np.ndarray, tol_m: float):
    """Rows (sorted by release) in groups: each joins the first group whose
    leader's release and height lie within ``tol_m`` (``Entries.from_rows``)."""
    leaders, members = [], []
    for i in rows:
        for g, lead in enumerate(leaders):
            same_h = (np.isnan(height[i]) and np.isnan(height[lead])) or (
                abs(height[i] - height[lead]) <= tol_m)
            if rel[i] - rel[lead] <= tol_m and same_h:
                members[g].append(i)
                break
        else:
            leaders.append(i)
            members.append([i])
    return [np.asarray(m) for m in members]
