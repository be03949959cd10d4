"""Rockfall intensity classes and the intensity-frequency (hazard) matrix.

Intensity (kinetic energy E of a block passing a point), Swiss practice:

    weak  E < 30 kJ,   medium  30 kJ <= E <= 300 kJ,   strong  E > 300 kJ.

Checked: Canton of Valais, "Gefahrenstufen für Massenbewegungen"
(https://vs.ch/de/web/sdana/instabilites-de-terrain, stored copy read for this
project): "Block- und Steinschlag: schwach < 30 kJ, mittel 30-300 kJ,
stark > 300 kJ"; probability
classes high / medium / low / very low for return periods of 30, 100, 300 and
over 300 years; hazard levels red, blue, yellow, yellow-white hatched, white.
The federal source (not read here) is BRP/BWW/BUWAL (1997) "Empfehlungen: Berücksichtigung der
Massenbewegungsgefahren bei raumwirksamen Tätigkeiten" (Bern), summarised in
Raetzo et al. (2002), Bull. Eng. Geol. Env. 61:263-268, and in FOEN (2016)
"Protection against mass movement hazards".

The matrix below (which cell is red, blue or yellow) is RECALLED, NOT VERIFIED
against the text of those guidelines; check it before a planning decision:

    probability \\ intensity    weak     medium   strong
    high    (T <= 30 yr)        blue     red      red
    medium  (30 < T <= 100)     yellow   blue     red
    low     (100 < T <= 300)    yellow   blue     red
    very low (T > 300 yr)       residual (yellow-white hatched) for every intensity

How a point is zoned (the Cadanav procedure, Jaboyedoff et al. 2005;
Abbruzzese et al. 2009, NHESS 9:1095): for each intensity class i with lower
energy threshold E_i (0, 30, 300 kJ), the annual frequency of a block reaching
x with E > E_i is

    f_i(x) = R * P(reach x) * P(E > E_i | reach x)

(R: blocks released per year; Hantz et al. 2021, Geosciences 11:158, "passage
frequency"); f_i gives a probability class, the matrix a level, and the point
takes the most severe level over i. A point no simulated block reaches is
white.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ENERGY_THRESHOLDS_KJ", "LEVELS", "PROBABILITY_CLASSES", "RETURN_PERIOD_BOUNDS_YR",
           "hazard_level", "intensity_class", "probability_class"]

ENERGY_THRESHOLDS_KJ = (30.0, 300.0)
INTENSITY_NAMES = ("weak", "medium", "strong")
PROBABILITY_CLASSES = ("high", "medium", "low", "very low")
RETURN_PERIOD_BOUNDS_YR = (30.0, 100.0, 300.0)
# hazard levels, least to most severe
LEVELS = ("white", "residual", "yellow", "blue", "red")
# _MATRIX[probability class][intensity class] -> level (recalled, see docstring)
_MATRIX = (
    ("blue", "red", "red"),
    ("yellow", "blue", "red"),
    ("yellow", "blue", "red"),
    ("residual", "residual", "residual"),
)


def intensity_class(energy_kJ: float) -> str:
    """Swiss intensity class of an energy in kJ; "" for NaN (no block)."""
    if not np.isfinite(energy_kJ):
        return ""
    if energy_kJ < ENERGY_THRESHOLDS_KJ[0]:
        return "weak"
    return "medium" if energy_kJ <= ENERGY_THRESHOLDS_KJ[1] else "strong"


def probability_class(freq_per_yr: float) -> str:
    """Probability class of an annual frequency (return period T = 1/f);
    "" when f = 0 or NaN."""
    if not (np.isfinite(freq_per_yr) and freq_per_yr > 0):
        return ""
    t = 1.0 / freq_per_yr
    for name, bound in zip(PROBABILITY_CLASSES, RETURN_PERIOD_BOUNDS_YR, strict=False):
        if t <= bound:
            return name
    return PROBABILITY_CLASSES[-1]


def hazard_level(freq_reach: float, freq_e30: float, freq_e300: float) -> str:
    """Level of a point from the annual frequencies of a block reaching it with
    E > 0, > 30 kJ and > 300 kJ (the most severe over the three classes);
    "" when the reach frequency is NaN."""
    if not np.isfinite(freq_reach):
        return ""
    best = "white"
    for i, f in enumerate((freq_reach, freq_e30, freq_e300)):
        p = probability_class(f)
        if not p:
            continue
        level = _MATRIX[PROBABILITY_CLASSES.index(p)][i]
        if LEVELS.index(level) > LEVELS.index(best):
            best = level
    return best
