"""Inference: the observation model, gradient fit, emulator, Bayesian posterior
and its diagnostics, the calibration stages, the adequacy and predictive
checks, importance weights.

``docs/architecture.md`` maps every module.
"""
