"""Bus backends, declared in :mod:`fieldbus.registry` and imported lazily, when a bus opens.

A missing optional dependency raises :class:`BackendUnavailableError` naming
the ``pip install`` that fixes it. Third-party backends register through the
``fieldbus.backends`` entry-point group (name = bus ``type``).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from fieldbus.errors import BackendUnavailableError
from fieldbus.registry import BACKENDS, bus_type_names, registered

if TYPE_CHECKING:
    from fieldbus.backends.base import Backend

__all__ = ["BACKENDS", "backend_class"]


def backend_class(kind: str) -> type[Backend]:
    """The backend class for bus type ``kind``."""
    if kind in BACKENDS:
        module_name, cls_name, extra = BACKENDS[kind]
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name and exc.name.startswith("fieldbus"):
                raise BackendUnavailableError(f"the {kind} backend is not built yet ({exc.name})") from None
            hint = f"pip install 'fieldbus[{extra}]'" if extra else "reinstall fieldbus"
            raise BackendUnavailableError(
                f"the {kind} backend needs the Python package '{exc.name}': {hint}"
            ) from None
        cls: type[Backend] = getattr(module, cls_name)
        return cls
    ep = registered().get(kind)
    if ep is not None:
        loaded: type[Backend] = ep.load()
        return loaded
    raise BackendUnavailableError(f"no backend for bus type '{kind}' (known: {', '.join(bus_type_names())})")
