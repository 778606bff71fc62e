"""Accuracy of the whole pipeline on generated YCB scenes with ground truth.

    python -m bench.scenarios_bench [--quick] [--scenarios moved,multiple] [--seed 1]
    python -m bench.scenarios_bench --set tuning|test [--real-camera] [--quick] [--worlds a,b]

For each scenario the synth generator lays out YCB objects (Calli et al. 2015, CC BY 4.0;
read from ../shared/data/ycb or $TWINDELTA_SHARED_DATA/ycb), renders both captures, and
the pipeline runs directly (no HTTP): reconstruct both captures (SfM + markers; the after
capture refined against the before cloud, as the snapshot job does), compare at the
thesis's thresholds (the "thesis" preset at mean + k·σ, k ∈ {0, 0.5, 1, 1.5}) and with
our default options ("ours"), then pose every identified change with the comparison job's
own pose step (:func:`workers.pipeline.pose.posing.pose_changes`) and score against the ground
truth (:func:`workers.demo.evaluate.match_changes`). Each found change also gets the oracle
metric (:func:`oracle_metrics`: what a perfect cluster would score against the same
detections). Also: every scenario again with a clean detector (no misses or false boxes,
jitter kept), one robustness run with 10 % missed and 5 % false boxes, reconstruction
quality per capture against the true surfaces, and stage timings. Writes
``bench/results/scenarios.json``.

With ``--set`` the scenes are the worlds of :mod:`bench.worlds` instead: the tuning set
(tune options and thresholds on it only) or the test set (other objects, rooms and seeds;
report, never tune), each world with its own objects as the library, distractors that must
come out unidentified, and with ``--real-camera`` each world again through a real camera
(lens distortion declared or left to SfM, exposure and white balance, blur, noise, JPEG).
Writes ``bench/results/scenarios_<set>.json`` with the set's name in it.

Reconstructions are cached under the work folder by a hash of their inputs (the before
capture is the same in every scenario of one seed), prepared models under bench/.cache/.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import platform
import shutil
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.formats.cameras import read_cameras
from bench.reconstruct_bench import (
    camera_metrics,
    cloud_metrics,
    visible_surface_samples,
)
from bench.worlds import SETS, World, real_camera
from workers.demo.evaluate import match_changes
from workers.pipeline.compare.data import CaptureData, TwinInstance
from workers.pipeline.compare.files import cameras_from_file, read_cameras_file
from workers.pipeline.compare.identify import identify, yolo_to_boxes
from workers.pipeline.compare.options import options_from_json
from workers.pipeline.compare.results import CompareResult
from workers.pipeline.compare.stage import compare_snapshots
from workers.pipeline.geometry import transform_points
from workers.pipeline.model import PreparedModel, prepare_model
from workers.pipeline.pose.posing import pose_changes
from workers.pipeline.reconstruct import options_from_preset, parse_cameras, reconstruct
from workers.pipeline.reconstruct.fusion import read_ply
from workers.pipeline.synth import (
    PRESETS,
    SCENARIOS,
    PathOptions,
    build_scenario,
    distractor_model,
    generate,
    load_model,
    load_true_surfaces,
    render_capture,
    visible_boxes,
)

ROOT = Path(__file__).resolve().parents[1]
TMP = Path(os.environ.get("TWINDELTA_BENCH_TMP", "/tmp/twindelta_bench"))
CACHE = ROOT / "bench" / ".cache"
#: the reconstruct stage's code: a cached cloud built by other code is not reused
RECONSTRUCT_SOURCE = ROOT / "workers" / "pipeline" / "reconstruct"
# power_drill first; the last non-symmetric object (hammer) is the generator's spare, the
# one that appears in added / swapped / multiple; master_chef_can is the symmetric one.
OBJECTS = ["power_drill", "large_clamp", "mustard_bottle", "master_chef_can", "hammer"]
THESIS_K = (0.0, 0.5, 1.0, 1.5)
QUICK_SCENARIOS = ("moved", "symmetric_moved", "multiple", "no_change")
WORK_RADIUS_M = 1.5
TARGETS = {
    "found_right_type_and_object": 1.0,
    "false_changes": 0,
    "true_class_metric_min": 0.8,
    "other_class_metric_max": 0.1,
    "translation_median_m": 0.005,
    "rotation_median_deg": 1.0,
    "translation_max_m": 0.01,
    "rotation_max_deg": 3.0,
    "flips": 0,
}
FLIP_DEG = 10.0  # a rotation error above this is a wrong pose hypothesis, not imprecision


def ycb_dir() -> Path:
    env = os.environ.get("TWINDELTA_SHARED_DATA")
    base = Path(env) if env else Path(__file__).resolve().parents[2] / "shared" / "data"
    return base / "ycb"


def _hash_inputs(*parts: Any) -> str:
    h = hashlib.sha256()
    for part in parts:
        if isinstance(part, Path) and part.is_dir():
            for f in sorted(part.iterdir()):
                h.update(f.name.encode())
                h.update(f.read_bytes())
        elif isinstance(part, Path) and part.is_file():
            h.update(part.read_bytes())
        else:
            h.update(repr(part).encode())
    return h.hexdigest()[:16]


def _source_digest(package: Path) -> str:
    """SHA-256 (16 hex digits) of the ``*.py`` files under ``package``, by relative path."""
    h = hashlib.sha256()
    for f in sorted(package.rglob("*.py")):
        h.update(str(f.relative_to(package)).encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def _timed(timings: dict[str, float], name: str, t0: float) -> None:
    timings[name] = round(timings.get(name, 0.0) + time.perf_counter() - t0, 3)


def scene(work: Path, scenario: str, seed: int, synth: Any, tag: str, models: Any) -> Path:
    """Generate (or reuse) the scenario under ``work/scenes``; returns its folder."""
    out = work / "scenes" / f"{tag}_{scenario}_s{seed}"
    if (out / "after" / "cameras.json").is_file() and (out / "ground_truth.json").is_file():
        return out
    shutil.rmtree(out, ignore_errors=True)
    generate(out, scenario, seed, synth, models)
    return out


#: SfM threads of every bench reconstruction: with one, a fresh reconstruction repeats
#: bit for bit (multithreaded matching and mapping do not); the service keeps all cores
BENCH_SFM_THREADS = 1
#: the pose step's figures behind ``verified`` kept per pose, to study the checks
QUALITY_FIGURES = (
    "fitness",
    "inlier_rmse",
    "cluster_coverage",
    "runner_up_ratio",
    "rotation_slack_deg",
    "final_turn_deg",
    "visible_fitness",
    "settled_by_visibility",
    "settled_by_reprojection",
    "settled_by_outline",
    "settled_by_photo_edges",
    "photo_edges",
    "reprojection",
)


def pose_figures(quality: dict[str, Any]) -> dict[str, Any]:
    """The :data:`QUALITY_FIGURES` of a ``pose_quality`` object (those it has)."""
    return {k: v for k, v in quality.items() if k in QUALITY_FIGURES}


def reconstruct_capture(
    work: Path, scene_dir: Path, capture: str, preset: str, reference_cloud: Path | None
) -> tuple[Path, dict[str, Any], bool]:
    """Reconstruct ``capture`` like the snapshot job (intrinsics + markers, no poses) but
    with ``BENCH_SFM_THREADS``, cached by a hash of the images, the resolved options, the
    reconstruct stage's source and the reference cloud (a changed default or stage rebuilds
    the cloud); returns (work dir, quality, whether it was cached)."""
    images = scene_dir / capture / "images"
    intrinsics = _declared_intrinsics(scene_dir, capture)
    reference = json.loads((scene_dir / "reference.json").read_text())
    options = options_from_preset(preset, num_threads=BENCH_SFM_THREADS)
    key = _hash_inputs(
        images, options, _source_digest(RECONSTRUCT_SOURCE), intrinsics, reference, reference_cloud
    )
    out = work / "reconstructions" / key
    if (out / "quality.json").is_file() and (out / "cloud.ply").is_file():
        return out, json.loads((out / "quality.json").read_text()), True
    shutil.rmtree(out, ignore_errors=True)
    res = reconstruct(
        images,
        out,
        options,
        None if intrinsics is None else parse_cameras({"intrinsics": intrinsics}),
        reference,
        reference_cloud,
    )
    return out, res.quality, False


def _declared_intrinsics(scene_dir: Path, capture: str) -> dict[str, Any] | None:
    """The capture's cameras.json intrinsics; None when it declares none (self-calibration)."""
    path = scene_dir / capture / "cameras.json"
    if not path.is_file():
        return None
    intrinsics = json.loads(path.read_text()).get("intrinsics")
    return None if intrinsics is None else dict(intrinsics)


