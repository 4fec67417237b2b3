"""A tiny, safe interpreter for node-selection expressions (``where = "x < 1e-9"``).

The expression is parsed with :mod:`ast` and evaluated node by node (never ``eval``):
numbers, arithmetic, comparisons (chained too), ``&``/``|``/``^``/``~``/``and``/``or``/
``not``, integer indexing and slicing (``X[:, 0]``), the names ``X`` (rest positions
``(n, dim)``), ``x``, ``y``, ``z`` (its columns) and ``pi``, and calls of a few NumPy
functions (``abs sqrt hypot minimum maximum sin cos arctan2 isclose logical_and
logical_or logical_not``, also spelled ``np.abs`` …; keywords ``atol``/``rtol`` only).
Anything else (attributes, other names or calls, strings, lambdas, …) is refused, and so
are constants beyond float64 (``1e999``) and constant arithmetic that overflows
(``9 ** 9 ** 9``, folded when the expression is checked); floating-point errors while
evaluating (overflow, division by zero, ``sqrt`` of a negative number) are errors too.
"""

from __future__ import annotations

import ast
import math

import numpy as np

__all__ = ["WhereError", "check_where", "where_mask"]


_WHERE_FUNCS = {
    name: getattr(np, name)
    for name in (
        "abs",
        "sqrt",
        "hypot",
        "minimum",
        "maximum",
        "sin",
        "cos",
        "arctan2",
        "isclose",
        "logical_and",
        "logical_or",
        "logical_not",
    )
}
_WHERE_KW = ("atol", "rtol")
_BINOPS = {
    ast.Add: np.add,
    ast.Sub: np.subtract,
    ast.Mult: np.multiply,
    ast.Div: np.true_divide,
    ast.FloorDiv: np.floor_divide,
    ast.Mod: np.mod,
    ast.Pow: np.power,
    ast.BitAnd: np.logical_and,
    ast.BitOr: np.logical_or,
    ast.BitXor: np.logical_xor,
}
_CMPOPS = {
    ast.Lt: np.less,
    ast.LtE: np.less_equal,
    ast.Gt: np.greater,
    ast.GtE: np.greater_equal,
    ast.Eq: np.equal,
    ast.NotEq: np.not_equal,
}


class WhereError(ValueError):
    """An expression that is not allowed or cannot be evaluated."""


def _constant(node: ast.Constant) -> float:
    """A numeric literal as a finite float (``1e999`` and huge integers are refused)."""
    if isinstance(node.value, bool) or not isinstance(node.value, (int, float)):
        raise WhereError(f"constant {node.value!r} is not a number")
    try:
        value = float(node.value)
    except OverflowError:
        value = math.inf
    if not math.isfinite(value):
        text = f"{node.value} " if isinstance(node.value, int) else ""
        short = text if len(text) <= 24 else f"{text[:12]}... ({len(text) - 1} digits) "
        raise WhereError(f"a constant {short}is beyond the range of float64 (1.8e308)")
    return value


