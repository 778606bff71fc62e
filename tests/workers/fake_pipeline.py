"""A fast stand-in for the pure pipeline, for tests of the service around it (job order,
twin updates, retries) that do not need real geometry.

It replaces the three pipeline calls the snapshot and comparison jobs make
(``reconstruct``, ``compare_snapshots``, ``pose_changes``) with functions of the same
signatures; everything else (claim, ingest re-read, persist, the twin) is the production
code. :func:`install` patches them into the glue modules, which is what a test's
``monkeypatch`` or the Celery plugin :mod:`tests.e2e.fake_pipeline_plugin` does.

The scene a capture shows is read from its detections: every detected class is an object
whose pose is a translation by the box centre ``(cx, cy, 0)`` metres. The fake comparison
reports a class seen only after as ``added`` (a new instance), one seen only before as
``removed`` (the twin's instance of that class), and one whose centre changed as ``moved``,
so the twin an environment ends with says which snapshots were applied and in what order.

Markers in a capture's image names steer a run: ``delay-<seconds>-…`` sleeps that long in
reconstruction, ``fail-…`` makes reconstruction fail, ``inventory-…`` makes the fake
inventory list every detected class as an object at its fake pose (verified); without it
the inventory is empty, as the real stage's is with no prepared library object.
"""

from __future__ import annotations

import json
import time
import uuid
from collections.abc import Callable, Collection, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d

from workers.pipeline.compare.data import CaptureData, TwinInstance
from workers.pipeline.compare.options import CompareOptions
from workers.pipeline.compare.results import CompareResult
from workers.pipeline.compare.thresholds import DistanceStats
from workers.pipeline.errors import PipelineError
from workers.pipeline.inventory import InventoryObject, InventoryOptions, InventoryResult
from workers.pipeline.reconstruct.stage import ReconstructionResult

FAKE_CHANGES = "fake_changes"


def reconstruct(
    *,
    images_dir: Path,
    work_dir: Path,
    progress: Callable[[str, float], None] | None = None,
    **_ignored: Any,
) -> ReconstructionResult:
    """A ten-point cloud and an empty cameras.json under ``work_dir``."""
    names = sorted(p.name for p in Path(images_dir).iterdir())
    delays = [float(name.split("-")[1]) for name in names if name.startswith("delay-")]
    time.sleep(max(delays, default=0.0))
    for name in names:
        if name.startswith("fail-"):
            raise PipelineError(f"fake reconstruction refused {name}", code="FakeFailure")
    work_dir.mkdir(parents=True, exist_ok=True)
    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(np.random.default_rng(0).random((10, 3)))
    cloud_path = work_dir / "cloud.ply"
    o3d.io.write_point_cloud(str(cloud_path), cloud)
    cameras_path = work_dir / "cameras.json"
    cameras_path.write_text(json.dumps({"images": {}}))
    quality = {"images_total": len(names), "alignment_residual_m": 0.0, "fake": True}
    quality_path = work_dir / "quality.json"
    quality_path.write_text(json.dumps(quality))
    if progress is not None:
        progress("write", 1.0)
    return ReconstructionResult(
        cloud_path=cloud_path,
        cameras_path=cameras_path,
        quality_path=quality_path,
        views=(),
        quality=quality,
    )


def scene(capture: CaptureData, classes: Sequence[str]) -> dict[str, float]:
    """Object name → x of its pose (the first box centre of its class, by image name)."""
    out: dict[str, float] = {}
    for name in sorted(capture.detections):
        for row in capture.detections[name]:
            out.setdefault(classes[int(row[0])], round(float(row[1]), 6))
    return out


def _pose(x: float) -> list[list[float]]:
    pose = np.eye(4)
    pose[0, 3] = x
    return [[float(v) for v in row] for row in pose]


def compare_snapshots(
    before: CaptureData,
    after: CaptureData,
    twin: Sequence[TwinInstance],
    classes: Sequence[str],
    diameters: Mapping[str, float],
    options: CompareOptions,
    progress: Callable[[str, float], None] | None = None,
) -> CompareResult:
    """The changes between the two scenes, matched to the twin's instances by class."""
    del diameters
    old, new = scene(before, classes), scene(after, classes)
    instances = {t.object_name: t.instance_id for t in twin}
    changes: list[dict[str, Any]] = []

    def change(kind: str, name: str, instance_id: str | None, x: float | None) -> None:
        changes.append(
            {
                "id": str(uuid.uuid4()),
                "type": kind,
                "object": name,
                "instance_id": instance_id,
                "pose": None if x is None else _pose(x),
                "previous_pose": None,
                "identification": None,
                "cluster": {"fake": True},
                "pose_quality": None,
                "centroid_env": None if x is None else [x, 0.0, 0.0],
            }
        )

    for name in sorted(set(old) | set(new)):
        if name in new and name not in old:
            change("added", name, str(uuid.uuid4()), new[name])
        elif name in old and name not in new:
            change("removed", name, instances.get(name), None)
        elif old[name] != new[name]:
            # a moved object the twin does not hold yet becomes a new instance there
            change("moved", name, instances.get(name) or str(uuid.uuid4()), new[name])
    if progress is not None:
        progress("compare", 1.0)
    stats = DistanceStats(mean=0.0, std=0.0, threshold=0.01)
    return CompareResult(
        options=options,
        distances={"added": stats, "removed": stats},
        clusters=(),
        changes=(),
        added_distances_m=np.zeros(0),
        removed_distances_m=np.zeros(0),
        stats={FAKE_CHANGES: changes},
    )


def pose_changes(
    result: CompareResult,
    after: CaptureData,
    classes: Sequence[str],
    available: Collection[str],
    load_model: Callable[[str], Any],
    compare_options: CompareOptions,
    pose_options: Mapping[str, Any] | None = None,
    progress: Callable[[str, float], None] | None = None,
) -> list[dict[str, Any]]:
    """The change records :func:`compare_snapshots` worked out (poses included)."""
    changes: list[dict[str, Any]] = result.stats[FAKE_CHANGES]
    return changes


def take_inventory(
    capture: CaptureData,
    classes: Sequence[str],
    class_diameters_m: Mapping[str, float],
    load_model: Callable[[str], Any],
    options: InventoryOptions,
    progress: Callable[[str, float], None] | None = None,
) -> InventoryResult:
    """One verified object per detected class at the scene's fake pose (x from its box
    centre), when an image name carries the ``inventory-`` marker; else none."""
    objects: list[InventoryObject] = []
    if any(name.startswith("inventory-") for name in capture.detections):
        for name, x in scene(capture, classes).items():
            objects.append(
                InventoryObject(
                    object_name=name,
                    class_id=list(classes).index(name),
                    env_from_object=np.asarray(_pose(x)),
                    pose_quality={"verified": True, "reasons": [], "fake": True},
                    identification={"metric": 1.0, "iou": 1.0, "overlaps": 1, "occurrences": 1},
                    centroid_env=np.array([x, 0.0, 0.0]),
                    cluster={"fake": True},
                    support="floor",
                )
            )
    if progress is not None:
        progress("inventory", 1.0)
    return InventoryResult(options, tuple(objects), (), (), {"objects": len(objects)})


def install(setattr_: Callable[[Any, str, Any], None] = setattr) -> None:
    """Patch the fake into the glue modules (``setattr_`` may be ``monkeypatch.setattr``)."""
    from workers import comparison, snapshot

    setattr_(snapshot, "reconstruct", reconstruct)
    setattr_(snapshot, "take_inventory", take_inventory)
    setattr_(comparison, "compare_snapshots", compare_snapshots)
    setattr_(comparison, "pose_changes", pose_changes)
