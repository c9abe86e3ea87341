"""PEP 562 lazy exports: a package's public names load on first use, so that importing a light
submodule (the CLI parser) does not import JAX, Warp or flax."""

from __future__ import annotations

import importlib
from collections.abc import Callable


def lazy_exports(package: str, exports: dict[str, str], namespace: dict) -> tuple[Callable, Callable]:
    """``(__getattr__, __dir__)`` for ``package``: ``exports`` maps a public name to its module,
    absolute or relative to ``package`` (a leading ``.`` is optional); a loaded name is cached
    in ``namespace`` (the package's ``globals()``)."""

    def __getattr__(name: str):
        mod = exports.get(name)
        if mod is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        path = mod if mod.startswith(package + ".") else f"{package}.{mod.lstrip('.')}"
        value = getattr(importlib.import_module(path), name)
        namespace[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted(set(namespace) | set(exports))

    return __getattr__, __dir__
