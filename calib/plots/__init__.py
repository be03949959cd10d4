"""Figures of a calibration, a predictive check and the discrepancy workflow
(matplotlib, Agg backend).

``docs/architecture.md`` maps every module.
"""
