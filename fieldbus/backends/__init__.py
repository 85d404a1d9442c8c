"""Bus backends, registered by name and imported lazily.

A missing optional dependency raises :class:`BackendUnavailableError` naming
the ``pip install`` that fixes it. Third-party backends register through the
``fieldbus.backends`` entry-point group (name = bus ``type``).
"""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points
from typing import TYPE_CHECKING

from fieldbus.errors import BackendUnavailableError

if TYPE_CHECKING:
    from fieldbus.backends.base import Backend

# bus type -> (module, class, the extra that provides its dependencies)
BACKENDS: dict[str, tuple[str, str, str | None]] = {
    "sim": ("fieldbus.backends.sim", "SimBackend", "ethercat"),  # the ethercat backend in process
    "ethercat": ("fieldbus.backends.ethercat", "EthercatBackend", "ethercat"),
    "canopen": ("fieldbus.backends.canopen", "CanopenBackend", "can"),
    "rawcan": ("fieldbus.backends.rawcan", "RawCanBackend", "can"),
}


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
    for ep in entry_points(group="fieldbus.backends"):
        if ep.name == kind:
            loaded: type[Backend] = ep.load()
            return loaded
    raise BackendUnavailableError(f"no backend for bus type '{kind}' (known: {', '.join(BACKENDS)})")
