"""The bus as a service over Cyclone DDS (``fieldbus serve``), with ROS 2 type and topic names.

Needs the optional extra ``dds`` (``pip install 'fieldbus[dds]'``, the
``cyclonedds`` package). See ``docs/dds.md`` for the topics, the messages and
the safety rules across the process boundary; :mod:`fieldbus.remote` is the
client.
"""

from __future__ import annotations

from fieldbus.errors import BackendUnavailableError


def require() -> None:
    """Raise :class:`BackendUnavailableError` (what to install) when ``cyclonedds`` is missing."""
    try:
        import cyclonedds.domain  # noqa: F401
    except ImportError:
        raise BackendUnavailableError(
            "serving over DDS needs the cyclonedds package: pip install 'fieldbus[dds]'"
        ) from None
