"""Read pybind11 signatures from docstrings and check a call against them (for the real_sdk tests).

pybind11 functions have no ``inspect.signature``; their docstrings start each overload with
``name(self: T, a: A, b: B = default) -> R``. :func:`check_call` raises TypeError, as pybind11
would, when no overload takes the given arguments: unknown keywords, too many or missing
positionals, or an enum / bool / int / float / tuple argument of the wrong type.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from types import ModuleType
from typing import Any


@dataclass(frozen=True)
class Param:
    name: str
    type: str
    has_default: bool
    default: str = ""


def _split_top(text: str) -> list[str]:
    """Split ``text`` at commas outside brackets and quotes."""
    parts, depth, quote, cur = [], 0, "", []
    for ch in text:
        if quote:
            quote = "" if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch in "([{<":
            depth += 1
        elif ch in ")]}>":
            depth -= 1
        elif ch == "," and depth == 0:
            parts.append("".join(cur).strip())
            cur = []
            continue
        cur.append(ch)
    if "".join(cur).strip():
        parts.append("".join(cur).strip())
    return parts


def overloads(func: Any, name: str | None = None) -> list[list[Param]]:
    """The parameter lists (without self) of every overload in ``func``'s pybind11 docstring."""
    doc = getattr(func, "__doc__", None) or ""
    name = name or getattr(func, "__name__", "")
    result = []
    for line in doc.splitlines():
        line = re.sub(r"^\s*\d+\.\s*", "", line)
        if not line.startswith(f"{name}("):
            continue
        depth, end = 0, None
        for i, ch in enumerate(line[len(name):], start=len(name)):
            depth += ch == "("
            depth -= ch == ")"
            if depth == 0:
                end = i
                break
        if end is None:
            continue
        params = []
        for part in _split_top(line[len(name) + 1:end]):
            if part in ("*args", "**kwargs"):
                params = None
                break
            head, _, default = part.partition(" = ")
            pname, _, ptype = head.partition(": ")
            params.append(Param(pname.strip(), ptype.strip(), bool(default), default.strip()))
        if params is None:
            continue
        if params and params[0].name == "self":
            params = params[1:]
        result.append(params)
    return result


def _resolve(module: ModuleType, dotted: str) -> Any:
    obj: Any = None
    parts = dotted.split(".")
    if parts[0] == module.__name__.split(".")[0]:
        obj, parts = module, parts[1:]
    else:
        return None
    for p in parts:
        obj = getattr(obj, p, None)
        if obj is None:
            return None
    return obj


def _type_ok(module: ModuleType, tstr: str, value: Any) -> bool:
    t = tstr.replace("typing.", "")
    m = re.fullmatch(r"Optional\[(.*)\]", t) or re.fullmatch(r"(.*) \| None", t)
    if m:
        if value is None:
            return True
        t = m.group(1)
    if t == "bool":
        return isinstance(value, bool)
    if t in ("int", "SupportsInt | SupportsIndex"):
        return isinstance(value, int) and not isinstance(value, bool)
    if t in ("float", "SupportsFloat | SupportsIndex"):
        return isinstance(value, int | float) and not isinstance(value, bool)
    if t == "str":
        return isinstance(value, str)
    if t == "datetime.timedelta":
        import datetime

        return isinstance(value, datetime.timedelta)
    m = re.fullmatch(r"tuple\[(.*)\]", t)
    if m:
        items = _split_top(m.group(1))
        return isinstance(value, tuple | list) and len(value) == len(items) and all(
            _type_ok(module, it, v) for it, v in zip(items, value, strict=True))
    cls = _resolve(module, t)
    if isinstance(cls, type) and hasattr(cls, "__members__"):  # a pybind11 enum: only its members
        return isinstance(value, cls)
    if isinstance(cls, type) and type(value).__module__.split(".")[0] == module.__name__.split(".")[0]:
        return isinstance(value, cls)  # another of the SDK's own classes where this one is wanted
    return True  # Python values for other types (lists, paths, implicit conversions) are not checked here


def check_call(module: ModuleType, func: Any, args: tuple[Any, ...], kwargs: dict[str, Any],
               name: str | None = None) -> list[Param]:
    """The first overload of ``func`` that takes ``args``/``kwargs``; TypeError when none does."""
    sigs = overloads(func, name)
    if not sigs:
        raise AssertionError(f"no pybind11 signature found in the docstring of {name or func!r}")
    for params in sigs:
        if len(args) > len(params):
            continue
        names = [p.name for p in params]
        if any(k not in names[len(args):] for k in kwargs):
            continue
        bound = dict(zip(names, args, strict=False)) | kwargs
        if any(p.name not in bound and not p.has_default for p in params):
            continue
        if all(_type_ok(module, p.type, bound[p.name]) for p in params if p.name in bound):
            return params
    shown = "\n  ".join("(" + ", ".join(f"{p.name}: {p.type}" for p in s) + ")" for s in sigs)
    raise TypeError(f"{name or getattr(func, '__name__', func)}{args!r} {kwargs!r} matches no overload:\n  {shown}")


class Checked:
    """``double`` seen through ``real_cls``: only names the real class has, calls only its signatures take.

    The double supplies the behaviour (a simulated robot); the real SDK class decides what
    may be called and how. Properties are read through (the real class must have them).
    """

    def __init__(self, double: Any, real_cls: type, module: ModuleType) -> None:
        object.__setattr__(self, "_double", double)
        object.__setattr__(self, "_real", real_cls)
        object.__setattr__(self, "_module", module)

    def __getattr__(self, name: str) -> Any:
        real = getattr(self._real, name)  # AttributeError where the real SDK has no such name
        value = getattr(self._double, name)
        if isinstance(real, property) or not callable(value):
            return value

        def call(*args: Any, **kwargs: Any) -> Any:
            check_call(self._module, real, args, kwargs, name)
            return value(*args, **kwargs)

        return call

    def __setattr__(self, name: str, value: Any) -> None:
        real = getattr(self._real, name)
        assert isinstance(real, property) and real.fset is not None, f"{self._real.__name__}.{name} is read-only"
        setattr(self._double, name, value)


def checked_class(double_cls: type, real_cls: type, module: ModuleType) -> Any:
    """A factory like ``real_cls(...)``: checks the constructor call, builds the double, wraps it in Checked."""

    def make(*args: Any, **kwargs: Any) -> Checked:
        check_call(module, real_cls.__init__, args, kwargs, "__init__")
        return Checked(double_cls(*args, **kwargs), real_cls, module)

    return make
