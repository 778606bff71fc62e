"""The formats the twin state and a snapshot's cloud can be downloaded in."""

from __future__ import annotations

from enum import StrEnum
from typing import Any

from app.core.export import gltf, laz

GLB_MEDIA_TYPE = gltf.MEDIA_TYPE
LAZ_MEDIA_TYPE = laz.MEDIA_TYPE
JSON_MEDIA_TYPE = "application/json"
PLY_MEDIA_TYPE = "application/octet-stream"


class StateFormat(StrEnum):
    """``json`` (default) or ``glb``: binary glTF 2.0, ``model/gltf-binary``."""

    json = "json"
    glb = "glb"


class CloudFormat(StrEnum):
    """``ply`` (default, binary PLY) or ``laz``: compressed LAS, ``application/vnd.laszip``."""

    ply = "ply"
    laz = "laz"


STATE_MEDIA_TYPES = {JSON_MEDIA_TYPE: StateFormat.json, GLB_MEDIA_TYPE: StateFormat.glb}
CLOUD_MEDIA_TYPES = {PLY_MEDIA_TYPE: CloudFormat.ply, LAZ_MEDIA_TYPE: CloudFormat.laz}
BINARY: dict[str, Any] = {"schema": {"type": "string", "format": "binary"}}
