"""Stage sizes of a calibration (``Budget``) and the presets per model.

Blocks are per parameter point and simulated entry (``calib.model.entries``).
``presets(model, quick)`` gives the default budget of ``python -m calib.fit``
and its ``--quick`` budget (tests, a first look). The discrepancy workflow's
own stage sizes are ``calib.discovery.discrepancy.Budget``.
"""

from __future__ import annotations

import dataclasses

__all__ = ["Budget", "presets"]


@dataclasses.dataclass(frozen=True)
class Budget:
    """Sizes of every stage (blocks are per parameter point and block size)."""

    n_design: int = 96
    n_design2: int = 64
    n_design3: int = 64
    n_blocks_design: int = 256
    n_levels: int = 10
    nuts_warmup: int = 500
    nuts_samples: int = 1000
    nuts_chains: int = 4
    n_realisations: int = 32
    realisation_waves: int = 3
    grad_starts: int = 3
    grad_steps: int = 40
    grad_k: int = 3
    n_blocks_grad: int = 256
    n_check: int = 2000
    n_predictive_draws: int = 32
    n_blocks_predictive: int = 64


def presets(model: str, quick: bool) -> Budget:
    """Stage sizes per model (``--quick`` for tests; the default for real use)."""
    if model == "crsp":
        if quick:
            return Budget(n_design=48, n_design2=32, n_design3=32, n_blocks_design=128,
                          nuts_warmup=200, nuts_samples=400, nuts_chains=2, grad_starts=2,
                          grad_steps=8, grad_k=2, n_blocks_grad=64, n_check=128,
                          n_predictive_draws=16, n_blocks_predictive=32,
                          realisation_waves=1)
        # twice the draws of the DEM's: with the log-likelihood GP NUTS costs ~15-20 s
        # (was ~160 s on Postignano, ~760 s on Tschamut), and the CRSP posteriors of
        # both sites mix slowly (Postignano seed 0: R-hat 1.016-1.023 at 1,000 draws
        # per chain, 1.010-1.013 at 2,000)
        return Budget(nuts_warmup=1000, nuts_samples=2000)
    if model == "dem":
        if quick:
            return Budget(n_design=8, n_design2=0, n_design3=0, n_blocks_design=4, nuts_warmup=200,
                          nuts_samples=400, nuts_chains=2, grad_starts=1, grad_steps=2,
                          grad_k=1, n_blocks_grad=4, n_check=4, n_predictive_draws=2,
                          n_blocks_predictive=2)
        return Budget(n_design=16, n_design2=0, n_design3=0, n_blocks_design=12, grad_starts=2,
                      grad_steps=8, grad_k=1, n_blocks_grad=8, n_check=16,
                      n_predictive_draws=4, n_blocks_predictive=4)
    raise ValueError(f"unknown model {model!r}")