def _pinhole(intrinsics: dict[str, Any]) -> dict[str, Any]:
    """PINHOLE intrinsics [fx, fy, cx, cy] of any cameras.json model (the lens left out)."""
    camera = read_cameras({"intrinsics": intrinsics}).intrinsics
    assert camera is not None
    return {**intrinsics, "model": "PINHOLE", "params": list(camera.pinhole)}


def cloud_digest(recon: Path) -> str:
    """The first 16 hex digits of the SHA-256 of a reconstruction's cloud.ply: two bench runs
    on the same clouds show the same digest (SfM repeats bit for bit on one kind of machine,
    not across kinds)."""
    return hashlib.sha256((recon / "cloud.ply").read_bytes()).hexdigest()[:16]


def machine() -> dict[str, Any]:
    """The CPU the figures come from, by model name, and how many (clouds differ from one
    CPU to another)."""
    cpuinfo = Path("/proc/cpuinfo")
    lines = cpuinfo.read_text().splitlines() if cpuinfo.is_file() else []
    model = next(
        (line.split(":", 1)[1].strip() for line in lines if line.startswith("model name")),
        platform.machine(),
    )
    return {"cpu": model, "cpus": os.cpu_count()}


def capture_quality(scene_dir: Path, capture: str, recon: Path) -> dict[str, Any]:
    """Cloud-to-true-surface distances, completeness (all and within WORK_RADIUS_M of the
    scene centre) and camera-centre errors against the true poses in ground_truth.json."""
    cached = recon / f"metrics_{capture}.json"
    if cached.is_file():
        return dict(json.loads(cached.read_text()))
    gt = json.loads((scene_dir / "ground_truth.json").read_text())
    # the true camera (lens included) of an extended scene, else the declared one; the
    # visibility samples use its pinhole part (a lens moves them by a few pixels at most)
    intrinsics = gt.get("camera") or _declared_intrinsics(scene_dir, capture)
    assert intrinsics is not None
    cams = {"intrinsics": _pinhole(intrinsics), "poses": gt["camera_poses"][capture]}
    meshes = load_true_surfaces(scene_dir, capture)
    cloud, _ = read_ply(recon / "cloud.ply")
    visible = visible_surface_samples(meshes, cams)
    views = cameras_from_file(read_cameras_file(recon / "cameras.json"))

    class _View:  # camera_metrics wants .name and .env_from_cam
        def __init__(self, name: str, env_from_cam: np.ndarray) -> None:
            self.name, self.env_from_cam = name, env_from_cam

    out = {
        **cloud_metrics(cloud, meshes, visible, WORK_RADIUS_M),
        **camera_metrics([_View(v.name, np.linalg.inv(v.cam_from_env)) for v in views], cams),
    }
    cached.write_text(json.dumps(out, indent=1))
    return out


