"""Damping-versus-size laws alpha(L), parsed safely from text.

The paper (Sect. 4.1, Table 1) had to lower UDEC's local damping coefficient
with block size: alpha = 0.90, 0.43, 0.30 for L = 0.2, 0.9, 1.8 m. A power law
``0.40*L**-0.5`` gives 0.894, 0.422, 0.298 at those sizes and is the default
law used to give each fragment its own alpha (Sect. 4.2).

Text laws are parsed with ``ast`` into a small expression tree: only numbers,
the name ``L``, ``+ - * / **``, unary minus and the functions ``exp``, ``log``,
``sqrt``, ``minimum``, ``maximum`` are accepted. Nothing is passed to ``eval``.
"""

from __future__ import annotations

import ast
from collections.abc import Callable

import jax.numpy as jnp

__all__ = ["DEFAULT_ALPHA_LAW", "AlphaLawError", "parse_alpha_law"]

DEFAULT_ALPHA_LAW = "0.40*L**-0.5"

_BINOPS = {
    ast.Add: lambda a, b: a + b,
    ast.Sub: lambda a, b: a - b,
    ast.Mult: lambda a, b: a * b,
    ast.Div: lambda a, b: a / b,
    ast.Pow: lambda a, b: a**b,
}
_FUNCS = {"exp": jnp.exp, "log": jnp.log, "sqrt": jnp.sqrt,
          "minimum": jnp.minimum, "maximum": jnp.maximum}


class AlphaLawError(ValueError):
    """A damping law that cannot be parsed or gives alpha outside [0, 1)."""


def _compile(node: ast.AST, text: str) -> Callable:
    if isinstance(node, ast.Expression):
        return _compile(node.body, text)
    if isinstance(node, ast.Constant) and isinstance(node.value, int | float) \
            and not isinstance(node.value, bool):
        value = float(node.value)
        return lambda L: value
    if isinstance(node, ast.Name):
        if node.id != "L":
            raise AlphaLawError(f"alpha law {text!r}: unknown name {node.id!r}; only 'L' "
                                "(fragment side, m) is allowed")
        return lambda L: L
    if isinstance(node, ast.BinOp) and type(node.op) in _BINOPS:
        op = _BINOPS[type(node.op)]
        left, right = _compile(node.left, text), _compile(node.right, text)
        return lambda L: op(left(L), right(L))
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub | ast.UAdd):
        inner = _compile(node.operand, text)
        sign = -1.0 if isinstance(node.op, ast.USub) else 1.0
        return lambda L: sign * inner(L)
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) \
            and node.func.id in _FUNCS and not node.keywords:
        fn = _FUNCS[node.func.id]
        args = [_compile(a, text) for a in node.args]
        return lambda L: fn(*[a(L) for a in args])
    raise AlphaLawError(f"alpha law {text!r}: unsupported syntax "
                        f"{type(node).__name__}; use numbers, L, + - * / ** and "
                        f"{', '.join(_FUNCS)}")


def parse_alpha_law(law: str | Callable) -> Callable:
    """Turn ``"0.40*L**-0.5"`` (or a callable) into a function alpha(L).

    Args:
        law: expression in the fragment side ``L`` (m), or a callable.

    Returns:
        A function mapping L (m, any shape) to alpha (dimensionless).

    Raises:
        AlphaLawError: on syntax outside the whitelist.
    """
    if callable(law):
        return law
    if not isinstance(law, str) or not law.strip():
        raise AlphaLawError("alpha law: expected a non-empty expression in L")
    if len(law) > 200:
        raise AlphaLawError("alpha law: expression longer than 200 characters")
    try:
        tree = ast.parse(law.strip(), mode="eval")
    except SyntaxError as exc:
        raise AlphaLawError(f"alpha law {law!r}: syntax error ({exc.msg})") from None
    return _compile(tree, law)
