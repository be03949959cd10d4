"""Release conditions of a hazard run (RocFall's "seeders"): the block-volume
distribution and its volume classes, the release zone, release heights and speeds,
and how ONE block's release is drawn from its key.

Block size. A block of volume V is simulated as the volume-equivalent sphere of
diameter d = (6 V / pi)^(1/3) (the toolkit's block-size rule,
``calib.model.entries``; ``calib.model.entries.sphere_diameter_m`` makes the
same sphere from a mass) and mass rho V, rho the site's rock density.

Volume laws (``VolumeLaw``; F the cumulative distribution, Q = F^-1):

* ``empirical``: the volumes of a block survey (``calib.files.block_survey``),
  each equally likely: a block is one of them drawn at random (a bootstrap of the
  survey), Q(p) = v_(floor(p n) + 1) of the n sorted volumes. Nothing beyond the
  survey's largest block is drawn.
* ``lognormal``: ln V normal with median ``median_m3`` and standard deviation
  ``sigma``, Q(p) = median exp(sigma Phi^-1(p)).
* ``powerlaw``: the magnitude-frequency relation of rockfall volumes, a power law
  of the number of blocks larger than V, N(> V) ~ V^-b (Dussauge-Peisser et al.
  2002, NHESS 2:15, "Probabilistic approach to rock fall hazard assessment:
  potential of historical data analysis": title and authors read in a stored
  copy, the law recalled, verify the exponents for a site), truncated to
  [vmin, vmax]: F(V) = (vmin^-b - V^-b) / (vmin^-b - vmax^-b),
  Q(p) = (vmin^-b - p (vmin^-b - vmax^-b))^(-1/b).

Design block by return period (``VolumeLaw.return_period_volume_m3``). De Biagi
et al. 2017 (NHESS 17:103, "Estimation of the return period of rockfall blocks
according to their size", doi:10.5194/nhess-17-103-2017) tie the design block
to its return period, estimated from a survey of the blocks fallen to the foot
of the slope and historical data (read: the abstract and first page in a stored
copy; the paper's own estimator was not read). Ours: blocks released as a
Poisson process of R blocks per year (``--release-rate-per-year``) whose
volumes follow F; blocks larger than V then come at R (1 - F(V)) per year, and
the T-year block is the V_T with R (1 - F(V_T)) = 1 / T, V_T = Q(1 - 1 / (R T))
(the mean return period of a Poisson process, T(c) = 1 / (lambda (1 - F(c))),
as in the R package kerdiest's ``mrp``). No such block exists where R T < 1.

Volume classes (``volume_classes``): the tables report per class. A class is a
volume range [v_lo, v_hi), i.e. a probability range [F(v_lo), F(v_hi)) of the
law; default edges at the law's 50, 90 and 99 % quantiles (our choice: four
classes, the top one the rarest 1 %, where design blocks lie: ONR 24810 takes
the 95-98 % fractile of the survey as design block, read in a vendor's summary).
Each class is simulated with the same number of blocks (stratified sampling,
equal allocation: rare large blocks get as many as common small ones), each
block with its own volume drawn from the law within the class, V = Q(p) with
p uniform in the class's probability range. A class's weight in the
distribution, its ``probability``, scales its annual frequencies.

Release zone (``ReleaseZone``): one abscissa; uniform on [A, B]; or points x_k
with weights w_k (block at x_k with probability w_k / sum w).
Release height and speed (``ReleaseState``): mean and standard deviation, each
block's value a normal truncated to >= 0, the solver's own release-error rule
(``solvers.truncated_normal``; our choice: a block starts on or above
the ground, never moving upslope); the speed is the block's horizontal release
velocity, as the fit takes a tracked release speed (``calib.model.forward``).
NaN mean: the solver's default (on the ground, 1 m/s horizontal).

Random numbers. Block j of a draw keyed K_d is keyed fold_in(K_d, j), the key the
solver gives it (``calib.hazard._units``); its release draws use
fold_in(fold_in(K_d, j), ``SEED_STREAM``), so a block's volume, abscissa, height
and speed depend on its index only, not on the chunk it runs in. Block j of every
class uses the same uniforms (common random numbers between classes, as between
the sizes of a run of fixed sizes).
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import ndtri
from scipy.special import ndtr
from scipy.special import ndtri as np_ndtri

from calib.model.entries import crsp_radius_m, sphere_diameter_m
from solvers.truncated_normal import nonnegative_normal

__all__ = ["DEFAULT_CLASS_QUANTILES", "SEED_STREAM", "ReleaseState", "ReleaseZone",
           "SeedArrays", "Seeder", "VolumeClass", "VolumeLaw", "diameter_m",
           "parse_release_zone", "parse_volume_law", "sample_release", "volume_classes",
           "volume_m3"]

# the stream of a block's release draws inside its key (any constant other than the
# solver's own uses of the key)
SEED_STREAM = 0x5EED
DEFAULT_CLASS_QUANTILES = (0.5, 0.9, 0.99)
# u in [0, 1) moved by half a step of float64 into (0, 1): Q(0) may be 0 (lognormal)
_HALF_STEP = 2.0**-54
_LAWS = {"lognormal": ("median_m3", "sigma"), "powerlaw": ("vmin_m3", "vmax_m3", "b")}


def diameter_m(volume_m3):
    """Volume-equivalent sphere diameter d = (6 V / pi)^(1/3), m (a volume is the mass
    of a block of unit density: ``calib.model.entries.sphere_diameter_m``)."""
    return sphere_diameter_m(volume_m3, 1.0)


def volume_m3(diameter):
    """Volume of the sphere of diameter d, pi d^3 / 6, m^3."""
    return math.pi * np.asarray(diameter, float) ** 3 / 6.0


@dataclasses.dataclass(frozen=True)
class VolumeLaw:
    """A block-volume distribution (module docstring).

    Attributes:
        kind: "empirical", "lognormal" or "powerlaw".
        values: empirical: the sorted volumes, m^3; lognormal: (median_m3, sigma);
            powerlaw: (vmin_m3, vmax_m3, b).
        source: where it comes from (an option's text, a survey file).
    """

    kind: str
    values: tuple[float, ...]
    source: str

    def cdf(self, v) -> np.ndarray:
        """P(V < v) (the empirical law: the fraction of the survey strictly below v)."""
        v = np.asarray(v, float)
        if self.kind == "empirical":
            return np.searchsorted(np.asarray(self.values), v, side="left") / len(self.values)
        if self.kind == "lognormal":
            median, sigma = self.values
            with np.errstate(divide="ignore"):
                return ndtr(np.log(np.maximum(v, 0.0) / median) / sigma)
        lo, hi, b = self.values
        vc = np.clip(v, lo, hi)
        return (lo**-b - vc**-b) / (lo**-b - hi**-b)

    def cdf_right(self, v) -> np.ndarray:
        """P(V <= v) (equal to ``cdf`` but for the survey's own volumes)."""
        if self.kind != "empirical":
            return self.cdf(v)
        return np.searchsorted(np.asarray(self.values), np.asarray(v, float),
                               side="right") / len(self.values)

    def quantile(self, p) -> np.ndarray:
        """Q(p), m^3, for p in [0, 1] (NumPy)."""
        return np.asarray(_quantile(self.kind, np.asarray(self.values, float),
                                    np.asarray(p, float), np), float)

    @property
    def support_m3(self) -> tuple[float, float]:
        """(smallest, largest) volume the law can give, m^3."""
        if self.kind == "empirical":
            return float(self.values[0]), float(self.values[-1])
        if self.kind == "lognormal":
            return 0.0, math.inf
        return float(self.values[0]), float(self.values[1])

    def return_period_volume_m3(self, return_period_yr: float, rate_per_year: float
                                ) -> float:
        """V_T with R (1 - F(V_T)) = 1 / T (module docstring).

        Raises:
            ValueError: R T < 1 (fewer than one block in T years).
        """
        n = rate_per_year * return_period_yr
        if not n >= 1.0:
            raise ValueError(f"{rate_per_year:g} blocks per year release fewer than one "
                             f"block in {return_period_yr:g} years: no {return_period_yr:g}-"
                             "year block")
        return float(self.quantile(1.0 - 1.0 / n))

    def record(self) -> dict:
        """JSON-ready description (hazard.nc's ``release_json``)."""
        if self.kind == "empirical":
            v = np.asarray(self.values)
            return {"kind": "empirical", "source": self.source, "n_volumes": int(v.size),
                    "min_m3": float(v[0]), "median_m3": float(np.median(v)),
                    "max_m3": float(v[-1])}
        return {"kind": self.kind, "source": self.source,
                **dict(zip(_LAWS[self.kind], map(float, self.values), strict=True))}


def _quantile(kind: str, values, p, xp):
    """Q(p) of a law (``xp``: numpy or jax.numpy; jit-able with jnp)."""
    if kind == "empirical":
        n = values.shape[0]
        i = xp.clip(xp.floor(p * n).astype(int if xp is np else jnp.int32), 0, n - 1)
        return values[i]
    if kind == "lognormal":
        nd = np_ndtri if xp is np else ndtri
        return values[0] * xp.exp(values[1] * nd(p))
    if kind == "powerlaw":
        lo, hi, b = values[0], values[1], values[2]
        return (lo**-b - p * (lo**-b - hi**-b)) ** (-1.0 / b)
    return values[0] + 0.0 * p  # "fixed": one volume (a size of a run of fixed sizes)


def _draw(kind: str, seeds: SeedArrays, u: jax.Array) -> jax.Array:
    """The volume of quantile p = p_lo + u (p_hi - p_lo) of the class (jnp). The
    survey's index is kept inside the class's own indices [n p_lo, n p_hi), which
    the rounding of p near p_hi could leave."""
    if kind != "empirical":
        return _quantile(kind, seeds.law_values, seeds.p_lo + u * (seeds.p_hi - seeds.p_lo),
                         jnp)
    n = seeds.law_values.shape[0]
    i_lo, i_hi = (jnp.round(p * n).astype(jnp.int32) for p in (seeds.p_lo, seeds.p_hi))
    i = i_lo + jnp.floor(u * (i_hi - i_lo)).astype(jnp.int32)
    return seeds.law_values[jnp.clip(i, i_lo, i_hi - 1)]


def parse_volume_law(text: str, option: str = "--volume-law") -> VolumeLaw:
    """``lognormal:median_m3=M,sigma=S`` or ``powerlaw:vmin_m3=A,vmax_m3=B,b=B`` as a
    ``VolumeLaw``.

    Raises:
        ValueError: one line naming ``option`` and what was expected.
    """
    expected = ("expected lognormal:median_m3=M,sigma=S or "
                "powerlaw:vmin_m3=A,vmax_m3=B,b=B (volumes in m^3)")
    kind, _, rest = text.partition(":")
    kind = kind.strip()
    if kind not in _LAWS:
        raise ValueError(f"{option} {text}: unknown law {kind!r}; {expected}")
    got = {}
    for part in filter(None, (s.strip() for s in rest.split(","))):
        name, eq, value = part.partition("=")
        name = name.strip()
        if not eq or name not in _LAWS[kind]:
            raise ValueError(f"{option} {text}: {part!r} is not one of "
                             f"{', '.join(n + '=...' for n in _LAWS[kind])}")
        try:
            got[name] = float(value)
        except ValueError:
            raise ValueError(f"{option} {text}: {name}: expected a number, got "
                             f"{value.strip()!r}") from None
        if not math.isfinite(got[name]) or got[name] <= 0:
            raise ValueError(f"{option} {text}: {name}: expected a positive finite number, "
                             f"got {value.strip()}")
    missing = [n for n in _LAWS[kind] if n not in got]
    if missing:
        raise ValueError(f"{option} {text}: {', '.join(missing)} missing; {expected}")
    values = tuple(got[n] for n in _LAWS[kind])
    if kind == "powerlaw" and not values[1] > values[0]:
        raise ValueError(f"{option} {text}: expected vmax_m3 > vmin_m3")
    return VolumeLaw(kind, values, f"{option} {text}")


class VolumeClass(NamedTuple):
    """One volume class of a law (module docstring).

    Attributes:
        p_lo, p_hi: its probability range [F(v_lo), F(v_hi)).
        volume_min_m3, volume_max_m3: the volumes it holds (the law's support
            within the class's range; empirical: its smallest and largest
            surveyed volume), m^3.
        volume_m3: its representative volume, the law's median within the class,
            Q((p_lo + p_hi) / 2), m^3.
        size_m: the representative volume's sphere diameter to 3 significant
            digits, m (the class's ``block_size_m`` in the tables and in hazard.nc,
            and the size ``calib.design --block-size-m`` names it by). Two classes
            whose sizes round alike are refused.
        label: e.g. "0.1-0.5 m3".
    """

    p_lo: float
    p_hi: float
    volume_min_m3: float
    volume_max_m3: float
    volume_m3: float
    size_m: float
    label: str

    @property
    def probability(self) -> float:
        """The class's weight in the distribution, p_hi - p_lo."""
        return self.p_hi - self.p_lo


def volume_classes(law: VolumeLaw, edges_m3=None, option: str = "--volume-classes-m3"
                   ) -> list[VolumeClass]:
    """The classes [e_k, e_k+1) of ``law`` between interior edges ``edges_m3`` (m^3,
    increasing; default: the law's quantiles ``DEFAULT_CLASS_QUANTILES``, merged where
    they coincide).

    Raises:
        ValueError: edges not increasing and positive, or a class without blocks.
    """
    if edges_m3 is None:
        edges = np.unique(law.quantile(DEFAULT_CLASS_QUANTILES))
        edges = [e for e in edges if 0.0 < law.cdf(e) < 1.0]
    else:
        edges = [float(e) for e in edges_m3]
        if any(not (math.isfinite(e) and e > 0) for e in edges) or any(
                b <= a for a, b in zip(edges, edges[1:])):
            raise ValueError(f"{option}: expected increasing positive volumes, got "
                             f"{','.join(f'{e:g}' for e in edges)}")
    lo_s, hi_s = law.support_m3
    bounds = [-math.inf, *edges, math.inf]
    out = []
    for a, b in zip(bounds, bounds[1:]):
        p_lo = 0.0 if a == -math.inf else float(law.cdf(a))
        p_hi = 1.0 if b == math.inf else float(law.cdf(b))
        if not p_hi > p_lo:
            raise ValueError(f"{option}: the class [{a:g}, {b:g}) m3 holds no block of "
                             f"{law.source} (its volumes span {lo_s:g}-{hi_s:g} m3)")
        if law.kind == "empirical":
            v = np.asarray(law.values)
            i_lo, i_hi = round(p_lo * v.size), round(p_hi * v.size)
            vmin, vmax = float(v[i_lo]), float(v[i_hi - 1])
        else:
            vmin, vmax = max(a, lo_s), min(b, hi_s)
        rep = float(law.quantile(0.5 * (p_lo + p_hi)))
        size = float(f"{float(diameter_m(rep)):.3g}")  # a size one can type (calib.design)
        out.append(VolumeClass(p_lo, p_hi, float(vmin), float(vmax), rep, size,
                               f"{vmin:.3g}-{vmax:.3g} m3"))
    sizes = [c.size_m for c in out]
    if len(set(sizes)) != len(sizes):
        raise ValueError(f"{option}: two classes of {law.source} have the same representative "
                         f"size to 3 digits ({', '.join(f'{d:g}' for d in sizes)} m): merge "
                         "them (fewer, wider classes)")
    return out


@dataclasses.dataclass(frozen=True)
class ReleaseZone:
    """Where blocks start (module docstring).

    Attributes:
        kind: "point", "uniform" or "points".
        x_m: the abscissa; (A, B) of the uniform zone; the points, m.
        weights: the points' weights (normalised), else ().
    """

    kind: str
    x_m: tuple[float, ...]
    weights: tuple[float, ...] = ()

    @property
    def span_m(self) -> tuple[float, float]:
        """(first, last) release abscissa, m."""
        return min(self.x_m), max(self.x_m)

    def text(self) -> str:
        """As ``summary.txt`` says it."""
        if self.kind == "point":
            return f"at x = {self.x_m[0]:g} m"
        if self.kind == "uniform":
            return f"uniformly on x = {self.x_m[0]:g}-{self.x_m[1]:g} m"
        return "at x = " + ", ".join(f"{x:g} m ({w:.0%})" for x, w in
                                     zip(self.x_m, self.weights, strict=True))

    def record(self) -> dict:
        return {"kind": self.kind, "x_m": list(self.x_m), "weights": list(self.weights)}


def parse_release_zone(text: str, option: str = "--release-zone-m") -> ReleaseZone:
    """``A:B`` (uniform, A < B) or ``x1:w1,x2:w2,...`` (points with weights > 0).

    Raises:
        ValueError: one line naming ``option`` and what was expected.
    """
    expected = "expected A:B (uniform, A < B) or x1:w1,x2:w2,... (points with weights), m"
    parts = [p.strip() for p in text.split(",") if p.strip()]
    pairs = []
    for p in parts:
        a, colon, b = p.partition(":")
        try:
            pairs.append((float(a), float(b)))
        except ValueError:
            raise ValueError(f"{option} {text}: {p!r}: {expected}") from None
        if not colon or not all(math.isfinite(v) for v in pairs[-1]):
            raise ValueError(f"{option} {text}: {p!r}: {expected}")
    if not pairs:
        raise ValueError(f"{option} {text}: {expected}")
    if len(pairs) == 1:
        a, b = pairs[0]
        if not a < b:
            raise ValueError(f"{option} {text}: {expected}")
        return ReleaseZone("uniform", (a, b))
    xs = [x for x, _ in pairs]
    w = np.asarray([w for _, w in pairs])
    if np.any(w <= 0):
        raise ValueError(f"{option} {text}: weights must be positive; {expected}")
    if len(set(xs)) != len(xs):
        raise ValueError(f"{option} {text}: points must be distinct")
    return ReleaseZone("points", tuple(xs), tuple(float(v) for v in w / w.sum()))


@dataclasses.dataclass(frozen=True)
class ReleaseState:
    """Release height above the ground (m) and horizontal speed (m/s) of the blocks:
    mean (NaN: the solver's default) and standard deviation (module docstring)."""

    height_m: float = math.nan
    height_sd_m: float = 0.0
    speed_m_s: float = math.nan
    speed_sd_m_s: float = 0.0

    def record(self) -> dict:
        def num(v):
            return None if math.isnan(v) else float(v)

        return {"height_m": num(self.height_m), "height_sd_m": self.height_sd_m,
                "speed_m_s": num(self.speed_m_s), "speed_sd_m_s": self.speed_sd_m_s,
                "rule": "normal truncated to >= 0 (solvers.truncated_normal); "
                        "speed = horizontal release velocity; "
                        "null: the solver's default (on the ground, 1 m/s)"}


class SeedArrays(NamedTuple):
    """What ``sample_release`` draws from, for the blocks of one class (a pytree).

    Attributes:
        law_values: the law's ``values`` (a fixed size: its volume, m^3, and its
            diameter, m).
        p_lo, p_hi: the class's probability range.
        zone_x_m: the zone's abscissae, m.
        zone_cum: cumulative weights of the points (points zones), else zeros.
        height_m, speed_m_s: (mean, sd) each (NaN mean: the solver's default).
        shape: (s, k) of the class's CRSP shape (``solvers.crsp.shape_constants``:
            the radius of a block of volume V is s (3 V / (4 pi))^(1/3); k = I /
            (m r^2)).
    """

    law_values: jax.Array
    p_lo: jax.Array
    p_hi: jax.Array
    zone_x_m: jax.Array
    zone_cum: jax.Array
    height_m: jax.Array
    speed_m_s: jax.Array
    shape: jax.Array


@dataclasses.dataclass(frozen=True)
class Seeder:
    """A hazard run's release conditions: the classes it reports (with their volume
    law, or one fixed size each), the zone and the release state.

    Attributes:
        law: the volume law, or None for a run of fixed sizes.
        classes: the volume classes (a run of fixed sizes: one per size).
        zone: where blocks start.
        state: release heights and speeds.
        shapes: the CRSP shape class of each class's blocks
            (``solvers.crsp.SHAPES``), or None: spheres.
    """

    law: VolumeLaw | None
    classes: tuple[VolumeClass, ...]
    zone: ReleaseZone
    state: ReleaseState = ReleaseState()
    shapes: tuple[str, ...] | None = None

    @classmethod
    def fixed_sizes(cls, sizes_m, zone: ReleaseZone, state: ReleaseState = ReleaseState(),
                    shapes: tuple[str, ...] | None = None) -> Seeder:
        """Blocks of the given sizes d (m), one class each, released by ``zone`` and
        ``state``; a size is the diameter of the sphere of the block's volume, in
        every shape (``shapes``, None: spheres; ``calib.model.entries``: radius s d
        / 2)."""
        from solvers.crsp import make_block

        # the volume as solvers.crsp.make_block computes it for the radius
        # calib.model.entries gives the shape: the block weighs, to the bit, what a run
        # without release conditions simulates
        forms = shapes or ("sphere",) * len(sizes_m)
        vols = [float(make_block(float(crsp_radius_m(float(d), f)), f, density_kg_m3=1.0)
                      .mass_kg) for d, f in zip(sizes_m, forms, strict=True)]
        classes = tuple(VolumeClass(0.0, 1.0, v, v, v, float(d), f"D = {d:g} m")
                        for d, v in zip(sizes_m, vols, strict=True))
        return cls(None, classes, zone, state, shapes)

    @property
    def class_shapes(self) -> tuple[str, ...]:
        """The CRSP shape class of each class's blocks."""
        return self.shapes or ("sphere",) * len(self.classes)

    @property
    def sizes_m(self) -> np.ndarray:
        """(T,) the classes' representative diameters, m."""
        return np.asarray([c.size_m for c in self.classes], float)

    @property
    def kinds(self) -> tuple[str, str]:
        """(law kind, zone kind): the static part of the draw (``sample_release``)."""
        return ("fixed" if self.law is None else self.law.kind), self.zone.kind

    def arrays(self, t: int) -> SeedArrays:
        """The ``SeedArrays`` of class ``t``."""
        c = self.classes[t]
        values = [c.volume_m3, c.size_m] if self.law is None else list(self.law.values)
        cum = (np.cumsum(self.zone.weights) if self.zone.kind == "points"
               else np.zeros(len(self.zone.x_m)))
        s = self.state
        f = _f64
        from solvers.crsp import shape_constants

        return SeedArrays(f(values), f(c.p_lo), f(c.p_hi), f(self.zone.x_m), f(cum),
                          f([s.height_m, s.height_sd_m]), f([s.speed_m_s, s.speed_sd_m_s]),
                          f(shape_constants(self.class_shapes[t])))

    def extrapolated_fraction(self, fitted_sizes_m) -> np.ndarray:
        """(T,) the fraction of each class's blocks whose size lies outside the range
        of ``fitted_sizes_m`` (the sizes a calibration was fitted on): under the law,
        (P(v_lo <= V < V(d_min)) + P(V(d_max) < V < v_hi)) / P(class); a fixed size
        1 or 0."""
        d = np.asarray(fitted_sizes_m, float)
        tol = 1e-9 * d.max()
        if self.law is None:
            return np.asarray([0.0 if d.min() - tol <= c.size_m <= d.max() + tol else 1.0
                               for c in self.classes])
        v_lo, v_hi = volume_m3(d.min() - tol), volume_m3(d.max() + tol)
        below, upto = float(self.law.cdf(v_lo)), float(self.law.cdf_right(v_hi))
        out = []
        for c in self.classes:
            outside = (max(0.0, min(below, c.p_hi) - c.p_lo)
                       + max(0.0, c.p_hi - max(upto, c.p_lo)))
            out.append(outside / c.probability)
        return np.asarray(out)

    def record(self) -> dict:
        """JSON-ready description (hazard.nc's ``release_json``)."""
        return {"volume_law": None if self.law is None else self.law.record(),
                "classes": [{"label": c.label, "volume_min_m3": c.volume_min_m3,
                             "volume_max_m3": c.volume_max_m3, "volume_m3": c.volume_m3,
                             "block_size_m": c.size_m, "probability": c.probability}
                            for c in self.classes] if self.law is not None else None,
                "zone": self.zone.record(), "state": self.state.record(),
                "shapes": list(self.class_shapes),
                "sampling": "each class (or size) with --n-blocks blocks per draw; a block's "
                            "volume, abscissa, height and speed drawn from its key "
                            "(calib.model.release)"}


def _f64(v) -> jax.Array:
    """``v`` as a float64 JAX array."""
    return jnp.asarray(v, jnp.float64)


def sample_release(seeds: SeedArrays, kinds: tuple[str, str], key: jax.Array):
    """ONE block's release (pure, jit-able; module docstring).

    Args:
        seeds: its class's ``SeedArrays``.
        kinds: (law kind, zone kind), static.
        key: the block's key (fold_in(K_d, j)); the draws use
            fold_in(key, ``SEED_STREAM``).

    Returns:
        (volume V, m^3; diameter d, m; abscissa x, m; height h, m; speed v, m/s), h
        and v NaN where the state keeps the solver's default. d = (6 V / pi)^(1/3),
        except for a fixed size, whose d is the size itself (so that its sphere is
        the one a run of fixed sizes simulates, to the last bit).
    """
    law_kind, zone_kind = kinds
    k_u, k_z = jax.random.split(jax.random.fold_in(key, SEED_STREAM))
    u = jax.random.uniform(k_u, (2,), dtype=jnp.float64) + _HALF_STEP
    z = jax.random.uniform(k_z, (2,), dtype=jnp.float64)
    volume = _draw(law_kind, seeds, u[0])
    d = seeds.law_values[1] if law_kind == "fixed" else jnp.cbrt(6.0 * volume / jnp.pi)
    zx = seeds.zone_x_m
    if zone_kind == "uniform":
        x = zx[0] + u[1] * (zx[1] - zx[0])
    elif zone_kind == "points":
        x = zx[jnp.minimum(jnp.searchsorted(seeds.zone_cum, u[1], side="right"),
                           zx.shape[0] - 1)]
    else:
        x = zx[0]
    # the solver's own release-error rule (solvers.truncated_normal): a normal
    # truncated to >= 0; a NaN mean stays NaN, kept as "the solver's default"
    h = nonnegative_normal(z[0], seeds.height_m[0], seeds.height_m[1])
    v = nonnegative_normal(z[1], seeds.speed_m_s[0], seeds.speed_m_s[1])
    return volume, d, x, h, v
