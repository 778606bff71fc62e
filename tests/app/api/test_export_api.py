"""Downloads for other tools over HTTP: the twin state as binary glTF (now and at an earlier
snapshot, by ``format`` or by ``Accept``) and a snapshot's cloud as LAZ, each read back by
an independent reader (the Khronos validator and trimesh; laspy)."""

from __future__ import annotations

import io
from dataclasses import dataclass
from itertools import pairwise
from pathlib import Path
from typing import Any

import laspy
import numpy as np
import open3d as o3d
import pytest
import trimesh
from fastapi.testclient import TestClient
from scipy.spatial.transform import Rotation
from sqlalchemy.orm import Session, sessionmaker

from app.core import twin
from app.core.enums import ChangeType, JobKind, SnapshotState, TwinUpdate
from app.core.export.gltf import GLTF_FROM_ENV
from app.core.export.ply import read_model
from app.core.models import Change, Comparison, Environment, Job, LibraryObject, Snapshot, new_id
from app.core.settings import get_settings
from app.core.storage import LocalStorage
from tests.app.conftest import Keys
from tests.app.core.export.test_gltf import gltf_json
from tests.app.core.export.validator import assert_valid

GLB = "model/gltf-binary"
LAZ = "application/vnd.laszip"
OBJ_TRIANGLE = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"


def rigid(seed: int) -> list[list[float]]:
    pose = np.eye(4)
    pose[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    pose[:3, 3] = np.random.default_rng(seed).uniform(-2, 2, 3)
    return [[float(v) for v in row] for row in pose]


def ply_bytes(geometry: Any, tmp: Path) -> bytes:
    path = tmp / f"{new_id()}.ply"
    if isinstance(geometry, o3d.geometry.TriangleMesh):
        assert o3d.io.write_triangle_mesh(str(path), geometry)
    else:
        assert o3d.io.write_point_cloud(str(path), geometry)
    return path.read_bytes()


def box_cm() -> o3d.geometry.TriangleMesh:
    """A 20 × 10 × 5 cm box in centimetres, with vertex colours (no normals: computed)."""
    box = o3d.geometry.TriangleMesh.create_box(20.0, 10.0, 5.0)
    box.vertex_colors = o3d.utility.Vector3dVector(np.random.default_rng(0).random((8, 3)))
    return box


def cloud(n: int, seed: int) -> o3d.geometry.PointCloud:
    rng = np.random.default_rng(seed)
    points = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(rng.normal(size=(n, 3)) * 0.05))
    points.colors = o3d.utility.Vector3dVector(rng.integers(0, 256, (n, 3)) / 255.0)
    return points


@dataclass(frozen=True)
class World:
    """An environment whose twin stands at seq 3 of 4 reconstructed snapshots. Seq 2 added
    drills a and b, a drill c of unknown pose, a scan, a bowl and a mug; seq 3 moved a and
    removed the scan; the twin has not reached seq 4. Library: drill a mesh PLY in cm, scan
    a cloud PLY, bowl an OBJ (drawn from its prepared cloud), mug nothing."""

    env_id: str
    snapshots: list[str]
    instances: dict[str, str]
    poses: dict[str, list[list[float]]]  # at seq 3
    objects: dict[str, str]


def upload_object(client: TestClient, keys: Keys, name: str, filename: str, data: bytes) -> str:
    units = "cm" if name == "drill" else "m"
    r = client.post(
        "/v1/objects",
        files={"file": (filename, io.BytesIO(data))},
        data={"name": name, "units": units},
        headers=keys.headers(),
    )
    assert r.status_code == 202, r.text
    return str(r.json()["id"])