def _where_eval(node, env):
    """Evaluate an allowed AST node; ``env`` is None for a structural check only."""
    ev = lambda n: _where_eval(n, env)  # noqa: E731
    if isinstance(node, ast.Expression):
        return ev(node.body)
    if isinstance(node, ast.Constant):
        return _constant(node)
    if isinstance(node, ast.Name):
        if node.id == "pi":
            return math.pi
        if node.id not in ("X", "x", "y", "z"):
            raise WhereError(f"unknown name {node.id!r} (use X, x, y, z, pi)")
        if env is None:
            return None
        if node.id not in env:
            raise WhereError(f"{node.id!r} is not defined for a {env['X'].shape[1]}D mesh")
        return env[node.id]
    if isinstance(node, ast.BinOp) and type(node.op) in _BINOPS:
        a, b = ev(node.left), ev(node.right)
        if env is None and not (isinstance(a, float) and isinstance(b, float)):
            return None  # the structural check folds constants only
        return _checked(node, _BINOPS[type(node.op)], a, b)
    if isinstance(node, ast.UnaryOp):
        a = ev(node.operand)
        if env is None:
            return -a if isinstance(a, float) and isinstance(node.op, ast.USub) else None
        if isinstance(node.op, ast.USub):
            return np.negative(a)
        if isinstance(node.op, ast.UAdd):
            return a
        if isinstance(node.op, (ast.Invert, ast.Not)):
            return np.logical_not(a)
    if isinstance(node, ast.BoolOp):
        vals = [ev(n) for n in node.values]
        if env is None:
            return None
        f = np.logical_and if isinstance(node.op, ast.And) else np.logical_or
        out = vals[0]
        for val in vals[1:]:
            out = f(out, val)
        return out
    if isinstance(node, ast.Compare) and all(type(o) in _CMPOPS for o in node.ops):
        vals = [ev(node.left)] + [ev(n) for n in node.comparators]
        if env is None:
            return None
        out = True
        for op, a, b in zip(node.ops, vals[:-1], vals[1:], strict=True):
            out = np.logical_and(out, _CMPOPS[type(op)](a, b))
        return out
    if isinstance(node, ast.Call):
        f = node.func
        if isinstance(f, ast.Attribute) and isinstance(f.value, ast.Name) and f.value.id == "np":
            fname = f.attr
        elif isinstance(f, ast.Name):
            fname = f.id
        else:
            raise WhereError("only calls of the allowed NumPy functions are allowed")
        if fname not in _WHERE_FUNCS:
            raise WhereError(
                f"function {fname!r} is not allowed (allowed: {', '.join(_WHERE_FUNCS)})"
            )
        args = [ev(a) for a in node.args]
        kw = {}
        for k in node.keywords:
            if k.arg not in _WHERE_KW:
                raise WhereError(f"keyword {k.arg!r} is not allowed")
            kw[k.arg] = ev(k.value)
        return None if env is None else _WHERE_FUNCS[fname](*args, **kw)
    if isinstance(node, ast.Subscript):
        base = ev(node.value)
        index = _where_index(node.slice, env)
        return None if env is None else base[index]
    raise WhereError(f"{type(node).__name__} is not allowed in a selection expression")


def _checked(node, op, a, b):
    """``op(a, b)`` with floating-point errors (overflow, 0/0, x/0) raised as WhereError
    naming the subexpression; a constant result must be a finite float64."""
    try:
        with np.errstate(over="raise", invalid="raise", divide="raise"):
            out = op(np.float64(a), np.float64(b)) if isinstance(a, float) else op(a, b)
    except (FloatingPointError, ZeroDivisionError, OverflowError) as e:
        what = str(e).removeprefix("FloatingPointError: ") or type(e).__name__
        raise WhereError(f"{ast.unparse(node)}: {what} (refusing non-finite values)") from None
    if isinstance(a, float) and isinstance(b, float):
        if isinstance(out, (np.bool_, bool)):
            return out
        out = float(out)
        if not math.isfinite(out):
            raise WhereError(f"{ast.unparse(node)} is beyond the range of float64 (1.8e308)")
    return out


def _where_index(node, env):
    if isinstance(node, ast.Tuple):
        return tuple(_where_index(e, env) for e in node.elts)
    if isinstance(node, ast.Slice):
        parts = [None if p is None else _where_int(p) for p in (node.lower, node.upper, node.step)]
        return slice(*parts)
    return _where_int(node)


def _where_int(node):
    neg = isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub)
    n = node.operand if neg else node
    if not (isinstance(n, ast.Constant) and type(n.value) is int):
        raise WhereError("indices must be integer constants or slices")
    return -n.value if neg else n.value


def where_mask(expr: str, X: np.ndarray) -> np.ndarray:
    """Evaluate a selection expression on rest positions ``X`` ``(n, dim)`` → ``(n,)`` bool.

    Floating-point errors (overflow, division by zero, invalid values such as
    ``sqrt(-1)``) raise :class:`WhereError` instead of warning and selecting by ``inf`` or
    ``nan``.
    """
    tree = check_where(expr)
    X = np.asarray(X, dtype=float)
    env = {"X": X, **{c: X[:, i] for i, c in enumerate("xyz"[: X.shape[1]])}}
    try:
        with np.errstate(over="raise", invalid="raise", divide="raise"):
            value = _where_eval(tree, env)
    except FloatingPointError as e:  # e.g. sqrt(x - 1) at x < 1
        raise WhereError(f"{e} (refusing non-finite values)") from None
    out = np.broadcast_to(np.asarray(value), (X.shape[0],))
    if out.dtype != bool:
        raise WhereError(f"the expression gives {out.dtype} values, not a boolean mask")
    return out


def check_where(expr: str) -> ast.Expression:
    """Parse ``expr`` and check that it uses only allowed constructs (no evaluation).

    Raises:
        WhereError: a syntax error or a construct that is not allowed.
    """
    try:
        tree = ast.parse(expr, mode="eval")
    except SyntaxError as e:
        raise WhereError(f"invalid expression ({e.msg})") from None
    _where_eval(tree, None)
    return tree
