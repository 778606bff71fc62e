"""The routes the operator console uses (issue #20): the calling key, environment summaries,
a decimated cloud, a snapshot's photos with cameras and boxes, a comparison's cluster points,
a change's views (re-projected outline against the detection), and a library model as glTF.

The scene: a 2 × 2 m floor at z = 0 and a 10 cm cube (z 0.05..0.15) that the after snapshot
added, seen by one camera 2 m above the origin looking down. The cube's stored cluster also
holds points 20 cm under the floor: projected, they fall inside the photo, but the floor
hides them, so the outline must leave them out.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest
import trimesh
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from app.core import auth, change_clusters
from app.core.enums import ComparisonState, JobKind, SnapshotState
from app.core.export import decimate
from app.core.models import Change, Comparison, Job, Snapshot, SnapshotImage, TwinInstance, new_id
from app.core.settings import get_settings
from app.core.storage import LocalStorage
from tests.app.api.test_export_api import OBJ_TRIANGLE, box_cm, ply_bytes, upload_object
from tests.app.conftest import Keys
from tests.app.core.export.validator import assert_valid

W, H, F = 640, 480, 500.0
# camera 2 m above the origin looking down: x_cam = x_env, y_cam = -y_env, z_cam = -z_env
ENV_FROM_CAM = [[1.0, 0, 0, 0], [0, -1.0, 0, 0], [0, 0, -1.0, 2.0], [0, 0, 0, 1.0]]
CUBE_BOX_PX = [306.0, 226.0, 334.0, 254.0]  # the cube's projection, rounded outwards
FLOOR_SIDE = 201  # 1 cm spacing: dense enough for the coarse z-buffer to hide what is under it
PHOTO = b"\xff\xd8\xff\xe0 not really a jpeg, served as stored \xff\xd9"


def write_ply(path: Path, points: np.ndarray, rgb: np.ndarray) -> None:
    """A binary PLY as Open3D writes a snapshot's cloud: double x y z, uchar r g b."""
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment written by the test\n"
        f"element vertex {len(points)}\nproperty double x\nproperty double y\n"
        "property double z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
        "end_header\n"
    )
    rec = np.empty(
        len(points),
        [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("r", "u1"), ("g", "u1"), ("b", "u1")],
    )
    rec["x"], rec["y"], rec["z"] = points.T
    rec["r"], rec["g"], rec["b"] = rgb.T
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(header.encode() + rec.tobytes())


def read_decimated(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    end = data.index(b"end_header\n") + len(b"end_header\n")
    head = data[:end].decode()
    assert "format binary_little_endian 1.0" in head
    assert "property float x\nproperty float y\nproperty float z\n" in head
    assert "property uchar red\nproperty uchar green\nproperty uchar blue\n" in head
    rec = np.frombuffer(data[end:], dtype=decimate.RECORD)
    return np.column_stack([rec["x"], rec["y"], rec["z"]]), np.column_stack(
        [rec["r"], rec["g"], rec["b"]]
    )


def floor(n_side: int) -> np.ndarray:
    g = np.linspace(-1.0, 1.0, n_side)
    x, y = np.meshgrid(g, g)
    return np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])


