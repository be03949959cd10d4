"""Sums over small axes whose rounding does not depend on a lane's place in a call.

Under ``vmap`` XLA's CPU backend vectorises a loop over the lanes of a call
and leaves the last one to four lanes to a scalar remainder loop. A
reduction (``jnp.sum``) of three or more terms inside the DEM's step is
compiled differently in the two loops, with another order of additions:
measured on a 2 m block at alpha 0.41 on the Postignano profile, 32
identical lanes of one call agreed to the bit for 5,407 steps, then the
corner forces of lanes 28-31 differed from those of lanes 0-27 in the last
bits (5343.88636158 against 5343.8863616 N/m), and a block that bounces
carries such a difference into another trajectory (the lanes stopped at
140.483 and 140.601 m). Elementwise arithmetic rounds the same in both loops
(measured: sin, cos, exp, log, tanh, atan2, sqrt, pow, a b + c), so
``ordered_sum`` writes the sum as a fixed chain of additions,

    s = x_0 + x_1 + ... + x_{n-1}    (left to right),

and a lane's result no longer depends on which lanes share its call, or on
where in the call it sits (our choice; the physics is unchanged).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["ordered_sum"]


def ordered_sum(x: jax.Array, axis: int | tuple[int, ...]) -> jax.Array:
    """Sum of ``x`` over ``axis`` as a left-to-right chain of additions.

    Meant for small static axes (the 4 corners of a fragment, a few
    neighbours times 4 corners): the chain is unrolled at trace time. Two
    terms are summed exactly alike in any order, so axes of length 2 need no
    chain.

    Args:
        x: array.
        axis: axis or axes to sum over (their elements in row-major order).

    Returns:
        ``x`` summed over ``axis``.
    """
    axes = (axis,) if isinstance(axis, int) else tuple(axis)
    axes = tuple(sorted(a % x.ndim for a in axes))
    kept = [a for a in range(x.ndim) if a not in axes]
    x = jnp.transpose(x, kept + list(axes))
    x = x.reshape(x.shape[:len(kept)] + (-1,))
    if x.shape[-1] == 0:
        return jnp.zeros(x.shape[:-1], x.dtype)
    total = x[..., 0]
    for i in range(1, x.shape[-1]):
        total = total + x[..., i]
    return total
