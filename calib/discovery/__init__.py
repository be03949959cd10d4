"""The discrepancy workflow: candidates, their fits and held-out scores, where the
baseline fails, synthetic data with a hidden effect, power studies, the
workflow's warnings.

``docs/architecture.md`` maps every module.
"""
