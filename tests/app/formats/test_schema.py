"""openapi/cameras.schema.json: generated from the reader's definitions, fresh, and what it
accepts the reader accepts (sample files of every producer)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import jsonschema
import numpy as np
import pytest

from app.formats import FormatError
from app.formats.cameras import CAMERA_MODELS, cameras_schema, read_cameras, schema_text
from tests.app.formats.test_cameras import PARAMS, PINHOLE, pose

ROOT = Path(__file__).resolve().parents[3]
VALIDATOR = jsonschema.Draft202012Validator(cameras_schema())


def test_the_published_schema_is_fresh_and_valid() -> None:
    assert (ROOT / "openapi" / "cameras.schema.json").read_text() == schema_text()
    jsonschema.Draft202012Validator.check_schema(cameras_schema())


def samples() -> list[dict[str, Any]]:
    """A capture station's shared intrinsics with poses, per-image intrinsics of every
    model (what reconstruct writes), and intrinsics alone."""
    per_image = {
        f"{m.lower()}.jpg": {"model": m, "width": 640, "height": 480, "params": PARAMS[m]}
        for m in CAMERA_MODELS
    }
    return [
        {"intrinsics": PINHOLE, "poses": {"a.jpg": pose(), "b.jpg": np.eye(4).tolist()}},
        {"intrinsics_per_image": per_image, "poses": {name: pose() for name in per_image}},
        {"intrinsics": PINHOLE},
        {"intrinsics": dict(PINHOLE, note="other keys of an intrinsics object are ignored")},
    ]


@pytest.mark.parametrize("doc", samples())
def test_sample_files_validate_and_read(doc: dict[str, Any]) -> None:
    VALIDATOR.validate(doc)
    read_cameras(doc)


@pytest.mark.parametrize(
    "doc",
    [
        {},
        {"intrinsics": dict(PINHOLE, model="FULL_OPENCV")},
        {"intrinsics": dict(PINHOLE, params=[1, 2, 3])},
        {"intrinsics": dict(PINHOLE, width=0)},
        {"intrinsics": PINHOLE, "images": {}},
        {"intrinsics": PINHOLE, "poses": {"a.jpg": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}},
        {"intrinsics_per_image": {}},
    ],
)
def test_what_the_schema_refuses_the_reader_refuses(doc: dict[str, Any]) -> None:
    assert not VALIDATOR.is_valid(doc)
    with pytest.raises(FormatError):
        read_cameras(doc)


def test_the_synthetic_captures_cameras_validate(tmp_path: Path) -> None:
    """What ``synth`` writes for a capture station's upload."""
    from workers.pipeline.synth.cameras import cameras_json_intrinsics
    from workers.pipeline.synth.options import CameraOptions

    doc = {"intrinsics": cameras_json_intrinsics(CameraOptions()).to_json()}
    VALIDATOR.validate(json.loads(json.dumps(doc)))