@pytest.fixture
def world(
    client: TestClient, keys: Keys, session_factory: sessionmaker[Session], tmp_path: Path
) -> World:
    classes = ["drill", "scan", "bowl", "mug"]
    r = client.post(
        "/v1/environments", json={"name": "cell-x", "classes": classes}, headers=keys.headers()
    )
    env_id = r.json()["id"]
    objects = {
        "drill": upload_object(client, keys, "drill", "drill.ply", ply_bytes(box_cm(), tmp_path)),
        "scan": upload_object(client, keys, "scan", "scan.ply", ply_bytes(cloud(300, 1), tmp_path)),
        "bowl": upload_object(client, keys, "bowl", "bowl.obj", OBJ_TRIANGLE),
    }
    storage = LocalStorage(get_settings().resolved_storage_dir)
    storage.write_bytes(
        f"objects/{objects['bowl']}/prepared/model.ply", ply_bytes(cloud(200, 2), tmp_path)
    )
    names = ["a", "b", "c", "scan", "bowl", "mug"]
    ids = {n: new_id() for n in names}
    with session_factory.begin() as s:
        bowl = s.get_one(LibraryObject, objects["bowl"])
        bowl.artifacts_key = f"objects/{bowl.id}/prepared"
        snaps = []
        for seq in (1, 2, 3, 4):
            snap_id = new_id()
            snaps.append(
                Snapshot(
                    id=snap_id,
                    environment_id=env_id,
                    seq=seq,
                    storage_prefix=f"snapshots/{snap_id}",
                    state=SnapshotState.reconstructed,
                    twin_update=[TwinUpdate.baseline, TwinUpdate.applied, TwinUpdate.applied, None][
                        seq - 1
                    ],
                )
            )
        s.add_all(snaps)
        s.flush()
        comparisons = []
        for before, after in pairwise(snaps[:3]):
            job = Job(kind=JobKind.comparison, task_name="comparison.run", environment_id=env_id)
            s.add(job)
            s.flush()
            comparison = Comparison(
                environment_id=env_id,
                before_id=before.id,
                after_id=after.id,
                job_id=job.id,
                automatic=True,
            )
            s.add(comparison)
            s.flush()
            comparisons.append(comparison.id)
        added = [
            {
                "type": ChangeType.added,
                "object": "drill" if n in "abc" else n,
                "instance_id": ids[n],
                "pose": None if n == "c" else rigid(i),
                "pose_quality": {"fitness": 0.5 + i / 10},
            }
            for i, n in enumerate(names)
        ]
        moved = {
            "type": ChangeType.moved,
            "object": "drill",
            "instance_id": ids["a"],
            "pose": rigid(9),
            "pose_quality": {"fitness": 0.99},
        }
        removed = {"type": ChangeType.removed, "object": "scan", "instance_id": ids["scan"]}
        object_ids = {"drill": objects["drill"], "scan": objects["scan"], "bowl": objects["bowl"]}
        for comparison_id, snap, changes in (
            (comparisons[0], snaps[1], added),
            (comparisons[1], snaps[2], [moved, removed]),
        ):
            twin.apply_changes(s, env_id, snap.id, comparison_id, changes, object_ids)
            for position, change in enumerate(changes):
                s.add(
                    Change(
                        comparison_id=comparison_id,
                        position=position,
                        type=change["type"],
                        object_name=change["object"],
                        instance_id=change["instance_id"],
                        pose=change.get("pose"),
                        pose_quality=change.get("pose_quality"),
                    )
                )
        env = s.get_one(Environment, env_id)
        env.twin_seq, env.twin_snapshot_id = 3, snaps[2].id
    poses = {n: rigid(i) for i, n in enumerate(names) if n not in ("c", "scan")}
    poses["a"] = rigid(9)
    return World(env_id, [x.id for x in snaps], ids, poses, objects)


def get_glb(client: TestClient, keys: Keys, url: str, tmp_path: Path, **kw: Any) -> bytes:
    headers = keys.headers("read") | kw.pop("headers", {})
    r = client.get(url, headers=headers, **kw)
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == GLB
    (tmp_path / "state.glb").write_bytes(r.content)
    assert_valid(tmp_path / "state.glb")
    return r.content


def nodes(data: bytes) -> dict[str, dict[str, Any]]:
    return {n["name"]: n for n in gltf_json(data)["nodes"]}


def test_the_state_as_glb_places_each_library_model_at_its_pose(
    client: TestClient, keys: Keys, world: World, tmp_path: Path
) -> None:
    url = f"/v1/environments/{world.env_id}/state"
    data = get_glb(client, keys, url, tmp_path, params={"format": "glb"})
    scene = trimesh.load(io.BytesIO(data), file_type="glb", force="scene", process=False)
    i = world.instances
    drawn = {f"drill/{i['a']}": "a", f"drill/{i['b']}": "b"}
    drawn |= {f"bowl/{i['bowl']}": "bowl", f"mug/{i['mug']}": "mug"}
    assert set(nodes(data)) == set(drawn) | {"environment"}
    for name, short in drawn.items():
        world_from_node, _geometry = scene.graph.get(name)
        expected = GLTF_FROM_ENV @ np.array(world.poses[short])
        np.testing.assert_allclose(world_from_node, expected, atol=1e-6)
    by_name = nodes(data)
    a, b = by_name[f"drill/{i['a']}"], by_name[f"drill/{i['b']}"]
    assert a["mesh"] == b["mesh"]  # one drill mesh, shared
    assert a["extras"]["instance_id"] == i["a"] and a["extras"]["class"] == "drill"
    assert a["extras"]["pose_quality"] == {"fitness": 0.99}
    # the drill file is in centimetres: the glTF holds metres
    box = read_model(
        Path(get_settings().resolved_storage_dir) / f"objects/{world.objects['drill']}/model.ply"
    )
    drill = scene.geometry[scene.graph.get(f"drill/{i['a']}")[1]]
    np.testing.assert_allclose(drill.vertices, box.positions * 0.01, atol=1e-7)
    bowl = scene.geometry[scene.graph.get(f"bowl/{i['bowl']}")[1]]
    assert isinstance(bowl, trimesh.PointCloud) and len(bowl.vertices) == 200  # prepared cloud
    mug = by_name[f"mug/{i['mug']}"]
    assert "mesh" not in mug and mug["extras"]["model_missing"] == "no library object of this class"
    root = by_name["environment"]["extras"]
    assert root["snapshot"] == world.snapshots[2] and root["seq"] == 3
    assert [(u["instance_id"], u["reason"]) for u in root["undrawn"]] == [(i["c"], "pose unknown")]