def cube(n: int, seed: int = 0) -> np.ndarray:
    """Points on the cube's surface (z 0.05..0.15, x and y ±0.05)."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-0.05, 0.05, (n, 3))
    face = rng.integers(0, 3, n)
    pts[np.arange(n), face] = np.sign(rng.uniform(-1, 1, n)) * 0.05
    pts[:, 2] += 0.10
    return pts


@dataclass(frozen=True)
class Scene:
    env_id: str
    before: str
    after: str
    comparison: str
    change: str
    cloud_points: np.ndarray
    cube_points: np.ndarray
    hidden_points: np.ndarray


@pytest.fixture
def scene(client: TestClient, keys: Keys, session_factory: sessionmaker[Session]) -> Scene:
    r = client.post(
        "/v1/environments",
        json={"name": "cell-c", "classes": ["box", "cup"]},
        headers=keys.headers(),
    )
    assert r.status_code == 201, r.text
    env_id = r.json()["id"]
    storage = LocalStorage(get_settings().resolved_storage_dir)
    cube_pts = cube(1500)
    hidden = np.column_stack(
        [np.full(50, 0.4), np.linspace(0.3, 0.5, 50), np.full(50, -0.2)]
    )  # under the floor
    after_cloud = np.vstack([floor(FLOOR_SIDE), cube_pts])
    rgb = np.tile(np.array([[40, 90, 200]], np.uint8), (len(after_cloud), 1))
    rgb[: FLOOR_SIDE**2] = [120, 120, 120]
    cameras = {
        "intrinsics": {"model": "PINHOLE", "width": W, "height": H, "params": [F, F, 320, 240]},
        "poses": {"a.jpg": ENV_FROM_CAM},
    }
    ids = {}
    with session_factory.begin() as s:
        for seq, points in ((1, floor(FLOOR_SIDE)), (2, after_cloud)):
            snap_id = new_id()
            prefix = f"snapshots/{snap_id}"
            snap = Snapshot(
                id=snap_id,
                environment_id=env_id,
                seq=seq,
                storage_prefix=prefix,
                state=SnapshotState.reconstructed,
                pointcloud_key=f"{prefix}/reconstruction/cloud.ply",
                cameras_key=f"{prefix}/reconstruction/cameras.json",
                n_images=2,
            )
            s.add(snap)
            write_ply(storage.path(snap.pointcloud_key), points, rgb[: len(points)])
            storage.write_bytes(snap.cameras_key, json.dumps(cameras).encode())
            for name, detections in (
                (
                    "a.jpg",
                    [
                        {"class_id": 0, "class": "box", "cx": 0.5, "cy": 0.5,
                         "w": 30 / W, "h": 30 / H, "confidence": 0.9},
                        {"class_id": 1, "class": "cup", "cx": 0.1, "cy": 0.1,
                         "w": 0.05, "h": 0.05, "confidence": None},
                    ],
                ),
                ("b.jpg", []),
            ):  # fmt: skip
                key = f"{prefix}/images/{name}"
                storage.write_bytes(key, PHOTO)
                s.add(
                    SnapshotImage(
                        snapshot_id=snap_id,
                        name=name,
                        file_key=key,
                        width=W,
                        height=H,
                        size_bytes=len(PHOTO),
                        detections=detections,
                    )
                )
            ids[seq] = snap_id
        s.flush()
        job = Job(kind=JobKind.comparison, task_name="comparison.run", environment_id=env_id)
        s.add(job)
        s.flush()
        comparison = Comparison(
            environment_id=env_id,
            before_id=ids[1],
            after_id=ids[2],
            job_id=job.id,
            state=ComparisonState.succeeded,
            clusters=[{"id": 0, "side": "added", "boxes": {"a.jpg": CUBE_BOX_PX}}],
        )
        s.add(comparison)
        s.flush()
        change = Change(
            comparison_id=comparison.id,
            position=0,
            type="added",
            object_name="box",
            cluster={"id": 0, "side": "added", "n_points": 1500},
            identification={"object": "box", "metric": 0.87},
        )
        s.add(change)
        s.add(TwinInstance(environment_id=env_id, object_name="box", pose=ENV_FROM_CAM))
        s.flush()
        after_prefix = f"snapshots/{ids[2]}"
        change_clusters.write(
            storage,
            change_clusters.clusters_key(after_prefix, comparison.id),
            [
                change_clusters.StoredCluster(
                    0, "added", change.id, len(cube_pts) + 50, np.vstack([cube_pts, hidden])
                ),
                change_clusters.StoredCluster(1, "removed", None, 30_000, np.zeros((30_000, 3))),
            ],
        )
        comparison_id, change_id = comparison.id, change.id
    return Scene(env_id, ids[1], ids[2], comparison_id, change_id, after_cloud, cube_pts, hidden)


def project(points: np.ndarray) -> np.ndarray:
    cam = np.linalg.inv(np.array(ENV_FROM_CAM)) @ np.column_stack([points, np.ones(len(points))]).T
    return np.column_stack([F * cam[0] / cam[2] + 320, F * cam[1] / cam[2] + 240])


# --- 1. the calling key ------------------------------------------------------------------------


def test_the_current_key_names_its_scopes_and_environments(
    client: TestClient, keys: Keys, scene: Scene, session_factory: sessionmaker[Session]
) -> None:
    for which, scopes in (("admin", ["admin"]), ("read", ["read"]), ("capture", ["capture"])):
        r = client.get("/v1/keys/current", headers=keys.headers(which))
        assert r.status_code == 200, r.text
        body = r.json()
        assert body["scopes"] == scopes and body["environment_ids"] is None
        assert body["name"] == f"test {which}" and set(body) == {
            "id", "name", "scopes", "environment_ids"
        }  # fmt: skip
    with session_factory.begin() as s:
        _row, token = auth.create_key(s, "station", ["capture"], environment_ids=[scene.env_id])
        _row, metrics = auth.create_key(s, "scraper", ["metrics"])
    r = client.get("/v1/keys/current", headers={"Authorization": f"Bearer {token}"})
    assert r.json()["environment_ids"] == [scene.env_id]
    r = client.get("/v1/keys/current", headers={"Authorization": f"Bearer {metrics}"})
    assert r.status_code == 200 and r.json()["scopes"] == ["metrics"]


def test_the_current_key_is_401_without_a_valid_key(client: TestClient, keys: Keys) -> None:
    assert client.get("/v1/keys/current").status_code == 401
    r = client.get("/v1/keys/current", headers={"Authorization": "Bearer td_nope_x"})
    assert r.status_code == 401 and r.json()["error"] == "Unauthorized"


# --- 2. environment summaries ------------------------------------------------------------------


def test_environments_list_their_twin_object_count_and_last_snapshot(
    client: TestClient, keys: Keys, scene: Scene
) -> None:
    r = client.post(
        "/v1/environments", json={"name": "empty", "classes": ["box"]}, headers=keys.headers()
    )
    assert r.json()["twin_object_count"] == 0 and r.json()["last_snapshot"] is None
    listed = {
        e["name"]: e for e in client.get("/v1/environments", headers=keys.headers("read")).json()
    }
    cell = listed["cell-c"]
    assert cell["twin_object_count"] == 1
    assert cell["last_snapshot"]["id"] == scene.after
    assert cell["last_snapshot"]["seq"] == 2 and cell["last_snapshot"]["state"] == "reconstructed"
    assert listed["empty"]["last_snapshot"] is None
    one = client.get(f"/v1/environments/{scene.env_id}", headers=keys.headers("read")).json()
    assert one["twin_object_count"] == 1 and one["last_snapshot"]["id"] == scene.after


# --- 3. the decimated cloud ----------------------------------------------------------------------


def test_a_decimated_cloud_is_an_even_deterministic_subset_and_is_cached(
    client: TestClient, keys: Keys, scene: Scene
) -> None:
    url = f"/v1/snapshots/{scene.after}/pointcloud"
    r = client.get(url, params={"max_points": 1000}, headers=keys.headers("read"))
    assert r.status_code == 200, r.text
    total = len(scene.cloud_points)
    assert r.headers["x-total-points"] == str(total)
    points, rgb = read_decimated(r.content)
    assert len(points) == 1000
    # every point is one of the cloud's (float32 of the stored doubles), none twice
    full = scene.cloud_points.astype(np.float32)
    index = {tuple(p) for p in full}
    assert all(tuple(p) in index for p in points)
    assert len({tuple(p) for p in points}) == 1000
    # even: the cube's share (1500 of 41 901) is kept within 4 binomial sigmas, and the four
    # floor quadrants keep equal shares (not "the first N": those would all be floor)
    on_cube = np.mean(points[:, 2] > 0.01)
    share = len(scene.cube_points) / total
    assert abs(on_cube - share) < 4 * np.sqrt(share * (1 - share) / 1000)
    floor_pts = points[points[:, 2] <= 0.01]
    quadrants = np.histogram2d(floor_pts[:, 0], floor_pts[:, 1], bins=2)[0].ravel()
    assert quadrants.min() > 0.8 * quadrants.mean()
    # colours come through
    assert {tuple(c) for c in rgb} <= {(120, 120, 120), (40, 90, 200)}
    # the same N is the same file, and it is kept
    again = client.get(url, params={"max_points": 1000}, headers=keys.headers("read"))
    assert again.content == r.content
    storage = LocalStorage(get_settings().resolved_storage_dir)
    cached = storage.path(f"snapshots/{scene.after}/reconstruction/decimated/1000.ply")
    assert cached.read_bytes() == r.content
    # a smaller N is a subset of a larger one
    small, _ = read_decimated(
        client.get(url, params={"max_points": 2000}, headers=keys.headers("read")).content
    )
    assert {tuple(p) for p in points} <= {tuple(p) for p in small}
    # an N between steps is rounded down (at most 10 cached files a decade)
    between = client.get(url, params={"max_points": 1999}, headers=keys.headers("read"))
    assert (
        between.content
        == client.get(url, params={"max_points": 1500}, headers=keys.headers("read")).content
    )
    assert len(read_decimated(between.content)[0]) == 1500
    # more than the cloud holds: every point
    every, _ = read_decimated(
        client.get(url, params={"max_points": 1_000_000}, headers=keys.headers("read")).content
    )
    assert len(every) == total
    # without max_points the stored cloud as it is
    whole = client.get(url, headers=keys.headers("read"))
    assert (
        whole.content
        == storage.path(f"snapshots/{scene.after}/reconstruction/cloud.ply").read_bytes()
    )


def test_a_cloud_newer_than_its_cache_is_decimated_again(
    client: TestClient, keys: Keys, scene: Scene
) -> None:
    url = f"/v1/snapshots/{scene.before}/pointcloud"
    first = client.get(url, params={"max_points": 1000}, headers=keys.headers("read"))
    storage = LocalStorage(get_settings().resolved_storage_dir)
    ply = storage.path(f"snapshots/{scene.before}/reconstruction/cloud.ply")
    moved = floor(40) + np.array([5.0, 0.0, 0.0])
    write_ply(ply, moved, np.zeros((len(moved), 3), np.uint8))
    second = client.get(url, params={"max_points": 1000}, headers=keys.headers("read"))
    assert second.content != first.content
    points, _ = read_decimated(second.content)
    assert points[:, 0].min() >= 4.0 - 1e-6


@pytest.mark.parametrize("bad", ["999", "5000001", "0", "-5", "many"])
def test_max_points_out_of_range_is_422(
    client: TestClient, keys: Keys, scene: Scene, bad: str
) -> None:
    r = client.get(
        f"/v1/snapshots/{scene.after}/pointcloud",
        params={"max_points": bad},
        headers=keys.headers("read"),
    )
    assert r.status_code == 422 and "max_points" in r.json()["detail"]


def test_a_decimated_cloud_is_ply_only(client: TestClient, keys: Keys, scene: Scene) -> None:
    r = client.get(
        f"/v1/snapshots/{scene.after}/pointcloud",
        params={"max_points": 1000, "format": "laz"},
        headers=keys.headers("read"),
    )
    assert r.status_code == 422 and "max_points" in r.json()["detail"]


def test_a_decimated_cloud_before_reconstruction_is_409(
    client: TestClient, keys: Keys, scene: Scene, session_factory: sessionmaker[Session]
) -> None:
    with session_factory.begin() as s:
        snap = s.get_one(Snapshot, scene.before)
        snap.pointcloud_key, snap.state = None, SnapshotState.processing
    r = client.get(
        f"/v1/snapshots/{scene.before}/pointcloud",
        params={"max_points": 1000},
        headers=keys.headers("read"),
    )
    assert r.status_code == 409 and r.json()["error"] == "PointCloudNotReady"


# --- 4. photos ---------------------------------------------------------------------------------


def test_photos_list_their_camera_and_boxes_in_pixels(
    client: TestClient, keys: Keys, scene: Scene
) -> None:
    r = client.get(f"/v1/snapshots/{scene.after}/images", headers=keys.headers("read"))
    assert r.status_code == 200, r.text
    a, b = r.json()
    assert (a["name"], b["name"]) == ("a.jpg", "b.jpg")
    assert a["registered"] and not b["registered"] and b["camera"] is None
    assert a["camera"]["K"] == [[F, 0, 320], [0, F, 240], [0, 0, 1]]
    assert a["camera"]["env_from_cam"] == ENV_FROM_CAM
    assert (a["width"], a["height"]) == (W, H)
    box, cup = a["detections"]
    assert box["class_name"] == "box" and box["class_id"] == 0 and box["confidence"] == 0.9
    np.testing.assert_allclose(box["box_px"], [305, 225, 335, 255])
    np.testing.assert_allclose(cup["box_px"], [48, 36, 80, 60])
    assert cup["confidence"] is None
    photo = client.get(a["url"], headers=keys.headers("read"))
    assert photo.status_code == 200 and photo.content == PHOTO
    assert photo.headers["content-type"] == "image/jpeg"


def test_a_photo_unknown_is_404_and_deleted_by_retention_is_410(
    client: TestClient, keys: Keys, scene: Scene, session_factory: sessionmaker[Session]
) -> None:
    url = f"/v1/snapshots/{scene.after}/images"
    r = client.get(f"{url}/nope.jpg", headers=keys.headers("read"))
    assert r.status_code == 404 and "nope.jpg" in r.json()["detail"]
    with session_factory.begin() as s:
        s.get_one(Snapshot, scene.after).images_deleted_at = datetime(2026, 1, 1, tzinfo=UTC)
    r = client.get(f"{url}/a.jpg", headers=keys.headers("read"))
    assert r.status_code == 410 and r.json()["error"] == "ImagesDeleted"
    assert "retention" in r.json()["detail"]
    # the list still answers: cameras and detections are kept
    assert len(client.get(url, headers=keys.headers("read")).json()) == 2


# --- 5. cluster points -------------------------------------------------------------------------


def test_clusters_carry_their_points_side_and_change(
    client: TestClient, keys: Keys, scene: Scene
) -> None:
    r = client.get(f"/v1/comparisons/{scene.comparison}/clusters", headers=keys.headers("read"))
    assert r.status_code == 200, r.text
    cube_cluster, other = r.json()["clusters"]
    assert cube_cluster["id"] == 0 and cube_cluster["side"] == "added"
    assert cube_cluster["change_id"] == scene.change and cube_cluster["n_points"] == 1550
    positions = np.array(cube_cluster["positions"]).reshape(-1, 3)
    expected = np.vstack([scene.cube_points, scene.hidden_points])
    np.testing.assert_allclose(positions, expected, atol=5.1e-5)  # 4 decimals
    assert other["change_id"] is None and other["side"] == "removed"
    assert other["n_points"] == 30_000 and len(other["positions"]) == 3 * 20_000


def test_clusters_of_a_comparison_not_succeeded_or_made_before_are_409(
    client: TestClient, keys: Keys, scene: Scene, session_factory: sessionmaker[Session]
) -> None:
    url = f"/v1/comparisons/{scene.comparison}/clusters"
    storage = LocalStorage(get_settings().resolved_storage_dir)
    storage.path(
        change_clusters.clusters_key(f"snapshots/{scene.after}", scene.comparison)
    ).unlink()
    r = client.get(url, headers=keys.headers("read"))
    assert r.status_code == 409 and r.json()["error"] == "ClustersNotStored"
    with session_factory.begin() as s:
        s.get_one(Comparison, scene.comparison).state = ComparisonState.running
    r = client.get(url, headers=keys.headers("read"))
    assert r.status_code == 409 and r.json()["error"] == "ComparisonNotSucceeded"


def test_stored_clusters_round_trip_and_are_capped(tmp_path: Path) -> None:
    many = np.random.default_rng(1).normal(size=(50_000, 3))
    few = np.random.default_rng(2).normal(size=(10, 3))
    storage = LocalStorage(tmp_path)
    change_clusters.write(
        storage,
        "c.npz",
        [
            change_clusters.StoredCluster(7, "removed", "c-1", 50_000, many),
            change_clusters.StoredCluster(8, "added", None, 10, few),
        ],
    )
    big, small = change_clusters.read(storage, "c.npz") or []
    assert (big.id, big.side, big.change_id, big.n_points) == (7, "removed", "c-1", 50_000)
    assert big.points_env.shape == (20_000, 3)
    index = {tuple(p) for p in many.astype(np.float32)}
    assert all(tuple(p) in index for p in big.points_env)  # its own points
    assert (small.id, small.change_id) == (8, None)
    np.testing.assert_array_equal(small.points_env, few.astype(np.float32))
    assert change_clusters.read(storage, "none.npz") is None
    storage.write_bytes("bad.npz", b"not a zip")
    with pytest.raises(Exception, match="cannot be read"):
        change_clusters.read(storage, "bad.npz")


# --- 6. a change's views -----------------------------------------------------------------------


def test_a_change_view_outlines_the_visible_cluster_beside_its_detection(
    client: TestClient, keys: Keys, scene: Scene
) -> None:
    url = f"/v1/comparisons/{scene.comparison}/changes/{scene.change}/views"
    r = client.get(url, headers=keys.headers("read"))
    assert r.status_code == 200, r.text
    (view,) = r.json()
    assert view["image"] == "a.jpg" and view["box_px"] == CUBE_BOX_PX
    np.testing.assert_allclose(view["detection_box_px"], [305, 225, 335, 255])
    assert view["iou"] == pytest.approx(28 * 28 / (30 * 30))
    assert view["counted"] is True
    outline = np.array(view["outline_px"])
    cube_px = project(scene.cube_points)
    # the hull of the visible cube: within its projection (whole pixels), spanning most of it
    assert len(outline) >= 4
    assert (outline.min(axis=0) >= cube_px.min(axis=0) - 1).all()
    assert (outline.max(axis=0) <= cube_px.max(axis=0) + 1).all()
    span = outline.max(axis=0) - outline.min(axis=0)
    assert (span > 0.9 * (cube_px.max(axis=0) - cube_px.min(axis=0))).all()
    # the points under the floor project inside the photo but are hidden: not outlined
    hidden_px = project(scene.hidden_points)
    assert (hidden_px >= 0).all() and (hidden_px[:, 0] < W).all() and (hidden_px[:, 1] < H).all()
    assert outline[:, 0].max() < hidden_px[:, 0].min()


def test_a_view_without_a_detection_of_the_class_is_not_counted(
    client: TestClient, keys: Keys, scene: Scene, session_factory: sessionmaker[Session]
) -> None:
    with session_factory.begin() as s:
        change = s.get_one(Change, scene.change)
        change.identification = {"object": "cup", "metric": 0.0}
        change.object_name = None
    url = f"/v1/comparisons/{scene.comparison}/changes/{scene.change}/views"
    (view,) = client.get(url, headers=keys.headers("read")).json()
    # the cup box is far from the cube: no overlap, so the photo did not count
    np.testing.assert_allclose(view["detection_box_px"], [48, 36, 80, 60])
    assert view["iou"] == 0.0 and view["counted"] is False


def test_views_of_an_unknown_change_are_404(client: TestClient, keys: Keys, scene: Scene) -> None:
    r = client.get(
        f"/v1/comparisons/{scene.comparison}/changes/{new_id()}/views",
        headers=keys.headers("read"),
    )
    assert r.status_code == 404 and "has no change" in r.json()["detail"]


# --- 7. a library model ------------------------------------------------------------------------


def test_a_library_model_is_glb_in_its_object_frame_in_metres(
    client: TestClient, keys: Keys, tmp_path: Path
) -> None:
    object_id = upload_object(client, keys, "drill", "drill.ply", ply_bytes(box_cm(), tmp_path))
    r = client.get(f"/v1/objects/{object_id}/model", headers=keys.headers("read"))
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "model/gltf-binary"
    (tmp_path / "model.glb").write_bytes(r.content)
    assert_valid(tmp_path / "model.glb")  # the Khronos validator: no errors or warnings
    scene = trimesh.load(io.BytesIO(r.content), file_type="glb", force="scene", process=False)
    (mesh,) = scene.geometry.values()
    box = np.asarray(box_cm().vertices) * 0.01  # the file is in centimetres
    np.testing.assert_allclose(mesh.vertices, box, atol=1e-7)
    world_from_node, _ = scene.graph.get(scene.graph.nodes_geometry[0])
    np.testing.assert_allclose(world_from_node, np.eye(4))  # object frame as it is


def test_a_model_not_prepared_is_409_and_an_unknown_object_404(
    client: TestClient, keys: Keys
) -> None:
    object_id = upload_object(client, keys, "bowl", "bowl.obj", OBJ_TRIANGLE)
    r = client.get(f"/v1/objects/{object_id}/model", headers=keys.headers("read"))
    assert r.status_code == 409 and r.json()["error"] == "ModelNotReady"
    r = client.get(f"/v1/objects/{new_id()}/model", headers=keys.headers("read"))
    assert r.status_code == 404


# --- scopes ------------------------------------------------------------------------------------


def read_urls(scene: Scene, object_id: str) -> list[str]:
    return [
        f"/v1/snapshots/{scene.after}/pointcloud?max_points=1000",
        f"/v1/snapshots/{scene.after}/images",
        f"/v1/snapshots/{scene.after}/images/a.jpg",
        f"/v1/comparisons/{scene.comparison}/clusters",
        f"/v1/comparisons/{scene.comparison}/changes/{scene.change}/views",
        f"/v1/objects/{object_id}/model",
    ]


def test_console_reads_need_a_read_key(
    client: TestClient, keys: Keys, scene: Scene, tmp_path: Path
) -> None:
    object_id = upload_object(client, keys, "drill", "drill.ply", ply_bytes(box_cm(), tmp_path))
    for url in read_urls(scene, object_id):
        assert client.get(url).status_code == 401, url
        r = client.get(url, headers=keys.headers("capture"))
        assert r.status_code == 403 and r.json()["error"] == "Forbidden", url
        assert client.get(url, headers=keys.headers("admin")).status_code == 200, url


def test_a_key_limited_to_another_environment_gets_404(
    client: TestClient, keys: Keys, scene: Scene, session_factory: sessionmaker[Session]
) -> None:
    r = client.post(
        "/v1/environments", json={"name": "other", "classes": ["box"]}, headers=keys.headers()
    )
    with session_factory.begin() as s:
        _row, token = auth.create_key(s, "elsewhere", ["read"], environment_ids=[r.json()["id"]])
    for url in read_urls(scene, new_id())[:-1]:
        got = client.get(url, headers={"Authorization": f"Bearer {token}"})
        assert got.status_code == 404, url
