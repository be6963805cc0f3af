"""Frozen parameter groups whose rules are declared once, in the fields' metadata.

A parameter dataclass declares each field's rule where the field is defined, with one of the
helpers below (they return :func:`dataclasses.field` objects), and calls :func:`validate` from its
``__post_init__``. The same rule then serves three readers:

* the dataclass itself (:func:`validate` raises :class:`~minegeo.errors.InputError` naming the
  field, its rule and the value given);
* the command line (:func:`arg_type` builds the option's argparse ``type=`` from the field's rule,
  refusing a value with the same message, before any work);
* a configuration file (``--config FILE`` reads each key through the option's ``type=``,
  :mod:`minegeo.cli._config`).

Rules (``meta`` is the field's metadata):

* :func:`bounded`: a finite number (or a whole number with ``integer=True``) within the bounds
  ``ge`` (>=), ``gt`` (>), ``le`` (<=), ``lt`` (<); ``optional=True`` also accepts ``None``;
* :func:`one_of`: one of a fixed set of strings (the arguments of a ``typing.Literal``);
* :func:`flag`: ``True`` or ``False`` (a NumPy boolean too);
* :func:`group`: an instance of a given parameter class (a nested group); ``optional=True`` also
  accepts ``None`` (an optional stage that is off).

Example::

    @dataclass(frozen=True)
    class IcpParams:
        max_iterations: int = bounded(30, ge=0, integer=True)
        method: Literal["a", "b"] = one_of("a", Literal["a", "b"])

        def __post_init__(self):
            validate(self)

    parser.add_argument("--icp-iterations", type=arg_type(IcpParams, "max_iterations"))
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import math
import numbers
import typing
from typing import Any

import numpy as np

from minegeo.errors import InputError

__all__ = ["bounded", "one_of", "flag", "group", "validate", "check_field", "rule_text", "arg_type", "field_rule"]

_KEY = "minegeo_rule"


def _field(default, default_factory, rule: dict) -> Any:
    kw: dict[str, Any] = {"metadata": {_KEY: rule}}
    if default_factory is not dataclasses.MISSING:
        kw["default_factory"] = default_factory
    elif default is not dataclasses.MISSING:
        kw["default"] = default
    return dataclasses.field(**kw)


def bounded(default=dataclasses.MISSING, *, ge: float | None = None, gt: float | None = None,
            le: float | None = None, lt: float | None = None, integer: bool = False,
            optional: bool = False) -> Any:
    """A numeric field: a finite number (a whole number when ``integer``) within the given bounds.

    Parameters
    ----------
    default : number or None
        The field's default.
    ge, gt : float, optional
        Lower bound, inclusive (``ge``) or exclusive (``gt``); at most one of them.
    le, lt : float, optional
        Upper bound, inclusive (``le``) or exclusive (``lt``); at most one of them.
    integer : bool
        The value must be a whole number (``int`` or a NumPy integer; ``bool`` is refused).
    optional : bool
        ``None`` is accepted as well (the feature is off).
    """
    if ge is not None and gt is not None or le is not None and lt is not None:
        raise TypeError("bounded: give at most one lower bound (ge or gt) and one upper bound (le or lt)")
    rule = {"kind": "number", "ge": ge, "gt": gt, "le": le, "lt": lt, "integer": bool(integer),
            "optional": bool(optional)}
    return _field(default, dataclasses.MISSING, rule)


def one_of(default, choices) -> Any:
    """A string field taking one of ``choices`` (a ``typing.Literal[...]`` or a tuple of strings)."""
    args = typing.get_args(choices) if typing.get_origin(choices) is typing.Literal else tuple(choices)
    if default not in args:
        raise TypeError(f"one_of: default {default!r} is not one of {args}")
    return _field(default, dataclasses.MISSING, {"kind": "choice", "choices": args})


def flag(default: bool) -> Any:
    """A boolean field (``True`` or ``False``; a NumPy boolean too)."""
    return _field(bool(default), dataclasses.MISSING, {"kind": "flag"})


def group(cls: type, default_factory=dataclasses.MISSING, *, default=dataclasses.MISSING,
          optional: bool = False) -> Any:
    """A nested parameter group: an instance of ``cls`` (``None`` too when ``optional``: the stage is off).

    ``default_factory`` (or ``default`` for ``None``) gives the field's default; without either the
    default is ``cls()``.
    """
    if default_factory is dataclasses.MISSING and default is dataclasses.MISSING:
        default_factory = cls
    return _field(default, default_factory, {"kind": "group", "cls": cls, "optional": bool(optional)})


def field_rule(cls: type, name: str) -> dict:
    """The rule declared for field ``name`` of the dataclass ``cls`` (a copy of its metadata entry)."""
    for f in dataclasses.fields(cls):
        if f.name == name:
            if _KEY not in f.metadata:
                raise KeyError(f"{cls.__name__}.{name} declares no rule")
            return dict(f.metadata[_KEY])
    raise KeyError(f"{cls.__name__} has no field {name!r}")


def _num(x: float) -> str:
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else f"{x:g}"  # 10**9, not 1e+09


def rule_text(rule: dict, none_text: str = "None") -> str:
    """What the rule accepts, in words: ``"a number > 0"``, ``"a whole number in [1, 21]"``,
    ``"one of ('a', 'b')"``; an optional field adds ``" or None"`` (``none_text``)."""
    kind = rule["kind"]
    if kind == "choice":
        return f"one of {rule['choices']}"
    if kind == "flag":
        return "True or False"
    if kind == "group":
        text = f"a {rule['cls'].__name__}"
    else:
        what = "a whole number" if rule["integer"] else "a finite number"
        lo = ("[", rule["ge"]) if rule["ge"] is not None else ("(", rule["gt"]) if rule["gt"] is not None else None
        hi = ("]", rule["le"]) if rule["le"] is not None else (")", rule["lt"]) if rule["lt"] is not None else None
        if lo and hi:
            text = f"{what} in {lo[0]}{_num(lo[1])}, {_num(hi[1])}{hi[0]}"
        elif lo:
            text = f"{what} {'>=' if lo[0] == '[' else '>'} {_num(lo[1])}"
        elif hi:
            text = f"{what} {'<=' if hi[0] == ']' else '<'} {_num(hi[1])}"
        else:
            text = what
    return f"{text} or {none_text}" if rule.get("optional") else text


def _accepts(rule: dict, value) -> bool:
    kind = rule["kind"]
    if value is None:
        return bool(rule.get("optional"))
    if kind == "choice":
        return isinstance(value, str) and value in rule["choices"]
    if kind == "flag":
        return isinstance(value, (bool, np.bool_))
    if kind == "group":
        return isinstance(value, rule["cls"])
    if isinstance(value, (bool, np.bool_)):
        return False
    if rule["integer"]:
        if not isinstance(value, numbers.Integral):
            return False
    elif not isinstance(value, numbers.Real) or not math.isfinite(float(value)):
        return False
    v = float(value) if not rule["integer"] else int(value)
    return ((rule["ge"] is None or v >= rule["ge"]) and (rule["gt"] is None or v > rule["gt"])
            and (rule["le"] is None or v <= rule["le"]) and (rule["lt"] is None or v < rule["lt"]))


def _message(where: str, rule: dict, value, none_text: str = "None") -> str:
    return f"{where} must be {rule_text(rule, none_text)}, got {value!r}"


def check_field(cls: type, name: str, value) -> None:
    """Check one value against the rule of field ``name`` of ``cls``.

    Raises
    ------
    InputError
        ``"<Class>.<name> must be <rule>, got <value>"``.
    """
    rule = field_rule(cls, name)
    if not _accepts(rule, value):
        raise InputError(_message(f"{cls.__name__}.{name}", rule, value))


def validate(obj) -> None:
    """Check every field of the dataclass instance ``obj`` that declares a rule (fields without one
    are left to the class).

    Raises
    ------
    InputError
        The first field whose value its rule refuses: ``"<Class>.<field> must be <rule>, got <value>"``.
    """
    cls = type(obj)
    for f in dataclasses.fields(obj):
        rule = f.metadata.get(_KEY)
        if rule is not None and not _accepts(rule, getattr(obj, f.name)):
            raise InputError(_message(f"{cls.__name__}.{f.name}", rule, getattr(obj, f.name)))


class _ArgType:
    """An argparse ``type=`` checking a value with a field's rule (:func:`arg_type`); the class is
    imported on first use, so that building a parser does not import the module defining it."""

    def __init__(self, cls: type | str, name: str, off: float | None, le: float | None = None):
        self._cls, self._name, self._off, self._le = cls, name, off, le

    def _rule(self) -> tuple[dict, str, str]:
        cls = self._cls
        if isinstance(cls, str):
            module, _, qual = cls.partition(":")
            cls = getattr(importlib.import_module(module), qual)
        rule = field_rule(cls, self._name)
        if rule["kind"] != "number":
            raise TypeError(f"arg_type: {cls.__name__}.{self._name} is not a numeric field")
        none_text = f"{_num(self._off)} (off)" if self._off is not None else "None"
        return rule, f"{cls.__name__}.{self._name}", none_text

    def _option_rule(self, rule: dict) -> dict:
        """The field's rule with the option's own upper bound ``le`` (where it is the tighter one)."""
        if self._le is None or any(rule[k] is not None and rule[k] <= self._le for k in ("le", "lt")):
            return rule
        return {**rule, "le": self._le, "lt": None}

    @property
    def __name__(self) -> str:  # the type's description in --dump-config and argparse messages
        rule, _, none_text = self._rule()
        return rule_text({**self._option_rule(rule), "optional": self._off is not None}, none_text)

    def __call__(self, text: str):
        rule, where, none_text = self._rule()
        try:
            value = int(str(text).strip(), 10) if rule["integer"] else float(text)
        except (TypeError, ValueError):
            raise argparse.ArgumentTypeError(
                f"{text!r} is not {'a whole number' if rule['integer'] else 'a number'}") from None
        if self._off is not None and value == self._off:
            return value
        option_rule = {**self._option_rule(rule), "optional": False}
        limit = "" if option_rule == {**rule, "optional": False} else \
            f"; this option takes {rule_text(option_rule)}"
        if not _accepts({**rule, "optional": False}, value):
            raise argparse.ArgumentTypeError(
                _message(where, {**rule, "optional": self._off is not None}, value, none_text) + limit)
        if not _accepts(option_rule, value):
            raise argparse.ArgumentTypeError(
                f"this option takes {rule_text(option_rule)}, got {value!r} ({where} itself takes "
                f"{rule_text({**rule, 'optional': False})})")
        return value


def arg_type(cls: type | str, name: str, *, off: float | None = None, le: float | None = None) -> _ArgType:
    """The argparse ``type=`` of a command-line option that sets field ``name`` of ``cls``.

    The text is parsed as a whole number (an ``integer`` rule) or a float, then checked with the
    field's own rule: a refused value raises :class:`argparse.ArgumentTypeError` with the message
    :func:`validate` gives for the same value (exit status 2 before any work; a ``--config`` file's
    value goes through the same ``type=``).

    Parameters
    ----------
    cls : type or str
        The parameter dataclass, or ``"module:Class"`` (imported when the option is first parsed:
        a parser can be built without importing the module).
    name : str
        Its field (a :func:`bounded` one).
    off : float, optional
        For an optional field: the option value that means ``None`` (e.g. 0 = off). The parsed value
        is returned as given (the caller maps it to ``None``); the message then reads
        ``"... or 0 (off)"`` where the dataclass's reads ``"... or None"``. Without ``off`` an
        option cannot give ``None``, and its message leaves the ``"or None"`` out.
    le : float, optional
        The option's own inclusive upper bound, for an option that deliberately takes less than
        the field (a count capped at :data:`minegeo.cli._argtypes.MAX_COUNT`, an angle that the
        option's meaning limits): a value the field's rule refuses gets the field's message as
        above followed by ``"; this option takes <its rule>"``; a value within the field's rule
        but above ``le`` is refused with a message giving both rules. Ignored where the field's
        own upper bound is already at most ``le``.
    """
    return _ArgType(cls, name, off, le)