def test_negotiation_by_accept_and_format(
    client: TestClient, keys: Keys, world: World, tmp_path: Path
) -> None:
    url = f"/v1/environments/{world.env_id}/state"
    by_format = get_glb(client, keys, url, tmp_path, params={"format": "glb"})
    by_accept = get_glb(client, keys, url, tmp_path, headers={"Accept": GLB})
    assert by_accept == by_format
    assert client.get(url, headers=keys.headers("read")).headers["vary"] == "Accept"
    for accept in (
        None,
        "*/*",
        "application/json",
        f"{GLB};q=0.5, application/json",
        "text/html, */*;q=0.1",
    ):
        headers = keys.headers("read") | ({"Accept": accept} if accept else {})
        r = client.get(url, headers=headers)
        assert r.status_code == 200 and r.headers["content-type"] == "application/json", accept
        assert len(r.json()["objects"]) == 5
    r = client.get(url, headers=keys.headers("read") | {"Accept": "text/html"})
    assert r.status_code == 406 and r.json()["error"] == "NotAcceptable"
    assert GLB in r.json()["detail"]
    # format wins over Accept
    r = client.get(url, params={"format": "json"}, headers=keys.headers("read") | {"Accept": GLB})
    assert r.headers["content-type"] == "application/json"
    r = client.get(url, params={"format": "obj"}, headers=keys.headers("read"))
    assert r.status_code == 422 and "format" in r.json()["detail"]


def test_the_state_at_an_earlier_snapshot_as_json_and_glb(
    client: TestClient, keys: Keys, world: World, tmp_path: Path
) -> None:
    url = f"/v1/environments/{world.env_id}/state"
    i = world.instances
    r = client.get(url, params={"snapshot": world.snapshots[1]}, headers=keys.headers("read"))
    body = r.json()
    assert r.status_code == 200 and body["at_snapshot"] == world.snapshots[1]
    assert body["twin"]["seq"] == 3  # where the twin stands now
    at2 = {o["instance_id"]: o for o in body["objects"]}
    assert set(at2) == set(i.values())  # the scan was still there, a not moved yet
    assert at2[i["a"]]["pose"] == rigid(0) and at2[i["a"]]["pose_quality"] == {"fitness": 0.5}
    assert at2[i["a"]]["since_snapshot"] == world.snapshots[1]
    data = get_glb(
        client, keys, url, tmp_path, params={"snapshot": world.snapshots[1], "format": "glb"}
    )
    by_name = nodes(data)
    assert f"scan/{i['scan']}" in by_name and by_name["environment"]["extras"]["seq"] == 2
    scene = trimesh.load(io.BytesIO(data), file_type="glb", force="scene", process=False)
    np.testing.assert_allclose(
        scene.graph.get(f"drill/{i['a']}")[0], GLTF_FROM_ENV @ np.array(rigid(0)), atol=1e-6
    )
    assert isinstance(scene.geometry[scene.graph.get(f"scan/{i['scan']}")[1]], trimesh.PointCloud)
    # the baseline: an empty twin
    data = get_glb(
        client, keys, url, tmp_path, params={"snapshot": world.snapshots[0], "format": "glb"}
    )
    assert set(nodes(data)) == {"environment"}


