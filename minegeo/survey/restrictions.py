"""Restrictions ``g(x) = 0`` of a survey network: a safe expression compiler and their constraint rows.

A restriction is written with the coordinates ``x<pt>``, ``y<pt>``, ``z<pt>`` of the network's
points, numbers, ``+ - * / ^`` and parentheses (e.g. ``(xB - xA)^2 + (yB - yA)^2 - 100^2``). It
is parsed to a Python AST that may hold nothing else (no names, calls or attributes), and
evaluated with no builtins. :func:`minegeo.survey.adjust_network` adds the linearised
restrictions as constraints ``C·Δ = c`` of the Gauss–Markov adjustment.
"""

from __future__ import annotations

import ast
import re

import numpy as np

from minegeo.errors import InputError

__all__ = ["compile_restriction", "restriction_constraints"]

_ALLOWED_AST = (
    ast.Expression,
    ast.BinOp,
    ast.UnaryOp,
    ast.Constant,
    ast.Name,
    ast.Load,
    ast.Add,
    ast.Sub,
    ast.Mult,
    ast.Div,
    ast.Pow,
    ast.USub,
    ast.UAdd,
)


def compile_restriction(expr: str, points):
    """Compile ``g(x) = 0`` written with x<pt>/y<pt>/z<pt>, numbers, + − * / ^ and parentheses.

    Parameters
    ----------
    expr : str
        The restriction as written in the network file.
    points : container of str
        The network's point names.

    Returns
    -------
    (code, dict)
        The compiled expression and its symbols ``{"_v0": (point, axis), ...}``.

    Raises
    ------
    InputError
        Unknown symbol, invalid syntax, or anything but numbers, coordinates and arithmetic.
    """
    text = expr.replace("^", "**")
    names = {}

    def repl(m):
        tok = m.group(0)
        if tok[0] in "xyz" and tok[1:] in points:
            sym = f"_v{len(names)}"
            names[sym] = (tok[1:], tok[0])
            return sym
        raise InputError(f"restriction {expr!r}: unknown symbol {tok!r} (use x<point>, y<point>, z<point>)")

    text = re.sub(r"[A-Za-z_][A-Za-z0-9_#@-]*", repl, text)
    try:
        tree = ast.parse(text, mode="eval")
    except SyntaxError:
        raise InputError(f"restriction {expr!r} is not a valid expression") from None
    for node in ast.walk(tree):
        if not isinstance(node, _ALLOWED_AST):
            raise InputError(f"restriction {expr!r}: only numbers, coordinates, + - * / ^ and () are allowed")
    return compile(tree, "<restriction>", "eval"), names


def restriction_constraints(model):
    """Constraint function ``x -> (C, c)`` of the network's restrictions, for :func:`minegeo.survey.adjust`.

    Parameters
    ----------
    model
        The network's parameter model (:class:`minegeo.survey.network._Model`): its ``net``
        (points, restrictions), ``coord(x, point, axis)`` (origin-reduced), ``origin`` and
        ``index`` ``{(point, axis): unknown}``.

    Returns
    -------
    callable
        ``fun(x) -> (C, c)`` with one row per restriction: ``c = −g(x)`` and ``C = ∂g/∂x`` by
        central differences (step ``1e-6·max(1, |coordinate|)``) over the adjusted coordinates.
    """
    exprs = [compile_restriction(e, model.net.points) for e in model.net.restrictions]

    def fun(x):
        C = np.zeros((len(exprs), x.size))
        c = np.zeros(len(exprs))
        for k, (code, syms) in enumerate(exprs):
            env = {s: model.coord(x, p, a) + model.origin.get(a, 0.0) for s, (p, a) in syms.items()}
            g0 = float(eval(code, {"__builtins__": {}}, env))  # noqa: S307 - AST-whitelisted
            c[k] = -g0
            for s, (p, a) in syms.items():
                i = model.index.get((p, a))
                if i is None:
                    continue
                h = 1e-6 * max(1.0, abs(env[s]))
                e1 = dict(env)
                e1[s] = env[s] + h
                e2 = dict(env)
                e2[s] = env[s] - h
                C[k, i] = (
                    eval(code, {"__builtins__": {}}, e1) - eval(code, {"__builtins__": {}}, e2)
                ) / (2 * h)  # noqa: S307
        return C, c

    return fun