def capture_data(scene_dir: Path, capture: str, recon: Path, quality: dict[str, Any]) -> Any:
    """The compare stage's view of a reconstructed capture (as workers/comparison.py builds
    it): cloud, cameras from cameras.json, YOLO rows from the capture's labels."""
    import open3d as o3d

    cloud = o3d.io.read_point_cloud(str(recon / "cloud.ply"))
    detections = {}
    for label in sorted((scene_dir / capture / "labels").glob("*.txt")):
        image = next((scene_dir / capture / "images").glob(label.stem + ".*")).name
        rows = [[float(v) for v in line.split()] for line in label.read_text().splitlines()]
        detections[image] = np.asarray(rows, dtype=np.float64).reshape(-1, 6)
    return CaptureData(
        points_env=np.asarray(cloud.points, dtype=np.float64),
        cameras=cameras_from_file(read_cameras_file(recon / "cameras.json")),
        detections=detections,
        colors=np.asarray(cloud.colors, dtype=np.float64) if cloud.has_colors() else None,
        alignment_residual_m=float(quality.get("alignment_residual_m") or 0.0),
        photos={p.name: p for p in sorted((scene_dir / capture / "images").iterdir())},
    )


def prepared_models(names: list[str]) -> tuple[dict[str, PreparedModel], dict[str, float]]:
    """Library models prepared from the YCB meshes once (cached under bench/.cache/)."""
    out, seconds = {}, {}
    for name in names:
        t0 = time.perf_counter()
        out[name] = prepare_model(
            ycb_dir() / name / "textured.obj", CACHE / "models" / name, name=name
        )
        seconds[name] = round(time.perf_counter() - t0, 3)
    return out, seconds


def twin_before(truth: dict[str, Any], models: dict[str, PreparedModel]) -> list[TwinInstance]:
    """The twin as it stands before: the before capture's true placements."""
    return [
        TwinInstance(
            instance_id=p["instance_id"],
            object_name=p["object"],
            env_from_object=np.asarray(p["env_from_object"]),
            centroid_env=transform_points(
                np.asarray(p["env_from_object"]), models[p["object"]].centre_object[None, :]
            )[0],
        )
        for p in truth["before"]
    ]


def cluster_table(result: CompareResult) -> list[dict[str, Any]]:
    """The thesis's table: identification metric per (cluster, class), for the clusters
    with any detector evidence (the rest are counted in ``n_clusters`` only)."""
    return [
        {
            "id": c.id,
            "side": c.side,
            "n_points": c.n_points,
            "object": c.object_name,
            "centroid": [round(v, 4) for v in c.centroid.tolist()],
            "metrics": {k: round(v, 4) for k, v in c.metrics.items()},
        }
        for c in result.clusters
        if any(v > 0 for v in c.metrics.values())
    ]