@pytest.mark.parametrize(
    ("snapshot", "status", "error"),
    [("nope", 404, "NotFound"), (3, 409, "SnapshotNotApplied"), ("other", 404, "NotFound")],
)
def test_a_snapshot_the_twin_does_not_reflect_is_refused(
    client: TestClient, keys: Keys, world: World, snapshot: Any, status: int, error: str
) -> None:
    if snapshot == "other":  # a snapshot of another environment
        env = client.post(
            "/v1/environments", json={"name": "other", "classes": ["x"]}, headers=keys.headers()
        ).json()
        url = f"/v1/environments/{env['id']}/state"
        snapshot = world.snapshots[1]
    else:
        url = f"/v1/environments/{world.env_id}/state"
        snapshot = world.snapshots[snapshot] if isinstance(snapshot, int) else snapshot
    for params in ({"snapshot": snapshot}, {"snapshot": snapshot, "format": "glb"}):
        r = client.get(url, params=params, headers=keys.headers("read"))
        assert r.status_code == status and r.json()["error"] == error, r.text
        assert snapshot in r.json()["detail"]


def finish_cloud(
    factory: sessionmaker[Session], snapshot_id: str, points: o3d.geometry.PointCloud
) -> Path:
    storage = LocalStorage(get_settings().resolved_storage_dir)
    with factory.begin() as s:
        snap = s.get_one(Snapshot, snapshot_id)
        snap.pointcloud_key = f"{snap.storage_prefix}/reconstruction/cloud.ply"
        path = storage.path(snap.pointcloud_key)
    path.parent.mkdir(parents=True)
    assert o3d.io.write_point_cloud(str(path), points)
    return path


def test_the_cloud_as_laz_reads_back_and_goes_with_the_snapshot(
    client: TestClient,
    keys: Keys,
    world: World,
    session_factory: sessionmaker[Session],
    tmp_path: Path,
) -> None:
    points = cloud(5000, 3)
    points.translate((3.0, -1.0, 0.5))
    ply = finish_cloud(session_factory, world.snapshots[0], points)
    url = f"/v1/snapshots/{world.snapshots[0]}/pointcloud"
    r = client.get(url, params={"format": "laz"}, headers=keys.headers("read"))
    assert r.status_code == 200 and r.headers["content-type"] == LAZ
    assert r.headers["content-disposition"].endswith('.laz"')
    las = laspy.read(io.BytesIO(r.content))
    source = read_model(ply)
    assert las.header.point_count == 5000
    assert np.abs(las.xyz - source.positions).max() <= 0.5e-4 + 1e-9
    rgb = np.stack([las.red, las.green, las.blue], axis=1).astype(np.int64)
    np.testing.assert_array_equal(rgb, np.round(source.colors * 255).astype(np.int64) * 257)  # type: ignore[operator]
    assert ply.with_suffix(".laz").is_file()  # cached beside the PLY
    r = client.get(url, headers=keys.headers("read") | {"Accept": LAZ})
    assert r.headers["content-type"] == LAZ and r.content == ply.with_suffix(".laz").read_bytes()
    r = client.get(url, headers=keys.headers("read"))
    assert r.headers["content-type"] == "application/octet-stream" and r.content == ply.read_bytes()
    r = client.get(url, headers=keys.headers("read") | {"Accept": "text/html"})
    assert r.status_code == 406 and r.json()["error"] == "NotAcceptable"
    r = client.get(url, params={"format": "xyz"}, headers=keys.headers("read"))
    assert r.status_code == 422 and "format" in r.json()["detail"]
    # seq 1 is neither the twin's snapshot nor the newest: it may be deleted, LAZ and all
    assert (
        client.delete(f"/v1/snapshots/{world.snapshots[0]}", headers=keys.headers()).status_code
        == 204
    )
    assert not ply.with_suffix(".laz").exists() and not ply.exists()


def test_laz_of_a_snapshot_without_a_cloud_is_409(
    client: TestClient, keys: Keys, world: World
) -> None:
    r = client.get(
        f"/v1/snapshots/{world.snapshots[3]}/pointcloud",
        params={"format": "laz"},
        headers=keys.headers("read"),
    )
    assert r.status_code == 409 and r.json()["error"] == "PointCloudNotReady"


def test_a_model_file_that_cannot_be_read_leaves_its_nodes_without_a_mesh(
    client: TestClient, keys: Keys, world: World, tmp_path: Path
) -> None:
    storage = LocalStorage(get_settings().resolved_storage_dir)
    key = f"objects/{world.objects['drill']}/model.ply"
    storage.write_bytes(key, b"ply\nformat binary_little_endian 1.0\nelement vertex 9\n")
    url = f"/v1/environments/{world.env_id}/state"
    by_name = nodes(get_glb(client, keys, url, tmp_path, params={"format": "glb"}))
    for short in ("a", "b"):
        drill = by_name[f"drill/{world.instances[short]}"]
        assert "mesh" not in drill and "could not be read" in drill["extras"]["model_missing"]
    assert "mesh" in by_name[f"bowl/{world.instances['bowl']}"]  # the others are drawn
