"""The inventory stage (workers.pipeline.inventory) on synthetic clouds: boxes on a floor
and on a table top seen by a ring of cameras, YOLO boxes from the true objects."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from tests.workers.pipeline.compare_scene import (
    CLASSES,
    NOISE,
    Obj,
    _sample_rect,
    bin_,
    capture,
    crate,
    ring_cameras,
)
from tests.workers.pipeline.test_compare_cli import write_capture
from workers.pipeline.__main__ import main
from workers.pipeline.compare.data import CaptureData
from workers.pipeline.errors import InputError
from workers.pipeline.inventory import (
    InventoryOptions,
    find_supports,
    inventory_options_from_json,
    standing_heights,
    take_inventory,
)
from workers.pipeline.model import PreparedModel, prepare_model

MODEL_DIRS: dict[str, Path] = {}
SIZES = {"crate": (0.4, 0.3, 0.3), "bin": (0.25, 0.25, 0.5), "cart": (0.3, 0.2, 0.025)}
CAMS = ring_cameras(n=10)


@pytest.fixture(scope="module")
def models(tmp_path_factory: pytest.TempPathFactory) -> dict[str, PreparedModel]:
    work = tmp_path_factory.mktemp("inventory_models")
    out = {}
    for name, size in SIZES.items():
        path = work / f"{name}.ply"
        o3d.io.write_triangle_mesh(path, o3d.geometry.TriangleMesh.create_box(*size))
        out[name] = prepare_model(path, work / name, name=name)
        MODEL_DIRS[name] = work / name
    return out


def _model_dir(model: PreparedModel) -> Path:
    """The work folder ``model`` was prepared in (``python -m workers.pipeline model``'s)."""
    return MODEL_DIRS[model.name]


def diameters(models: dict[str, PreparedModel]) -> dict[str, float]:
    return {name: m.diameter_m for name, m in models.items()}


def wall(rng: np.random.Generator, y: float = 2.0) -> np.ndarray:
    """A 4 m × 1.5 m wall at ``y`` standing on the floor (a vertical plane)."""
    pts = _sample_rect(rng, np.array([-2.0, y, 0.0]), np.array([4.0, 0, 0]), np.array([0, 0, 1.5]))
    return pts + rng.normal(0, NOISE, pts.shape)


def table_top(rng: np.random.Generator, height: float = 0.6) -> np.ndarray:
    """A 1.0 × 0.7 m table top at ``height`` centred on (−1.2, −1.0)."""
    pts = _sample_rect(
        rng, np.array([-1.7, -1.35, height]), np.array([1.0, 0, 0]), np.array([0, 0.7, 0])
    )
    return pts + rng.normal(0, NOISE, pts.shape)


def test_supports_are_the_floor_and_the_table_not_the_wall_nor_an_object_top() -> None:
    rng = np.random.default_rng(0)
    scene = capture([crate(0.6, 0.3)], CAMS, seed=1, extra=np.vstack([wall(rng), table_top(rng)]))
    supports = find_supports(scene.points_env, 0.6, InventoryOptions())
    assert [s.name for s in supports] == ["floor", "surface_1"]
    assert supports[0].height_m == pytest.approx(0.0, abs=0.002)
    assert supports[1].height_m == pytest.approx(0.6, abs=0.002)
    assert supports[0].noise_m == pytest.approx(NOISE, rel=0.3)
    # the floor beneath the crate was never sampled: its footprint is filled there
    assert supports[0].covers(np.array([[0.6, 0.3, 0.0]]))[0]
    assert supports[1].covers(np.array([[-1.2, -1.0, 0.7]]))[0]
    assert not supports[1].covers(np.array([[0.6, 0.3, 0.7]]))[0]


def test_standing_heights_are_above_the_highest_support_beneath() -> None:
    rng = np.random.default_rng(0)
    scene = capture([], CAMS, seed=1, extra=table_top(rng))
    supports = find_supports(scene.points_env, 0.6, InventoryOptions())
    probe = np.array([[-1.2, -1.0, 0.65], [-1.2, -1.0, 0.3], [1.0, 1.0, 0.1], [9.0, 9.0, 0.1]])
    heights, owner = standing_heights(probe, supports)
    np.testing.assert_allclose(heights[:3], [0.05, 0.3, 0.1], atol=0.003)
    assert owner.tolist() == [1, 0, 0, -1]
    assert np.isnan(heights[3])


def _four_objects() -> CaptureData:
    """Two crates and a bin on the floor, one crate on a table behind a wall."""
    rng = np.random.default_rng(3)
    table = [Obj(0, (-1.2, -1.0), (((0.0, 0.0), (0.4, 0.3, 0.3)),))]
    on_table = capture(table, [], seed=4, x_range=(-1.45, -0.95)).points_env
    on_table = on_table[on_table[:, 2] > 0.003]  # its box only: the floor part is left out
    on_table[:, 2] += 0.6
    objs = [crate(-0.8, 0.5), bin_(0.7, -0.6), crate(0.6, 0.8)]
    scene = capture(objs, CAMS, seed=1, extra=np.vstack([wall(rng), table_top(rng), on_table]))
    raised = Obj(0, (-1.2, -1.0), (((0.0, 0.0), (0.4, 0.3, 0.3)),))
    dets = capture([*objs, raised], CAMS, seed=9).detections  # boxes of the floor-level crate
    return CaptureData(scene.points_env, scene.cameras, _lift_boxes(dets, raised), None)


def test_every_object_is_found_with_its_class_and_place(
    models: dict[str, PreparedModel],
) -> None:
    """Four objects (:func:`_four_objects`), two instances of one class kept apart, each
    where it stands (within 1 cm)."""
    result = take_inventory(_four_objects(), CLASSES, diameters(models), models.__getitem__)
    found = sorted((o.object_name, *np.round(o.centroid_env[:2], 1)) for o in result.objects)
    assert found == [
        ("bin", 0.7, -0.6),
        ("crate", -1.2, -1.0),
        ("crate", -0.8, 0.5),
        ("crate", 0.6, 0.8),
    ]
    for obj in result.objects:
        assert obj.env_from_object is not None
        assert obj.identification["metric"] >= 0.5
        assert obj.pose_quality is not None and obj.pose_quality["reprojection"]["passed"]
    by_support = {o.support for o in result.objects if o.centroid_env[2] > 0.6}
    assert by_support == {"surface_1"}
    assert result.stats["objects"] == 4


def test_the_objects_do_not_depend_on_how_many_are_posed_at_once(
    models: dict[str, PreparedModel],
) -> None:
    """The segments posed one after the other and three at a time give the same objects,
    poses and figures, bit for bit, in the same order."""
    scene = _four_objects()

    def found(threads: int) -> list[tuple[str, list[list[float]], object]]:
        options = inventory_options_from_json({"pose": {"threads": threads}})
        result = take_inventory(scene, CLASSES, diameters(models), models.__getitem__, options)
        return [
            (o.object_name, np.asarray(o.env_from_object).tolist(), o.pose_quality)
            for o in result.objects
        ]

    one = found(1)
    assert len(one) == 4
    assert found(3) == one


def _lift_boxes(dets: Mapping[str, np.ndarray], raised: Obj) -> dict[str, np.ndarray]:
    """The YOLO rows of ``dets`` with the raised object's boxes re-made at table height."""
    lifted = Obj(raised.class_id, raised.xy, raised.parts)
    corners = lifted.corners() + np.array([0.0, 0.0, 0.6])
    out = {}
    for cam in CAMS:
        rows = [r for r in dets[cam.name] if not _is_box_of(r, cam, lifted.corners())]
        p = corners @ cam.cam_from_env[:3, :3].T + cam.cam_from_env[:3, 3]
        uv = (p[:, :2] / p[:, 2:]) @ cam.k[:2, :2].T + cam.k[:2, 2]
        x1, y1 = np.clip(uv.min(axis=0), 0, [cam.width, cam.height])
        x2, y2 = np.clip(uv.max(axis=0), 0, [cam.width, cam.height])
        if x2 - x1 > 4 and y2 - y1 > 4:
            w, h = cam.width, cam.height
            rows.append(
                np.array([0, (x1 + x2) / 2 / w, (y1 + y2) / 2 / h, (x2 - x1) / w, (y2 - y1) / h, 1])
            )
        out[cam.name] = np.array(rows).reshape(-1, 6)
    return out


def _is_box_of(row: np.ndarray, cam: object, corners: np.ndarray) -> bool:
    """Whether YOLO ``row`` is the box of the object with these corners in ``cam``."""
    p = corners @ cam.cam_from_env[:3, :3].T + cam.cam_from_env[:3, 3]  # type: ignore[attr-defined]
    uv = (p[:, :2] / p[:, 2:]) @ cam.k[:2, :2].T + cam.k[:2, 2]  # type: ignore[attr-defined]
    centre = uv.mean(axis=0) / [cam.width, cam.height]  # type: ignore[attr-defined]
    return bool(np.linalg.norm(row[1:3] - centre) < 0.03)


def test_an_unknown_object_is_not_an_object(models: dict[str, PreparedModel]) -> None:
    """A box no detector box covers (no class) stays out: 0 false objects."""
    unknown = Obj(0, (-0.2, -0.9), (((0.0, 0.0), (0.3, 0.2, 0.2)),))
    objs = [crate(-0.8, 0.5)]
    scene = capture([*objs, unknown], CAMS, seed=1)
    scene = CaptureData(scene.points_env, scene.cameras, capture(objs, CAMS, seed=1).detections)
    result = take_inventory(scene, CLASSES, diameters(models), models.__getitem__)
    assert [o.object_name for o in result.objects] == ["crate"]
    assert result.stats["segments"] == 2


def test_a_segment_whose_pose_misses_the_boxes_is_rejected(
    models: dict[str, PreparedModel],
) -> None:
    """A thin 10 cm column the detector calls a crate: identified as a crate (its boxes
    fit the column), but no pose of the 40 × 30 × 30 cm crate re-projects onto those boxes,
    so it is rejected, not an object; without the re-projection rule it is listed
    unverified."""
    column = Obj(0, (0.3, -0.4), (((0.0, 0.0), (0.1, 0.1, 0.45)),))
    scene = capture([column], CAMS, seed=1)
    strict = take_inventory(scene, CLASSES, diameters(models), models.__getitem__)
    assert strict.objects == ()
    assert [r["object"] for r in strict.rejected] == ["crate"]
    loose = take_inventory(
        scene,
        CLASSES,
        diameters(models),
        models.__getitem__,
        InventoryOptions(require_reprojection=False),
    )
    assert [o.object_name for o in loose.objects] == ["crate"]
    assert not loose.objects[0].verified


def _smear(rng: np.random.Generator, x: float, y: float, half: tuple[float, float]) -> np.ndarray:
    """The stereo's smear around a flat object's foot: a band 12 cm wide around its
    footprint (half sizes ``half``, centred at x, y), sloping from 2 cm high to 8 mm."""
    pts = rng.uniform(-1, 1, (30000, 2)) * (np.array(half) + 0.12)
    out = np.maximum(np.abs(pts[:, 0]) - half[0], np.abs(pts[:, 1]) - half[1])
    pts, out = pts[out > 0.002], out[out > 0.002]
    return np.column_stack([pts[:, 0] + x, pts[:, 1] + y, 0.02 - 0.012 * out / 0.12])


def test_a_segment_too_loose_for_its_boxes_is_named_by_its_posed_model(
    models: dict[str, PreparedModel],
) -> None:
    """A flat cart (2.5 cm high) with the smear around its foot: the segment's box is too
    loose for the cart's boxes (metric in [0.3, 0.5)); posed as a cart, the model's own
    boxes fit them, so it is found, its figures saying how; with the lower threshold off
    it is not."""
    rng = np.random.default_rng(5)
    cart = Obj(2, (0.2, -0.3), (((0.0, 0.0), SIZES["cart"]),))
    scene = capture([cart], CAMS, seed=1, extra=_smear(rng, 0.2, -0.3, (0.15, 0.1)))
    result = take_inventory(scene, CLASSES, diameters(models), models.__getitem__)
    assert [o.object_name for o in result.objects] == ["cart"]
    ident = result.objects[0].identification
    assert 0.3 <= ident["metric"] < 0.5 <= ident["model_metric"], ident
    # where the cart stands (the smear, 12 cm of it all round, pulls the fit by 1-2 cm)
    assert np.linalg.norm(result.objects[0].centroid_env[:2] - [0.2, -0.3]) < 0.03
    off = InventoryOptions(compare={"twin_identify_threshold": None})
    assert take_inventory(scene, CLASSES, diameters(models), models.__getitem__, off).objects == ()
    # boxed as a crate instead, the posed 30 cm crate does not fit the flat segment's boxes:
    # not an object, even where poses that miss the boxes are listed
    as_crate = {
        k: np.column_stack([np.zeros(len(v)), v[:, 1:]]) for k, v in scene.detections.items()
    }
    crate_scene = CaptureData(scene.points_env, scene.cameras, as_crate, None)
    loose = InventoryOptions(require_reprojection=False)
    result = take_inventory(crate_scene, CLASSES, diameters(models), models.__getitem__, loose)
    assert result.objects == ()
    assert [r["reason"].split(":")[0] for r in result.rejected] == ["named by no class"]


def test_a_class_without_a_prepared_model_is_listed_without_a_pose() -> None:
    scene = capture([bin_(0.7, -0.6)], CAMS, seed=1)

    def never(name: str) -> PreparedModel:
        raise AssertionError(f"{name} loaded")

    result = take_inventory(scene, CLASSES, {"crate": 0.6}, never)
    assert [(o.object_name, o.env_from_object) for o in result.objects] == [("bin", None)]


def test_no_support_no_objects_and_bad_inputs_are_refused() -> None:
    cloud = np.random.default_rng(0).normal(0, 1.0, (500, 3))
    result = take_inventory(CaptureData(cloud), CLASSES, {"crate": 0.6}, lambda n: None)  # type: ignore[arg-type,return-value]
    assert result.objects == () and result.supports == ()
    with pytest.raises(InputError, match="not one of the classes"):
        take_inventory(CaptureData(cloud), CLASSES, {"chair": 0.6}, lambda n: None)  # type: ignore[arg-type,return-value]
    with pytest.raises(InputError, match="unknown inventory options"):
        inventory_options_from_json({"band": 1})
    with pytest.raises(InputError, match="unknown inventory preset"):
        inventory_options_from_json({"preset": "nope"})
    with pytest.raises(InputError, match="unknown compare options"):
        inventory_options_from_json({"compare": {"nope": 1}})
    with pytest.raises(InputError, match="must be < 1"):
        InventoryOptions(grow_band_factor=1.5)


def test_options_round_trip() -> None:
    options = inventory_options_from_json({"preset": "fast", "band_min_m": 0.006})
    assert options.band_min_m == 0.006 and dict(options.pose) == {"preset": "fast"}
    assert json.loads(json.dumps(options.to_json()))["pose"] == {"preset": "fast"}


def test_the_cli_lists_the_objects_of_a_capture_folder(
    tmp_path: Path, models: dict[str, PreparedModel], capsys: pytest.CaptureFixture[str]
) -> None:
    write_capture(tmp_path / "capture", capture([crate(-0.8, 0.5), bin_(0.7, -0.6)], CAMS, 1))
    model_args = [f"--model={name}={_model_dir(models[name])}" for name in SIZES]
    out = tmp_path / "inventory.json"
    code = main(["inventory", str(tmp_path / "capture"), *model_args, "--out", str(out), "--quiet"])
    assert code == 0
    listed = json.loads(out.read_text())
    assert sorted(o["object"] for o in listed["objects"]) == ["bin", "crate"]
    assert [s["name"] for s in listed["supports"]] == ["floor"]
    assert main(["inventory", str(tmp_path / "capture"), "--options", "[1]"]) == 2
    assert "must be a JSON object" in capsys.readouterr().err


def test_patches_of_one_level_are_one_support_with_the_floor_noise() -> None:
    """A sparse floor patch cut off by a wall, with a 1.5 cm flat object on it, is floor:
    one support, the floor's noise, and the object's top stands above its band (the patch
    alone, mostly object, took the object's height for its noise: 9.7 mm, the object hidden)."""
    rng = np.random.default_rng(5)
    patch = _sample_rect(
        rng, np.array([-1.0, 2.2, -0.002]), np.array([0.5, 0, 0]), np.array([0, 0.4, 0])
    )[::3]
    flat = _sample_rect(
        rng, np.array([-0.9, 2.3, 0.015]), np.array([0.3, 0, 0]), np.array([0, 0.2, 0])
    )
    beneath = (np.abs(patch[:, 0] + 0.75) < 0.15) & (np.abs(patch[:, 1] - 2.4) < 0.1)
    patch = patch[~beneath] + rng.normal(0, NOISE, (int((~beneath).sum()), 3))
    flat += rng.normal(0, NOISE, flat.shape)
    scene = capture([], CAMS, seed=1, extra=np.vstack([wall(rng), patch, flat]))
    supports = find_supports(scene.points_env, 0.3, InventoryOptions())
    assert [s.name for s in supports] == ["floor"]
    floor = supports[0]
    assert floor.area_m2 > 10 and floor.covers(np.array([[-0.75, 2.4, 0.0]]))[0]
    assert floor.noise_m == pytest.approx(NOISE, rel=0.3)
    heights, owner = standing_heights(flat, supports)
    assert (owner == 0).all()
    assert np.mean(heights > 3.0 * floor.noise_m) > 0.95


def test_a_table_top_reconstructed_with_holes_is_still_a_support() -> None:
    """A plain table top whose cloud has holes (4 of 10 blocks of 6 cm kept): the closing
    bridges them, where one cell of closing left patches each smaller than a support."""
    rng = np.random.default_rng(3)
    top = table_top(rng)
    block = np.floor(top[:, :2] / 0.06).astype(int)
    keys, inverse = np.unique(block, axis=0, return_inverse=True)
    top = top[(rng.uniform(size=len(keys)) < 0.4)[inverse.ravel()]]
    scene = capture([crate(0.6, 0.3)], CAMS, seed=1, extra=top)
    supports = find_supports(scene.points_env, 0.6, InventoryOptions())
    assert [s.name for s in supports] == ["floor", "surface_1"]
    assert supports[1].height_m == pytest.approx(0.6, abs=0.003)
    assert supports[1].area_m2 > 0.25
    one_cell = find_supports(scene.points_env, 0.6, InventoryOptions(support_closing_cells=1))
    assert [s.name for s in one_cell] == ["floor"]