def score(
    truth: dict[str, Any], records: list[dict[str, Any]], result: CompareResult
) -> dict[str, Any]:
    """Changes found with the right type and object, false changes, identification metrics
    of the true class and the best other class, symmetry-aware pose errors, and what came
    of each distractor (:func:`score_distractors`)."""
    library = [c for c in truth["changes"] if not c.get("unidentified")]
    matches, unmatched = match_changes({**truth, "changes": library}, records)
    distractors = score_distractors(truth, unmatched)
    explained = {d["cluster"] for d in distractors if d["outcome"] == "unidentified"}
    metrics_by_cluster = {c.id: c.metrics for c in result.clusters}
    rows = []
    for m in matches:
        row: dict[str, Any] = {"type": m.truth["type"], "object": m.truth["object"]}
        if m.found is not None:
            row["cluster"] = m.found["cluster"]["id"]
            metrics = metrics_by_cluster.get(m.found["cluster"]["id"], {})
            symmetric = m.rpy_error_deg is not None and any(map(math.isnan, m.rpy_error_deg))
            quality = m.found.get("pose_quality") or {}
            row.update(
                found=True,
                true_class_metric=metrics.get(m.truth["object"], 0.0),
                other_class_metric_max=max(
                    (v for k, v in metrics.items() if k != m.truth["object"]), default=0.0
                ),
                verified=quality.get("verified"),
                pose_reasons=quality.get("reasons"),
                pose_figures=pose_figures(quality),
                translation_error_m=m.translation_error_m,
                rotation_error_deg=m.rotation_error_deg,
                # per-axis errors of the model origin mean nothing for a symmetric object
                # (any rotation about its axis is right); its translation_error_m is
                # minimised over the symmetry group
                xyz_error_m=None if symmetric else m.xyz_error_m,
                rpy_error_deg=None if symmetric else m.rpy_error_deg,
                symmetric=symmetric,
            )
        else:
            row["found"] = False
        rows.append(row)
    return {
        "changes": rows,
        # a change to the twin that no true change explains (an identified object)
        "false_changes": [
            {"type": f["type"], "object": f.get("object"), "cluster": f["cluster"]["id"]}
            for f in unmatched
            if f.get("object") is not None
        ],
        # clusters no class explains (reported, never applied to the twin), distractors'
        # own aside
        "unidentified": sum(
            1 for f in unmatched if f.get("object") is None and f["cluster"]["id"] not in explained
        ),
        "distractors": distractors,
    }


DISTRACTOR_REACH_M = 0.15  # a found change this far outside a distractor's footprint is not its


def score_distractors(
    truth: dict[str, Any], unmatched: list[dict[str, Any]]
) -> list[dict[str, Any]]:
    """Per true distractor change (``unidentified`` in the ground truth): the found change
    whose cluster centroid lies nearest its footprint centre in xy, within its footprint
    radius + DISTRACTOR_REACH_M; ``outcome`` "unidentified" (right), "identified" (a
    library object: wrong, also counted as a false change) or "missed"."""
    out = []
    for change in truth["changes"]:
        if not change.get("unidentified"):
            continue
        centre = np.asarray(change["pose"])[:2, 3]
        model = distractor_model(change["distractor"])
        reach = model.footprint_radius_m() + DISTRACTOR_REACH_M
        distances = [
            (float(np.linalg.norm(np.asarray(f["cluster"]["centroid"][:2]) - centre)), f)
            for f in unmatched
        ]
        near = sorted((t for t in distances if t[0] <= reach), key=lambda t: t[0])
        row: dict[str, Any] = {"distractor": change.get("distractor"), "outcome": "missed"}
        if near:
            dist, found = near[0]
            row.update(
                outcome="unidentified" if found.get("object") is None else "identified",
                identified_as=found.get("object"),
                cluster=found["cluster"]["id"],
                distance_m=round(dist, 3),
            )
        out.append(row)
    return out


