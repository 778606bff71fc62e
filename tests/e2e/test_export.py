"""Exports through the running service (PostgreSQL, a private Redis, the API and a Celery
worker with the fast fake pipeline of :mod:`tests.e2e.fake_pipeline_plugin`): library
objects prepared by the real job, three snapshots processed so the twin has instances, then
the state downloaded as binary glTF (now and at an earlier snapshot) and a cloud as LAZ,
each read back by an independent reader (the Khronos validator, trimesh, laspy)."""

from __future__ import annotations

import io
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import laspy
import numpy as np
import open3d as o3d
import pytest
import trimesh

from app.core.export.gltf import GLTF_FROM_ENV
from app.core.export.ply import read_model
from tests.app.core.export.validator import assert_valid
from tests.e2e.conftest import (
    Processes,
    RedisServer,
    fake_pipeline_service,
    poll_job,
    wait_until,
)
from tests.e2e.test_twin_order import upload

pytestmark = [pytest.mark.slow, pytest.mark.e2e, pytest.mark.postgres, pytest.mark.redis]

CLASSES = ["drill", "scan"]
# class → the fake pose's x (metres): the scan comes with snapshot 2 and goes with 3
SCENES: list[dict[str, float]] = [{"drill": 0.2}, {"drill": 0.3, "scan": 0.6}, {"drill": 0.5}]


def library_files(tmp_path: Path) -> dict[str, bytes]:
    """A coloured box mesh (drill) and a sphere's points (scan), as PLY."""
    box = o3d.geometry.TriangleMesh.create_box(0.2, 0.1, 0.05)
    box.vertex_colors = o3d.utility.Vector3dVector(np.random.default_rng(0).random((8, 3)))
    o3d.io.write_triangle_mesh(str(tmp_path / "drill.ply"), box)
    directions = np.random.default_rng(1).normal(size=(2000, 3))
    on_sphere = 0.05 * directions / np.linalg.norm(directions, axis=1, keepdims=True)
    sphere = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(on_sphere))
    o3d.io.write_point_cloud(str(tmp_path / "scan.ply"), sphere)
    return {name: (tmp_path / f"{name}.ply").read_bytes() for name in CLASSES}


def glb(client: httpx.Client, env_id: str, tmp_path: Path, **params: str) -> trimesh.Scene:
    """The state as .glb, validated (0 errors, 0 warnings) and loaded by trimesh."""
    r = client.get(
        f"/v1/environments/{env_id}/state",
        params=params,
        headers={"Accept": "model/gltf-binary"},
    )
    assert r.status_code == 200 and r.headers["content-type"] == "model/gltf-binary", r.text
    path = tmp_path / f"state-{params.get('snapshot', 'now')}.glb"
    path.write_bytes(r.content)
    assert_valid(path)
    scene = trimesh.load(io.BytesIO(r.content), file_type="glb", force="scene", process=False)
    assert isinstance(scene, trimesh.Scene)
    return scene


def check_scene(scene: trimesh.Scene, state: dict[str, Any], models: dict[str, Any]) -> None:
    """Every instance of the JSON ``state`` is a node ``<class>/<id>`` at gltf_from_env @
    pose, carrying its library model's vertices."""
    assert {f"{o['object']}/{o['instance_id']}" for o in state["objects"]} == (
        set(scene.graph.nodes_geometry)
    )
    for o in state["objects"]:
        world, geometry = scene.graph.get(f"{o['object']}/{o['instance_id']}")
        np.testing.assert_allclose(world, GLTF_FROM_ENV @ np.array(o["pose"]), atol=1e-6)
        np.testing.assert_allclose(
            scene.geometry[geometry].vertices, models[o["object"]].positions, atol=1e-7
        )


def test_the_twin_as_glb_now_and_then_and_a_cloud_as_laz(
    tmp_path: Path,
    pg_url: str,
    redis_server: RedisServer,
    processes: Callable[..., Processes],
) -> None:
    procs = processes(database_url=pg_url, broker_url=redis_server.url)
    client = fake_pipeline_service(procs)
    files = library_files(tmp_path)
    for name, data in files.items():
        r = client.post(
            "/v1/objects",
            files={"file": (f"{name}.ply", data)},
            data={"name": name, "symmetry": "none"},
        )
        assert r.status_code == 202, r.text
        assert poll_job(client, r.json()["job"]["id"], 120)["state"] == "succeeded"
    models = {name: read_model(tmp_path / f"{name}.ply") for name in CLASSES}
    env_id = client.post("/v1/environments", json={"name": "cell-e", "classes": CLASSES}).json()[
        "id"
    ]
    snaps = [upload(client, env_id, scene, "v", CLASSES) for scene in SCENES]
    wait_until(
        lambda: client.get(f"/v1/environments/{env_id}").json()["twin"]["seq"] == len(SCENES),
        120,
        "the twin to take every snapshot",
        every_s=0.5,
    )

    state = client.get(f"/v1/environments/{env_id}/state").json()
    assert [o["object"] for o in state["objects"]] == ["drill"]
    check_scene(glb(client, env_id, tmp_path), state, models)

    then = client.get(f"/v1/environments/{env_id}/state", params={"snapshot": snaps[1]}).json()
    assert sorted(o["object"] for o in then["objects"]) == ["drill", "scan"]
    scene = glb(client, env_id, tmp_path, snapshot=snaps[1])
    check_scene(scene, then, models)
    scan = next(o for o in then["objects"] if o["object"] == "scan")
    points = scene.geometry[scene.graph.get(f"scan/{scan['instance_id']}")[1]]
    assert isinstance(points, trimesh.PointCloud)  # a cloud model is drawn as points

    r = client.get(f"/v1/snapshots/{snaps[2]}/pointcloud", params={"format": "laz"})
    assert r.status_code == 200 and r.headers["content-type"] == "application/vnd.laszip"
    ply = client.get(f"/v1/snapshots/{snaps[2]}/pointcloud")
    (tmp_path / "cloud.ply").write_bytes(ply.content)
    cloud = read_model(tmp_path / "cloud.ply")
    las = laspy.read(io.BytesIO(r.content))
    assert las.header.point_count == len(cloud.positions)
    assert np.abs(las.xyz - cloud.positions).max() <= 0.5e-4 + 1e-9
    # the fake pipeline's cloud has no colours: a point format without them
    assert cloud.colors is None and las.header.point_format.id == 0
    again = client.get(
        f"/v1/snapshots/{snaps[2]}/pointcloud", headers={"Accept": "application/vnd.laszip"}
    )
    assert again.content == r.content  # the kept file
