"""Partial factors and rules of a rockfall barrier design (UNI 11211-4 as practised in
Italy, Peila & Ronco 2009), each with its value and the source it was read in.

Design values (Peila & Ronco 2009, NHESS 9:1291-1298; the factors' names and
ranges read in RocFall's "UNI 11211 Design" help page, which cites UNI
11211-4:2012 and that paper; the product forms below are recalled from the paper
and consistent with that page, whose formulas were not read):

    v_d  = v_p gamma_Tr gamma_Dp                       (design speed)
    h_d  = h_p gamma_Tr gamma_Dp                       (design passing height)
    m_d  = Vol_d rho gamma_VolF gamma_gamma            (design mass)
    E_sd = 1/2 m_d v_d^2                               (design energy, translational)
    E_sd <= E_kit / gamma_E,  E_kit = MEL or SEL        (energy check)
    H_kit >= h_d + f_min                               (height check)
    D_A >= D_d                                         (elongation check)

with v_p, h_p the p-th percentile (95, UNI 11211-4; 95 or 99, ONR 24810:2021)
of the simulated speed and passing height at the barrier. ``SOURCES`` says, for
each factor and rule, what was read and what is recalled only.
"""

from __future__ import annotations

import dataclasses
import math

__all__ = ["DEFAULTS", "GAMMA_E", "MIN_FREE_BOARD_M", "REFERENCES", "SOURCES", "Factors",
           "free_board_m", "min_protected_distance_m"]

# the sources read (or named) for the factors and rules; SOURCES cite them by key
REFERENCES = {
    "R": "RocFall help page 'UNI 11211 Design' (Rocscience), copy read at "
         "scribd.com/document/615855522; it cites UNI (2012) UNI 11211-4:2012 'Rockfall "
         "protective measures. Part 4: Definitive and executive design' and [PR]",
    "PR": "Peila, D. and Ronco, C. (2009): Technical Note: Design of rockfall net fences and "
          "the new ETAG 027 European guideline, Nat. Hazards Earth Syst. Sci. 9:1291-1298 "
          "(named by [R]; its full text was not read here)",
    "M": "Marchelli, M. (2022): A design method for double line of rockfall net fences in "
         "the framework of probabilistic trajectory analyses, GEAM 166 (read: 'UNI "
         "11211-4:2018; ONR 24810:2021 ... the 95th or 99th percentiles')",
    "T1": "trumerschutzbauten.com, 'ONR 24810 constructive rules' (read)",
    "T2": "trumerschutzbauten.com, 'ETAG 27 Guidelines' (read): EAD 340059-00-0106 replaced "
          "ETAG 027 in 2019; one MEL and two SEL tests, none at SEL for 100 kJ kits; MEL, SEL, "
          "residual-height category and maximum elongation declared",
    "G": "Geosciences 9(1):49 (2019), 'Review of Approval of Flexible Rockfall Protection "
         "Systems According to ETAG 027' (read: energy classes, 66 kits)",
}
SOURCES = {
    "percentile": "95th: UNI 11211-4, '95 % suggested and the default' [R]; 99th as an "
                  "option: ONR 24810:2021 [M]",
    "gamma_Tr": "reliability of the trajectory simulation: 1.02 back-analysed on site, 1.10 "
                "coefficients from the literature [R]",
    "gamma_Dp": "quality of the topographic survey: 1.02 high, 1.10 low [R]",
    "gamma_VolF": "precision of the design-block survey: 1.02 high, 1.10 low [R]",
    "gamma_gamma": "unit weight of the rock: >= 1.0, generally 1.0 [R]",
    "gamma_E": "E_sd <= E_kit / gamma_E, E_kit the MEL or the SEL [R]; 1.2 against the MEL "
               "and 1.0 against the SEL: recalled from [PR], unverified",
    "free_board": "f_min at least 0.5 m [R] (whose text reads 'at least 0.5 m and at most "
                  "half the average size of the block (for example, f_min = the radius)'); "
                  "our rule: f_min = max(0.5 m, D/2)",
    "elongation": "distance to the protected object >= 1.2 x the MEL elongation and >= the "
                  "elongation + 1 m: ONR 24810 [T1]; UNI 11211-4 asks D_A >= D_d [R], D_d "
                  "not read here",
    "kits": "kits declared by MEL, SEL, residual-height category, maximum elongation "
            "(EAD 340059-00-0106, ETAG 027 before) [T2], [G]",
    "formulas": "v_d = v_p gamma_Tr gamma_Dp, h_d = h_p gamma_Tr gamma_Dp, m_d = Vol rho "
                "gamma_VolF gamma_gamma, E_sd = 1/2 m_d v_d^2: recalled from [PR], "
                "consistent with the factors of [R]",
}
# gamma_E against each energy level (recalled, unverified: SOURCES["gamma_E"])
GAMMA_E = {"MEL": 1.2, "SEL": 1.0}
MIN_FREE_BOARD_M = 0.5
# ONR 24810 (SOURCES["elongation"])
ELONGATION_FACTOR = 1.2
ELONGATION_MARGIN_M = 1.0


@dataclasses.dataclass(frozen=True)
class Factors:
    """The partial factors of one design (module docstring; ``SOURCES``).

    Defaults (``DEFAULTS``) are our choices within the ranges read: gamma_Tr
    1.02 because ``calib.fit`` back-analyses the site's own runouts; gamma_Dp
    and gamma_VolF 1.10 because the toolkit cannot know the surveys' quality;
    gamma_gamma 1.0; gamma_E by the energy level checked (``GAMMA_E``).
    """

    gamma_Tr: float = 1.02
    gamma_Dp: float = 1.10
    gamma_VolF: float = 1.10
    gamma_gamma: float = 1.0
    gamma_E: float = GAMMA_E["MEL"]

    def check(self, names: dict[str, str] | None = None) -> None:
        """Raise ``ValueError`` naming the first factor that is not a positive
        finite number (``names``: factor -> the option that set it)."""
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                who = (names or {}).get(f.name, f.name)
                raise ValueError(f"{who}: expected a positive factor, got {v!r}")

    def below_one(self) -> list[str]:
        """Names of the factors below 1 (they lower the design values)."""
        return [f.name for f in dataclasses.fields(self) if getattr(self, f.name) < 1.0]

    def table(self) -> list[dict]:
        """One row per factor: symbol, value, source."""
        return [{"factor": f.name, "value": getattr(self, f.name), "source": SOURCES[f.name]}
                for f in dataclasses.fields(self)]


DEFAULTS = Factors()


def free_board_m(block_size_m: float, requested_m: float | None = None) -> float:
    """The free board above the design passing height: max(0.5 m, D/2), or the
    requested one where given (``SOURCES["free_board"]``).

    Raises:
        ValueError: a requested free board below that minimum.
    """
    least = max(MIN_FREE_BOARD_M, 0.5 * block_size_m)
    if requested_m is None:
        return least
    if not (math.isfinite(requested_m) and requested_m >= least):
        raise ValueError(f"--free-board-m {requested_m:g}: below the minimum max(0.5 m, D/2) "
                         f"= {least:g} m for D = {block_size_m:g} m")
    return float(requested_m)


def min_protected_distance_m(max_elongation_m: float) -> float:
    """Least distance from the barrier to the protected object for a kit of this
    MEL elongation: max(1.2 e, e + 1 m) (ONR 24810, ``SOURCES["elongation"]``)."""
    return max(ELONGATION_FACTOR * max_elongation_m, max_elongation_m + ELONGATION_MARGIN_M)
