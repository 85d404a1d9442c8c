"""Bus backends, registered by name and imported lazily (the registry: :mod:`fieldbus.registry`).

A missing optional dependency raises :class:`BackendUnavailableError` naming
the ``pip install`` that fixes it. Third-party backends register through the
``fieldbus.backends`` entry-point group (name = bus ``type``).
"""

from fieldbus.registry import BACKENDS, backend_class

__all__ = ["BACKENDS", "backend_class"]
