"""Lazy package exports: public names are imported on first use.

Packages whose modules pull heavy libraries (OpenCV, gtsam, pymavlink, pycolmap) export
their API through :func:`lazy_exports`, so ``import skyfix.<package>`` and ``skyfix --help``
stay fast::

    __getattr__, __dir__, __all__ = lazy_exports(__name__, {"FusionEngine": "engine", ...})

A module name without a dot is a submodule of the package; a dotted one is absolute.
"""

from __future__ import annotations

import importlib
import sys
import types
from collections.abc import Callable
from typing import Any


class _ExportNamedLikeItsModule(types.ModuleType):
    """A package that exports a function named like the submodule defining it.

    Importing ``skyfix.thermal.geolocate`` makes the import system bind the submodule to the
    package attribute ``geolocate``; an eager ``from .geolocate import geolocate`` rebinds the
    function afterwards, a lazy export would not. Binding the submodule's namesake instead keeps
    ``from skyfix.thermal import geolocate`` the function whatever was imported first.
    """

    _shadowed: frozenset[str] = frozenset()

    def __setattr__(self, name: str, value: Any) -> None:
        if (name in self._shadowed and isinstance(value, types.ModuleType)
                and value.__name__ == f"{self.__name__}.{name}"):
            value = getattr(value, name)
        super().__setattr__(name, value)


def lazy_exports(package: str, exports: dict[str, str]
                 ) -> tuple[Callable[[str], Any], Callable[[], list[str]], list[str]]:
    """(``__getattr__``, ``__dir__``, ``__all__``) for ``package`` exporting ``exports`` (name -> module)."""
    names = sorted(exports)
    shadowed = frozenset(n for n, m in exports.items() if m == n)
    if shadowed:
        sys.modules[package].__class__ = type(
            "Package", (_ExportNamedLikeItsModule,), {"_shadowed": shadowed})

    def __getattr__(name: str) -> Any:
        module = exports.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module if "." in module else f"{package}.{module}"), name)
        setattr(sys.modules[package], name, value)  # later look-ups skip this function
        return value

    def __dir__() -> list[str]:
        return names

    return __getattr__, __dir__, names