def oracle_metrics(
    scenario: str,
    seed: int,
    synth: Any,
    ycb: list[Any],
    captures: dict[str, CaptureData],
    classes: list[str],
    rows: list[dict[str, Any]],
    result: CompareResult,
) -> None:
    """Adds to each found change row the identification metric a perfect cluster would get
    from these detections (``oracle_true_class_metric``): its box in every view is the true
    visible box of the object (the generator's instance buffer, re-rendered), counted in
    every view where the detector could fire (≥ its ``min_visible_px``), scored by
    :func:`identify` against the capture's labels (``captures[name].detections``). It is the
    ceiling set by the detector's misses and box jitter alone; the row's
    ``true_class_metric`` is ours."""
    truth_scene = build_scenario(scenario, ycb, seed, synth)
    width, height = synth.camera.width, synth.camera.height
    clusters = {c.id: c for c in result.clusters}
    rendered: dict[str, tuple[list[str], list[dict[int, Any]]]] = {}
    for row in rows:
        cluster = clusters.get(row.get("cluster", -1))
        if cluster is None:
            continue
        capture = "after" if cluster.side == "added" else "before"
        if capture not in rendered:
            names, boxes = [], []
            for name, view in render_capture(truth_scene, capture, synth):
                names.append(name)
                boxes.append(visible_boxes(view.instance, synth.detection.min_visible_px))
            rendered[capture] = (names, boxes)
        names, boxes = rendered[capture]
        placements = truth_scene.capture(capture)
        same = [i for i, p in enumerate(placements) if p.model.name == row["object"]]
        if not same:
            continue
        index = min(
            same,
            key=lambda i: float(
                np.linalg.norm(placements[i].env_from_object[:3, 3] - cluster.centroid)
            ),
        )
        truth_boxes = {
            v: np.asarray(b[index][:4], dtype=np.float64) for v, b in enumerate(boxes) if index in b
        }
        labels = captures[capture].detections
        dets = [yolo_to_boxes(labels.get(name, np.zeros((0, 6))), width, height) for name in names]
        table = identify([truth_boxes], dets, classes)
        k = classes.index(row["object"])
        row["oracle_true_class_metric"] = float(table.metric[0, k])
        row["oracle_views_visible"] = int(table.occurrences[0])
        row["oracle_views_detected"] = int(table.overlaps[0, k])
        row["oracle_mean_iou"] = float(table.mean_iou[0, k])


def run_scenario(
    work: Path,
    scenario: str,
    seed: int,
    synth: Any,
    tag: str,
    recon_preset: str,
    ycb: list[Any],
    models: dict[str, PreparedModel],
    thesis_k: tuple[float, ...] = THESIS_K,
) -> dict[str, Any]:
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    scene_dir = scene(work, scenario, seed, synth, tag, ycb)
    _timed(timings, "generate", t0)
    truth = json.loads((scene_dir / "ground_truth.json").read_text())
    classes: list[str] = truth["classes"]

    t0 = time.perf_counter()
    before_dir, before_q, before_cached = reconstruct_capture(
        work, scene_dir, "before", recon_preset, None
    )
    _timed(timings, "reconstruct_before", t0)
    t0 = time.perf_counter()
    after_dir, after_q, after_cached = reconstruct_capture(
        work, scene_dir, "after", recon_preset, before_dir / "cloud.ply"
    )
    _timed(timings, "reconstruct_after", t0)
    t0 = time.perf_counter()
    quality = {
        "before": {
            **capture_quality(scene_dir, "before", before_dir),
            "images_registered": before_q.get("images_registered"),
            "images_total": before_q.get("images_total"),
            "reprojection_error_px": before_q.get("mean_reprojection_error_px"),
            "stage_timings_s": before_q.get("timings_s"),
            "cached": before_cached,
            "cloud_sha256": cloud_digest(before_dir),
        },
        "after": {
            **capture_quality(scene_dir, "after", after_dir),
            "images_registered": after_q.get("images_registered"),
            "images_total": after_q.get("images_total"),
            "reprojection_error_px": after_q.get("mean_reprojection_error_px"),
            "alignment_residual_m": after_q.get("alignment_residual_m"),
            "stage_timings_s": after_q.get("timings_s"),
            "cached": after_cached,
            "cloud_sha256": cloud_digest(after_dir),
        },
    }
    _timed(timings, "quality_metrics", t0)

    before = capture_data(scene_dir, "before", before_dir, before_q)
    after = capture_data(scene_dir, "after", after_dir, after_q)
    twin = twin_before(truth, models)
    diameters = {name: models[name].diameter_m for name in classes}
    thresholds: dict[str, Any] = {}
    variants = [
        (f"thesis_k{k:g}", "thesis", {"threshold": {"kind": "mean_std", "k": k}}) for k in thesis_k
    ]
    variants.append(("ours", "default", {}))
    ours: CompareResult | None = None
    for name, preset, overrides in variants:
        t0 = time.perf_counter()
        options = options_from_json(preset, overrides)
        result = compare_snapshots(before, after, twin, classes, diameters, options)
        _timed(timings, f"compare_{name}", t0)
        data = result.to_json()
        thresholds[name] = {
            "preset": preset,
            "threshold": options.threshold.to_json(),
            "distances": data["distances"],
            "n_clusters": len(result.clusters),
            "clusters": cluster_table(result),
            "changes": [
                {"type": c.type, "object": c.object_name, "cluster": c.cluster.id}
                for c in result.changes
                if c.object_name is not None
            ],
            "unidentified": sum(1 for c in result.changes if c.object_name is None),
            "stage_timings_s": result.stats.get("timings_s"),
        }
        if name == "ours":
            ours = result
    assert ours is not None
    t0 = time.perf_counter()
    records = pose_changes(
        ours, after, classes, models, models.__getitem__, options_from_json("default")
    )
    _timed(timings, "pose", t0)
    scored = score(truth, records, ours)
    t0 = time.perf_counter()
    captures = {"before": before, "after": after}
    oracle_metrics(scenario, seed, synth, ycb, captures, classes, scored["changes"], ours)
    _timed(timings, "oracle", t0)
    return {
        "scene": str(scene_dir),
        "truth": [
            {"type": c["type"], "object": c["object"], "replaced_object": c["replaced_object"]}
            for c in truth["changes"]
        ],
        "reconstruction": quality,
        "thresholds": thresholds,
        "ours": scored,
        "timings_s": timings,
    }


