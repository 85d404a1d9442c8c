"""Drive maps: YAML -> validated model -> bit layout -> numpy process images."""

from fieldbus.core.pdo.load import drive_map_from_text, load_drive_map, parse_drive_map
from fieldbus.core.pdo.model import (
    CanopenConfig,
    CanopenPdo,
    Channel,
    Direction,
    DriveMap,
    EthercatConfig,
    Pdo,
    SdoWrite,
    SyncManager,
)

__all__ = [
    "CanopenConfig",
    "CanopenPdo",
    "Channel",
    "Direction",
    "DriveMap",
    "EthercatConfig",
    "Pdo",
    "SdoWrite",
    "SyncManager",
    "drive_map_from_text",
    "load_drive_map",
    "parse_drive_map",
]
