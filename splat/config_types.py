"""Type checks of config dataclasses against their defaults: a field set to a value of another type
(a string for an int from a hand-edited config file, 10.5 iterations from Python) is named with its
class and field before any work, not met as a TypeError deep in a run (or, for a float where an int
is due, trained with silently)."""

from __future__ import annotations

import dataclasses
import numbers
import re
from typing import Any


def typed(cls, f: dataclasses.Field, value: Any) -> Any:
    """``value`` checked against the type of field ``f``'s default (bool, int, float, str, tuple; a float
    field takes an int): a config file edited by hand names the field, not a TypeError deep in a run."""
    default = f.default
    if default is dataclasses.MISSING or default is None or value is None:
        return value
    kinds = {bool: (bool,), int: (numbers.Integral,), float: (numbers.Real,), str: (str,), tuple: (tuple,)}
    want, kind = kinds.get(type(default)), type(default).__name__
    if isinstance(default, str) and {"int", "Literal"} <= set(re.findall(r"\w+", str(f.type))):  # a count or a word
        want, kind = (numbers.Integral, str), f"int or {default!r}"
    ok = want is not None and isinstance(value, want) and not (isinstance(value, bool) and type(default) is not bool)
    if want is not None and not ok:
        raise ValueError(f"{cls.__name__}.{f.name} must be {kind} (like its default "
                         f"{default!r}), got {value!r}")
    if isinstance(default, tuple) and default and all(isinstance(d, numbers.Real) and not isinstance(d, bool)
                                                      for d in default):
        bad = [v for v in value if isinstance(v, bool) or not isinstance(v, numbers.Real)]
        if bad:  # a YAML `background: [a, b, c]` failed as a TypeError in the first check that added them
            raise ValueError(f"{cls.__name__}.{f.name} must hold numbers (like its default {default!r}), got {value!r}")
    return float(value) if type(default) is float else value


def check_types(cfg: Any) -> None:
    """Every field of the dataclass ``cfg``, and of the dataclasses it holds, checked with :func:`typed`
    (a list is taken where a tuple is due, as from Python one would write it). Raises ValueError."""
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if f.default_factory is not dataclasses.MISSING and dataclasses.is_dataclass(f.default_factory):
            if not dataclasses.is_dataclass(value):  # `loss: null` in a config file
                raise ValueError(f"{type(cfg).__name__}.{f.name} must be a {f.default_factory.__name__} section, "
                                 f"got {value!r}")
        if dataclasses.is_dataclass(value):
            check_types(value)
        else:  # a list where a tuple is due, as one writes it from Python: its elements still checked
            typed(type(cfg), f, tuple(value) if isinstance(value, list) and isinstance(f.default, tuple) else value)