def summarise(runs: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Headline figures over every scenario and each against its target."""
    rows = [r for run in runs.values() for r in run["ours"]["changes"]]
    found = [r for r in rows if r["found"]]
    posed = [r for r in found if r.get("translation_error_m") is not None]
    dt = [r["translation_error_m"] for r in posed]
    dr = [r["rotation_error_deg"] for r in posed]
    false = sum(len(run["ours"]["false_changes"]) for run in runs.values())
    unidentified = sum(run["ours"]["unidentified"] for run in runs.values())
    true_metric = [r["true_class_metric"] for r in found]
    oracle = [r["oracle_true_class_metric"] for r in found if "oracle_true_class_metric" in r]
    of_oracle = [
        r["true_class_metric"] / r["oracle_true_class_metric"]
        for r in found
        if r.get("oracle_true_class_metric")
    ]
    other_metric = [r["other_class_metric_max"] for r in found]
    # per-axis errors only where they mean something: non-symmetric objects (their rows
    # carry them) whose pose is not a flip (a flip's Euler angles are ~180° on two axes
    # and arbitrary on the third; flips are counted on their own)
    per_axis = [
        r for r in posed if r.get("xyz_error_m") is not None and r["rotation_error_deg"] <= FLIP_DEG
    ]
    xyz_rows = [r["xyz_error_m"] for r in per_axis]
    xyz = np.abs(np.asarray(xyz_rows)) if xyz_rows else np.zeros((0, 3))
    rpy = [r["rpy_error_deg"] for r in per_axis if r.get("rpy_error_deg") is not None]
    rpy_abs = np.abs(np.asarray(rpy)) if rpy else np.zeros((0, 3))

    def med(a: list[float]) -> float | None:
        return float(statistics.median(a)) if a else None

    figures: dict[str, Any] = {
        "true_changes": len(rows),
        "found_right_type_and_object": len(found) / len(rows) if rows else 1.0,
        "false_changes": false,
        "unidentified_clusters": unidentified,
        "verified_poses": sum(1 for r in posed if r.get("verified")),
        "true_class_metric_min": min(true_metric) if true_metric else None,
        # the same metric for a perfect cluster (true boxes) against the same detections:
        # the ceiling the detector's misses and jitter leave (see oracle_metrics)
        "oracle_true_class_metric_min": min(oracle) if oracle else None,
        "true_class_metric_of_oracle_min": min(of_oracle) if of_oracle else None,
        "other_class_metric_max": max(other_metric) if other_metric else None,
        "posed": len(posed),
        "translation_median_m": med(dt),
        "rotation_median_deg": med(dr),
        "translation_max_m": max(dt) if dt else None,
        "rotation_max_deg": max(dr) if dr else None,
        "flips": sum(1 for v in dr if v > FLIP_DEG),
        "per_axis_poses": len(per_axis),
        "xyz_abs_median_m": np.median(xyz, axis=0).tolist() if len(xyz) else None,
        "xyz_abs_max_m": xyz.max(axis=0).tolist() if len(xyz) else None,
        "rpy_abs_median_deg": np.median(rpy_abs, axis=0).tolist() if len(rpy_abs) else None,
        "rpy_abs_max_deg": rpy_abs.max(axis=0).tolist() if len(rpy_abs) else None,
    }
    verdicts = {}
    for key, target in TARGETS.items():
        value = figures.get(key)
        if value is None:
            verdicts[key] = "n/a"
        elif key in ("found_right_type_and_object", "true_class_metric_min"):
            verdicts[key] = "met" if value >= target else "not met"
        else:
            verdicts[key] = "met" if value <= target else "not met"
    distractors = [d for run in runs.values() for d in run["ours"].get("distractors", [])]
    if distractors:
        # a distractor must come out unidentified, never as a library object
        outcomes = [d["outcome"] for d in distractors]
        figures["distractors"] = len(distractors)
        figures["distractors_unidentified"] = outcomes.count("unidentified")
        figures["distractors_identified_as_library"] = outcomes.count("identified")
        figures["distractors_missed"] = outcomes.count("missed")
        verdicts["distractors_identified_as_library"] = (
            "met" if figures["distractors_identified_as_library"] == 0 else "not met"
        )
    figures["targets"] = TARGETS
    figures["verdicts"] = verdicts
    return figures


TUNING_RULE = (
    "tune options and thresholds only on the tuning set; the test set (other objects, rooms "
    "and seeds) is reported, never tuned on"
)


def run_world(
    args: argparse.Namespace,
    world: World,
    synth: Any,
    variant: str,
    ycb: dict[str, Any],
    models: dict[str, PreparedModel],
    recon_preset: str,
) -> dict[str, Any]:
    """One world of a set through the whole pipeline (:func:`run_scenario`), its scene
    cached under a tag holding a hash of its options."""
    tag = f"{args.set}_{world.name}_{variant}_{_hash_inputs(repr(synth), world)[:8]}"
    run = run_scenario(
        args.work,
        world.scenario,
        world.seed,
        synth,
        tag,
        recon_preset,
        [ycb[n] for n in world.objects],
        models,
        (),
    )
    run["world"] = {
        "scenario": world.scenario,
        "objects": list(world.objects),
        "room": world.room,
        "path": world.path,
        "seed": world.seed,
        "target": world.target,
        "distractors": list(world.distractors),
    }
    run["effects"] = vars(synth.effects) if synth.effects.active else None
    return run


def run_world_set(args: argparse.Namespace) -> int:
    """``--set tuning|test``: every world of the set (and with ``--real-camera`` each one
    again through a real camera), reported per variant with the set's name; ``--worlds``
    keeps a subset (each world keeps the lens it has in the whole set); writes
    ``bench/results/scenarios_<set>.json`` unless ``--out`` says otherwise. Returns 2 naming
    an unknown world."""
    t_start = time.perf_counter()
    worlds = SETS[args.set]
    if args.worlds:
        wanted = args.worlds.split(",")
        unknown = sorted(set(wanted) - {w.name for w in worlds})
        if unknown:
            print(f"unknown worlds of the {args.set} set: {', '.join(unknown)}", file=sys.stderr)
            return 2
        worlds = tuple(w for w in worlds if w.name in wanted)
    base, recon_preset = PRESETS["bench"], "default"
    if args.quick:
        base, recon_preset = replace(base, path=PathOptions(n_views=24)), "fast"
    names = sorted({n for w in worlds for n in w.objects})
    ycb = {n: load_model(ycb_dir() / n / "textured.obj", n) for n in names}
    models, prep_s = prepared_models(names)
    out = args.out or ROOT / "bench" / "results" / f"scenarios_{args.set}.json"
    report: dict[str, Any] = {
        "what": f"whole pipeline on the {args.set} worlds of bench/worlds.py vs ground truth",
        "set": args.set,
        "rule": TUNING_RULE,
        "quick": args.quick,
        "worlds": [w.name for w in worlds],
        "objects": names,
        "synth": {
            "preset": "bench",
            "n_views": base.path.n_views,
            "detection": vars(base.detection),
        },
        "reconstruct_preset": recon_preset,
        "compare_options": options_from_json("default").to_json(),
        "model_prepare_s": prep_s,
        "load_average": os.getloadavg(),
        "machine": machine(),
        "variants": {},
    }
    variants = [("ideal_camera", False)] + ([("real_camera", True)] if args.real_camera else [])
    failed = False
    for variant, real in variants:
        runs: dict[str, Any] = {}
        report["variants"][variant] = {"scenarios": runs}
        for world in worlds:
            synth = world.options(base)
            if real:
                synth = real_camera(synth, SETS[args.set].index(world))
            print(f"[scenarios:{args.set}:{variant}] {world.name} ...", flush=True)
            try:
                runs[world.name] = run_world(args, world, synth, variant, ycb, models, recon_preset)
            except Exception as exc:  # one failing world must not lose the others
                runs[world.name] = {"error": f"{type(exc).__name__}: {exc}"}
                failed = True
                print(f"[scenarios:{args.set}] {world.name} failed: {exc}", flush=True)
            ok = {k: v for k, v in runs.items() if "error" not in v}
            report["variants"][variant]["summary"] = summarise(ok) if ok else None
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(json.dumps(report, indent=1, default=float))
    report["load_average_end"] = os.getloadavg()
    report["total_s"] = round(time.perf_counter() - t_start, 1)
    out.write_text(json.dumps(report, indent=1, default=float))
    print(json.dumps({k: v.get("summary") for k, v in report["variants"].items()}, default=float))
    return 1 if failed else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="4 scenarios, 24 views, fast MVS")
    parser.add_argument("--scenarios", default=None, help="comma-separated subset")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--work", type=Path, default=TMP / "scenarios")
    parser.add_argument(
        "--out", type=Path, help="result file (default bench/results/scenarios[_<set>].json)"
    )
    parser.add_argument("--no-robustness", action="store_true")
    parser.add_argument(
        "--no-clean-detector", action="store_true", help="skip the run without missed boxes"
    )
    parser.add_argument(
        "--set", choices=sorted(SETS), help="the worlds of bench/worlds.py instead of --scenarios"
    )
    parser.add_argument(
        "--real-camera", action="store_true", help="with --set: each world again, real camera"
    )
    parser.add_argument(
        "--worlds", help="with --set: a comma-separated subset of its worlds (default all)"
    )
    args = parser.parse_args(argv)
    t_start = time.perf_counter()
    if not (ycb_dir() / OBJECTS[0] / "textured.obj").is_file():
        print(f"skipped: YCB models not found under {ycb_dir()}")
        return 2
    if args.set is not None:
        return run_world_set(args)
    if args.real_camera or args.worlds:
        parser.error("--real-camera and --worlds go with --set")
    args.out = args.out or ROOT / "bench" / "results" / "scenarios.json"
    names = (
        args.scenarios.split(",")
        if args.scenarios
        else list(QUICK_SCENARIOS if args.quick else SCENARIOS)
    )
    bench = PRESETS["bench"]
    if args.quick:
        synth, tag, recon_preset = replace(bench, path=PathOptions(n_views=24)), "quick", "fast"
    else:
        synth, tag, recon_preset = bench, "bench", "default"
    ycb = [load_model(ycb_dir() / n / "textured.obj", n) for n in OBJECTS]
    models, prep_s = prepared_models(OBJECTS)
    report: dict[str, Any] = {
        "what": "whole pipeline on generated YCB scenes vs ground truth (pipeline called directly)",
        "quick": args.quick,
        "seed": args.seed,
        "objects": OBJECTS,
        "synth": {
            "preset": "bench",
            "n_views": synth.path.n_views,
            "image": [synth.camera.width, synth.camera.height],
            "detection": vars(synth.detection),
        },
        "reconstruct_preset": recon_preset,
        "model_prepare_s": prep_s,
        "load_average": os.getloadavg(),
        "cpus": os.cpu_count(),
        "scenarios": {},
    }

    def write() -> None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(report, indent=1, default=float))

    for name in names:
        print(f"[scenarios] {name} ...", flush=True)
        t0 = time.perf_counter()
        try:
            run = run_scenario(args.work, name, args.seed, synth, tag, recon_preset, ycb, models)
        except Exception as exc:  # one failing scenario must not lose the others
            report["scenarios"][name] = {"error": f"{type(exc).__name__}: {exc}"}
            print(f"[scenarios] {name} failed: {exc}", flush=True)
            write()
            continue
        report["scenarios"][name] = run
        report["summary"] = summarise(
            {k: v for k, v in report["scenarios"].items() if "error" not in v}
        )
        print(
            f"[scenarios] {name}: {time.perf_counter() - t0:.0f} s, "
            f"ours {json.dumps(run['ours'], default=float)[:600]}",
            flush=True,
        )
        write()
    ok = {k: v for k, v in report["scenarios"].items() if "error" not in v}
    report["summary"] = summarise(ok)
    if not args.no_clean_detector:
        # the same scenes (same images, so cached reconstructions) with a detector that
        # misses nothing and makes no false boxes, its ±2 px box jitter kept: what the
        # identification metric is when the misses of the bench preset are taken away
        clean = replace(
            synth, detection=replace(synth.detection, miss_rate=0.0, false_positive_rate=0.0)
        )
        print("[scenarios] clean detector (no misses, no false boxes) ...", flush=True)
        clean_runs: dict[str, Any] = {}
        for name in names:
            try:
                run = run_scenario(
                    args.work, name, args.seed, clean, tag + "_clean", recon_preset, ycb, models, ()
                )
                clean_runs[name] = {"ours": run["ours"], "timings_s": run["timings_s"]}
            except Exception as exc:
                clean_runs[name] = {"error": f"{type(exc).__name__}: {exc}"}
        ok_clean = {k: v for k, v in clean_runs.items() if "error" not in v}
        report["clean_detector"] = {
            "detection": vars(clean.detection),
            "scenarios": clean_runs,
            "summary": summarise(ok_clean) if ok_clean else None,
        }
        write()
    if not args.no_robustness:
        name = "multiple" if "multiple" in names else names[0]
        noisy = replace(
            synth,
            detection=replace(synth.detection, miss_rate=0.10, false_positive_rate=0.05),
        )
        print(f"[scenarios] robustness on {name} (10 % missed, 5 % false boxes) ...", flush=True)
        try:
            run = run_scenario(
                args.work, name, args.seed, noisy, tag + "_noisy", recon_preset, ycb, models, ()
            )
            run["detection"] = vars(noisy.detection)
            run["summary"] = summarise({name: run})
            report["robustness"] = run
        except Exception as exc:
            report["robustness"] = {"error": f"{type(exc).__name__}: {exc}"}
    report["load_average_end"] = os.getloadavg()
    report["total_s"] = round(time.perf_counter() - t_start, 1)
    write()
    print(json.dumps(report["summary"], indent=1, default=float))
    failed = [k for k, v in report["scenarios"].items() if "error" in v]
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
