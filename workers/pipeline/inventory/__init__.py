"""Inventory of a reconstructed snapshot: every library object it shows, with its pose.

``supports`` finds the floor, table tops and shelf boards; ``stage`` segments what stands
on them, identifies each segment as the compare stage does and poses it as the pose stage
does; ``options`` the settings; ``cli`` the command line.
"""

from workers.pipeline.inventory.options import (
    INVENTORY_PRESETS,
    InventoryOptions,
    inventory_options_from_json,
)
from workers.pipeline.inventory.stage import (
    InventoryObject,
    InventoryResult,
    take_inventory,
)
from workers.pipeline.inventory.supports import Support, find_supports, standing_heights

__all__ = [
    "INVENTORY_PRESETS",
    "InventoryObject",
    "InventoryOptions",
    "InventoryResult",
    "Support",
    "find_supports",
    "inventory_options_from_json",
    "standing_heights",
    "take_inventory",
]
