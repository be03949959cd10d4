"""A normal draw truncated to non-negative values, by the inverse CDF.

A release height or speed measured with an error is an uncertain input: the
true value is ``x ~ N(m, sd^2)`` restricted to ``x >= 0`` (a block cannot
start inside the ground, a speed is not negative). ``m`` may itself be
negative: a tracked release that a raster puts below its ground is a release
at a height drawn from the error's tail above 0.

Inverse-CDF draw (e.g. Robert 1995, "Simulation of truncated normal
variables", Stat. Comput. 5, 121-125, Sect. 1): with ``Phi`` and ``Phi^-1``
``jax.scipy.special.ndtr`` and ``ndtri`` and u uniform in [0, 1), the draw
``x = F^-1(u)`` of the truncated distribution function
``F(x) = (Phi((x - m) / sd) - p0) / (1 - p0)``, ``p0 = Phi(-m / sd)``, is
written in whichever tail keeps it accurate:

* m >= 0: ``x = m + sd Phi^-1(p0 + u (1 - p0))`` (p0 <= 1/2; near ``1 - p0 = 1``
  for m >> sd, where the other form would round ``Phi(m / sd)`` to 1);
* m < 0: ``x = m - sd Phi^-1((1 - u) q)``, ``q = Phi(m / sd) = 1 - p0`` (the
  upper tail, accurate where m lies many sds below 0 and ``1 - p0`` would
  round to 0). Where q underflows (m below about -37 sd) the draw is 0, the
  limit of the tail's scale ``sd^2 / |m|``.

Both arguments of ``Phi^-1`` are floored at the smallest normal float64, so
that the draw stays finite (``Phi^-1(0) = -inf``) and within about 37.5 sd of
m where p0 underflows (m above about 37 sd).

``sd = 0`` is the point value clipped at 0, ``max(m, 0)``, and the draw tends
to it as ``sd -> 0``. Pure and jit-able; the caller supplies the uniform.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.scipy.special import ndtr, ndtri

__all__ = ["nonnegative_normal"]

_TINY = float(jnp.finfo(jnp.float64).tiny)


def nonnegative_normal(u: jax.Array, mean: jax.Array, sd: jax.Array) -> jax.Array:
    """A draw of N(mean, sd^2) truncated to >= 0 (module docstring).

    Args:
        u: uniform in [0, 1).
        mean: m, any sign.
        sd: the error's sd, >= 0; 0 gives ``max(mean, 0)``.

    Returns:
        x >= 0, the shape of the broadcast arguments.
    """
    pos = sd > 0.0
    safe_sd = jnp.where(pos, sd, 1.0)
    a = mean / safe_sd
    # One Phi and one Phi^-1, not both forms computed and one selected: each is a
    # long piecewise polynomial that every program drawing a release compiles. The
    # lower form needs p0 = Phi(-a), a >= 0; the upper one q = Phi(a), a < 0: both
    # are Phi(-|a|), the accurate tail. The sign flip is exact.
    lower = mean >= 0.0
    tail = ndtr(-jnp.abs(a))
    arg = jnp.where(lower, tail + u * (1.0 - tail), (1.0 - u) * jnp.maximum(tail, _TINY))
    x = mean + jnp.where(lower, safe_sd, -safe_sd) * ndtri(jnp.maximum(arg, _TINY))
    return jnp.maximum(jnp.where(pos, x, mean), 0.0)
