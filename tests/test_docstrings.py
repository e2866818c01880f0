"""API docs: every public function and class of every ``edgevo_jax`` module has a docstring.

Public = listed in the module's ``__all__``; for a module without ``__all__``, every function
or class defined in that module whose name does not start with ``_``. The public methods and
properties of those classes (defined in the class itself, name without ``_``) are held to the
same rule. ``edgevo_jax.data`` (bundled sequence files, no code) is skipped.
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil
import re
from pathlib import Path
from types import ModuleType

import pytest

import edgevo_jax

SKIP = ("edgevo_jax.data", "edgevo_jax.pipeline", "edgevo_jax.backend")  # data; shims


def _modules() -> list[str]:
    names, todo = [edgevo_jax.__name__], [(edgevo_jax.__path__, edgevo_jax.__name__)]
    while todo:  # walk_packages would import the skipped packages to look inside them
        path, prefix = todo.pop()
        for info in pkgutil.iter_modules(path, prefix=prefix + "."):
            if any(info.name == s or info.name.startswith(s + ".") for s in SKIP):
                continue
            names.append(info.name)
            if info.ispkg:
                todo.append(([str(Path(path[0]) / info.name.rsplit(".", 1)[-1])], info.name))
    return sorted(names)


def _own_doc(obj: object) -> str:
    """The object's own docstring: not one inherited from a base class (inspect.getdoc would
    return that), and not the ``Name(field, ...)`` line that dataclasses and NamedTuple write
    when a class has none."""
    doc = obj.__dict__.get("__doc__") if isinstance(obj, type) else getattr(obj, "__doc__", None)
    doc = (doc or "").strip()
    name = getattr(obj, "__name__", "")
    if isinstance(obj, type) and re.fullmatch(rf"{re.escape(name)}\(.*\)", doc, re.DOTALL):
        return ""
    return doc


def _is_function_or_class(obj: object) -> bool:
    # jax.jit-wrapped functions are not inspect.isfunction, but are callables with a __wrapped__
    return inspect.isclass(obj) or inspect.isfunction(obj) or hasattr(obj, "__wrapped__")


def _public(module: ModuleType) -> list[tuple[str, object]]:
    if hasattr(module, "__all__"):
        items = [(name, getattr(module, name)) for name in module.__all__]
        return [(n, o) for n, o in items if _is_function_or_class(o)]
    return [
        (name, obj) for name, obj in vars(module).items()
        if not name.startswith("_") and _is_function_or_class(obj)
        and getattr(obj, "__module__", None) == module.__name__
    ]


def _members(cls: type) -> list[tuple[str, object]]:
    """Public methods and properties defined in the class body itself (not inherited)."""
    out = []
    for name, value in vars(cls).items():
        if name.startswith("_"):
            continue
        if isinstance(value, property):
            out.append((name, value.fget))
        elif isinstance(value, staticmethod | classmethod):
            out.append((name, value.__func__))
        elif inspect.isfunction(value):
            out.append((name, value))
    return out


MODULES = _modules()


def test_walk_finds_the_package() -> None:
    assert "edgevo_jax.frontend.residuals" in MODULES
    assert "edgevo_jax.datasets.tum" in MODULES
    assert not any(m.startswith("edgevo_jax.data.") or m == "edgevo_jax.data" for m in MODULES)


@pytest.mark.parametrize("name", MODULES)
def test_public_api_has_docstrings(name: str) -> None:
    module = importlib.import_module(name)
    assert _own_doc(module), f"module {name} has no docstring"
    missing = []
    for attr, obj in _public(module):
        if not _own_doc(obj):
            missing.append(f"{name}.{attr}")
        if inspect.isclass(obj) and obj.__module__ == name:  # re-exports: checked at home
            missing += [f"{name}.{attr}.{m}" for m, f in _members(obj) if not _own_doc(f)]
    assert not missing, "public functions / classes without a docstring: " + ", ".join(missing)


def test_checker_sees_missing_docstrings() -> None:
    """The helpers flag what they should: a bare function, a bare dataclass or NamedTuple
    (whose generated ``Name(...)`` line is not documentation), a class that only inherits."""
    import dataclasses
    from typing import NamedTuple

    def bare() -> None:
        pass

    @dataclasses.dataclass
    class BareData:
        x: int

    class BareTuple(NamedTuple):
        x: int

    class Child(ValueError):
        pass

    def documented() -> None:
        """Has one."""

    class WithMethods:
        """Documented class, undocumented members."""

        def method(self) -> None:
            pass

        @property
        def prop(self) -> int:
            return 1

        def _private(self) -> None:
            pass

    for obj in (bare, BareData, BareTuple, Child):
        assert not _own_doc(obj), obj
    assert _own_doc(documented)
    assert [m for m, f in _members(WithMethods) if not _own_doc(f)] == ["method", "prop"]
