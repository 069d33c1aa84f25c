"""Old public names kept for one release: each is served with a ``DeprecationWarning`` that names
its new home."""

from __future__ import annotations

import importlib
import warnings
from typing import Any, Callable

#: old attribute -> (new module, new attribute; ``None``: the module itself)
Aliases = dict[str, tuple[str, "str | None"]]


def resolve(module: str, name: str, aliases: Aliases, *, stacklevel: int = 3) -> Any:
    """The object the old name ``module.name`` stands for, after a ``DeprecationWarning``."""
    new_module, new_name = aliases[name]
    new = new_module if new_name is None else f"{new_module}.{new_name}"
    warnings.warn(
        f"{module}.{name} is deprecated and will be removed in the next release: use {new}",
        DeprecationWarning,
        stacklevel=stacklevel,
    )
    value = importlib.import_module(new_module)
    return value if new_name is None else getattr(value, new_name)


def module_getattr(module: str, aliases: Aliases) -> Callable[[str], Any]:
    """A module ``__getattr__`` (PEP 562) that serves the deprecated ``aliases``."""

    def __getattr__(name: str) -> Any:
        if name not in aliases:
            raise AttributeError(f"module {module!r} has no attribute {name!r}")
        return resolve(module, name, aliases)

    return __getattr__
