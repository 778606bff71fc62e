"""Accuracy and cost of the inventory stage on generated YCB scenes with ground truth.

    python -m bench.inventory_bench --set tuning|test [--worlds a,b] [--options JSON] [--quick]

Each world of :mod:`bench.worlds` (tune on ``tuning``, report ``test``) is generated with 30
views (the bench preset's detector: ±2 px jitter, 5 % missed, 2 % false boxes) and both its
captures reconstructed like the snapshot job (cached; :mod:`bench.scenarios_bench`'s
helpers). For each capture the inventory (:func:`workers.pipeline.inventory.take_inventory`)
is scored against the capture's true placements:

- **found**: a true library object visible in ≥ 5 views (the detector boxed it: a box of its
  class around its projected centre) found with its class within max(½ diameter, 5 cm);
- **false objects**: objects no true library object of their class explains (distractors
  named as library objects count here);
- **poses**: symmetry-aware errors (:func:`workers.demo.evaluate.errors`), all and verified;
- **twin**: the service's own twin code (:mod:`app.core.twin`, :mod:`app.core.inventory`)
  on a scratch SQLite database: the first inventory fills the twin, the comparison's changes
  (posed as the comparison job does) are applied, the second inventory confirms; the open
  instances are scored against the after capture's truth: every object with class and pose
  within 1 cm / 3°, nothing extra;
- **time**: the inventory's wall and CPU seconds per capture beside the compare stage's on
  the same pair in the same run (the baseline), on this machine's cores.

Writes ``bench/results/inventory_<set>.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sqlalchemy.orm import Session

from app.core import inventory, twin
from app.core.db import Base, make_engine
from app.core.enums import ObjectState
from app.core.models import Comparison, Environment, Job, LibraryObject, Snapshot
from bench.scenarios_bench import (
    ROOT,
    TMP,
    _hash_inputs,
    capture_data,
    cloud_digest,
    machine,
    pose_figures,
    prepared_models,
    reconstruct_capture,
    scene,
    ycb_dir,
)
from bench.worlds import SETS, World
from workers.comparison import compare_twin
from workers.demo.evaluate import _symmetry, errors
from workers.pipeline.compare.data import CaptureData
from workers.pipeline.compare.options import options_from_json
from workers.pipeline.compare.stage import compare_snapshots
from workers.pipeline.inventory import InventoryResult, inventory_options_from_json, take_inventory
from workers.pipeline.model import PreparedModel
from workers.pipeline.pose.posing import pose_changes
from workers.pipeline.synth import PATH_PRESETS, PRESETS, ROOM_PRESETS, PathOptions, load_model

MIN_VIEWS = 5
#: the timing scene: 10 objects placed ("no_change" holds the last non-symmetric one back as
#: the spare), on the floor and a table, 30 views
TIMING_OBJECTS: tuple[str, ...] = (
    "power_drill",
    "large_clamp",
    "mustard_bottle",
    "master_chef_can",
    "hammer",
    "extra_large_clamp",
    "mug",
    "tomato_soup_can",
    "wood_block",
    "adjustable_wrench",
    "padlock",
)
TIMING_SEED = 7
TARGETS = {
    "found_of_visible": 0.95,
    "false_objects": 0,
    "translation_median_m": 0.003,
    "rotation_median_deg": 1.0,
    "verified_translation_max_m": 0.01,
    "verified_rotation_max_deg": 3.0,
    "twin_equals_truth": True,
    "inventory_s_per_10_objects": 30.0,
}


def timing_synth() -> Any:
    """The timing scene's generator options: the bench preset, a table, 30 views on the
    path for rooms with furniture."""
    path = replace(PATH_PRESETS["wide_high"], n_views=30)
    return replace(PRESETS["bench"], path=path, room=ROOM_PRESETS["closed_table"])


def views_boxed(data: CaptureData, classes: list[str], placement: dict[str, Any]) -> int:
    """Views whose detections hold a box of the placement's class around its projected
    centre (the object's origin lifted by nothing: the model origin is on its body)."""
    k = classes.index(placement["object"])
    centre = np.asarray(placement["env_from_object"], dtype=np.float64)[:3, 3]
    n = 0
    for cam in data.cameras:
        p = cam.cam_from_env[:3, :3] @ centre + cam.cam_from_env[:3, 3]
        if p[2] <= 0.05:
            continue
        u, v = (cam.k @ (p / p[2]))[:2]
        rows = data.detections.get(cam.name, np.zeros((0, 6)))
        for r in rows:
            if round(float(r[0])) != k:
                continue
            cx, cy, w, h = r[1] * cam.width, r[2] * cam.height, r[3] * cam.width, r[4] * cam.height
            if abs(u - cx) <= w / 2 and abs(v - cy) <= h / 2:
                n += 1
                break
    return n


def centre_of(pose: Any, model: PreparedModel) -> np.ndarray:
    """(3,) the model's centre posed by 4×4 ``pose`` (a symmetric object's origin may lie
    off its axis: centres, not origins, say where an object is)."""
    return np.asarray(np.asarray(pose, dtype=np.float64) @ np.append(model.centre_object, 1.0))


def _pairs(
    truths: list[dict[str, Any]],
    found: list[dict[str, Any]],
    reach: dict[str, float],
    models: dict[str, PreparedModel],
) -> list[tuple[int, int]]:
    """Truth–found pairs of one class whose centres lie within reach, nearest first, each
    used once."""
    cands = []
    for i, t in enumerate(truths):
        tp = centre_of(t["env_from_object"], models[t["object"]])[:3]
        for j, f in enumerate(found):
            if f["object"] != t["object"]:
                continue
            fp = (
                centre_of(f["pose"], models[f["object"]])[:3]
                if f.get("pose") is not None
                else np.asarray(f["centroid_env"])
            )
            d = float(np.linalg.norm(tp - fp))
            if d <= reach[t["object"]]:
                cands.append((d, i, j))
    used_i: set[int] = set()
    used_j: set[int] = set()
    out = []
    for _d, i, j in sorted(cands):
        if i not in used_i and j not in used_j:
            used_i.add(i)
            used_j.add(j)
            out.append((i, j))
    return out


def score_capture(
    truth: dict[str, Any],
    capture: str,
    data: CaptureData,
    result: InventoryResult,
    models: dict[str, PreparedModel],
) -> dict[str, Any]:
    """Per true object: views boxed, found, pose errors; and the false objects."""
    classes = truth["classes"]
    placements = [p for p in truth[capture] if not p.get("distractor")]
    found = [o.to_json() for o in result.objects]
    reach = {n: max(0.5 * m.diameter_m, 0.05) for n, m in models.items()}
    pairs = dict(_pairs(placements, found, reach, models))
    rows = []
    for i, p in enumerate(placements):
        row: dict[str, Any] = {
            "object": p["object"],
            "support": p.get("support"),
            "views_boxed": views_boxed(data, classes, p),
            "found": i in pairs,
        }
        if i in pairs:
            f = found[pairs[i]]
            row["metric"] = f["identification"].get("metric")
            quality = f.get("pose_quality") or {}
            row["verified"] = bool(quality.get("verified"))
            row["reasons"] = quality.get("reasons")
            row["figures"] = pose_figures(quality)
            if f.get("pose") is not None:
                e = errors(f["pose"], p["env_from_object"], _symmetry(truth, p["object"]))
                row["translation_error_m"] = e.translation_m
                row["rotation_error_deg"] = e.rotation_deg
        rows.append(row)
    matched = set(pairs.values())
    false = [
        {
            "object": f["object"],
            "centroid_env": f["centroid_env"],
            "verified": bool((f.get("pose_quality") or {}).get("verified")),
        }
        for j, f in enumerate(found)
        if j not in matched
    ]
    return {
        "objects": rows,
        "false_objects": false,
        "rejected": [{k: r.get(k) for k in ("object", "reason")} for r in result.rejected],
        "supports": [s.to_json() for s in result.supports],
        "stats": result.stats,
    }


def _service_twin(
    classes: list[str],
    before: CaptureData,
    after: CaptureData,
    inv_before: InventoryResult,
    inv_after: InventoryResult,
    models: dict[str, PreparedModel],
) -> tuple[list[dict[str, Any]], list[dict[str, Any]], dict[str, int], float]:
    """The service's own twin code (:mod:`app.core.twin`, :mod:`app.core.inventory`) on a
    scratch SQLite database: the first inventory fills the twin, the comparison's posed
    changes are applied, the second inventory confirms. Returns the twin's open instances
    after (object, pose, centroid), the comparison's changes, the confirmation's counts
    and the compare-and-pose seconds."""
    with tempfile.TemporaryDirectory() as scratch:
        engine = make_engine(f"sqlite:///{scratch}/twin.db")
        Base.metadata.create_all(engine)
        with Session(engine) as session:
            env = Environment(name="bench", classes=classes)
            library = [
                LibraryObject(
                    name=name,
                    state=ObjectState.ready,
                    diameter_m=model.diameter_m,
                    filename=f"{name}.ply",
                    file_key=name,
                    size_bytes=0,
                )
                for name, model in models.items()
            ]
            session.add_all([env, *library])
            session.flush()
            snaps = [Snapshot(environment_id=env.id, seq=seq, storage_prefix="") for seq in (1, 2)]
            job = Job(kind="comparison", task_name="bench")
            session.add_all([*snaps, job])
            session.flush()
            comparison = Comparison(
                environment_id=env.id, before_id=snaps[0].id, after_id=snaps[1].id, job_id=job.id
            )
            session.add(comparison)
            session.flush()
            inventory.record(session, snaps[0], [o.to_json() for o in inv_before.objects], {})
            inventory.fill_baseline(session, env, snaps[0])
            instances = compare_twin(twin.state_at(session, env.id, 1))
            t0 = time.perf_counter()
            options = options_from_json("default")
            diameters = {n: m.diameter_m for n, m in models.items()}
            result = compare_snapshots(before, after, instances, classes, diameters, options)
            records = pose_changes(result, after, classes, models, models.__getitem__, options)
            compare_s = time.perf_counter() - t0
            object_ids = {o.name: o.id for o in library}
            twin.apply_changes(session, env.id, snaps[1].id, comparison.id, records, object_ids)
            inventory.record(session, snaps[1], [o.to_json() for o in inv_after.objects], {})
            confirmed = inventory.confirm(session, env, snaps[1], comparison.id)
            current = [
                {"object": i.object_name, "pose": i.pose, "centroid_env": i.centroid_env}
                for i in twin.current(session, env.id)
            ]
        engine.dispose()
    counts = {
        "drift_refreshed": len(confirmed["drifted"]),
        "restored": len(confirmed["restored"]),
        "added_by_inventory": len(confirmed["added"]),
    }
    return current, records, counts, compare_s


def twin_check(
    truth: dict[str, Any],
    before: CaptureData,
    after: CaptureData,
    inv_before: InventoryResult,
    inv_after: InventoryResult,
    models: dict[str, PreparedModel],
) -> dict[str, Any]:
    """The service's twin rules on the world's two snapshots (see the module docstring),
    scored against the after capture's truth."""
    classes = truth["classes"]
    current, records, confirmed, compare_s = _service_twin(
        classes, before, after, inv_before, inv_after, models
    )
    # against the truth of the after capture
    placements = [p for p in truth["after"] if not p.get("distractor")]
    match_reach = {n: max(0.5 * m.diameter_m, 0.05) for n, m in models.items()}
    tp = dict(_pairs(placements, current, match_reach, models))
    rows = []
    for i, p in enumerate(placements):
        row: dict[str, Any] = {
            "object": p["object"],
            "views_boxed": views_boxed(after, classes, p),
            "in_twin": i in tp,
        }
        pose = current[tp[i]]["pose"] if i in tp else None
        if pose is not None:
            e = errors(pose, p["env_from_object"], _symmetry(truth, p["object"]))
            row["translation_error_m"] = e.translation_m
            row["rotation_error_deg"] = e.rotation_deg
            row["within_pose_target"] = e.translation_m <= 0.01 and e.rotation_deg <= 3.0
        elif i in tp:
            row["within_pose_target"] = False  # an instance without a pose
        rows.append(row)
    extra = [t["object"] for j, t in enumerate(current) if j not in set(tp.values())]
    visible = [r for r in rows if r["views_boxed"] >= MIN_VIEWS]
    return {
        "changes": [{"type": r["type"], "object": r.get("object")} for r in records],
        "truth_changes": [{"type": c["type"], "object": c["object"]} for c in truth["changes"]],
        **confirmed,
        "objects": rows,
        "extra": extra,
        "equals_truth": not extra and all(r.get("within_pose_target") for r in visible),
        "compare_and_pose_s": round(compare_s, 2),
    }


def _timed_inventory(
    data: CaptureData, classes: list[str], models: dict[str, PreparedModel], options: Any
) -> tuple[InventoryResult, float, float]:
    t0, c0 = time.perf_counter(), time.process_time()
    result = take_inventory(
        data, classes, {n: m.diameter_m for n, m in models.items()}, models.__getitem__, options
    )
    return result, time.perf_counter() - t0, time.process_time() - c0


def run_world(
    work: Path, set_name: str, world: World, base: Any, options: Any, recon_preset: str
) -> dict[str, Any]:
    synth = world.options(base)
    ycb = [load_model(ycb_dir() / n / "textured.obj", n) for n in world.objects]
    tag = f"{set_name}_{world.name}_{_hash_inputs(repr(synth), world)[:8]}"
    scene_dir = scene(work, world.scenario, world.seed, synth, tag, ycb)
    truth = json.loads((scene_dir / "ground_truth.json").read_text())
    before_dir, before_q, _ = reconstruct_capture(work, scene_dir, "before", recon_preset, None)
    after_dir, after_q, _ = reconstruct_capture(
        work, scene_dir, "after", recon_preset, before_dir / "cloud.ply"
    )
    models, _ = prepared_models(list(world.objects))
    classes = truth["classes"]
    out: dict[str, Any] = {"world": vars(world) | {"objects": list(world.objects)}, "captures": {}}
    datas, results = {}, {}
    for capture, recon, q in (("before", before_dir, before_q), ("after", after_dir, after_q)):
        data = capture_data(scene_dir, capture, recon, q)
        result, wall, cpu = _timed_inventory(data, classes, models, options)
        datas[capture], results[capture] = data, result
        scored = score_capture(truth, capture, data, result, models)
        scored["inventory_s"] = round(wall, 2)
        scored["inventory_cpu_s"] = round(cpu, 2)
        scored["points"] = len(data.points_env)
        scored["cloud_sha256"] = cloud_digest(recon)
        scored["views"] = len(data.cameras)
        out["captures"][capture] = scored
    twin = twin_check(
        truth, datas["before"], datas["after"], results["before"], results["after"], models
    )
    out["twin"] = twin
    return out


def run_timing(work: Path, options: Any, recon_preset: str) -> dict[str, Any]:
    """The inventory of the timing scene's first capture (10 objects, 30 views): wall and
    CPU seconds per step, objects found and posed, and the figure the target is set in
    (seconds for 10 objects on this machine's cores)."""
    synth = timing_synth()
    ycb = [load_model(ycb_dir() / n / "textured.obj", n) for n in TIMING_OBJECTS]
    tag = f"timing_{_hash_inputs(repr(synth), TIMING_OBJECTS)[:8]}"
    scene_dir = scene(work, "no_change", TIMING_SEED, synth, tag, ycb)
    truth = json.loads((scene_dir / "ground_truth.json").read_text())
    recon, quality, _ = reconstruct_capture(work, scene_dir, "before", recon_preset, None)
    models, _ = prepared_models(list(TIMING_OBJECTS))
    data = capture_data(scene_dir, "before", recon, quality)
    result, wall, cpu = _timed_inventory(data, truth["classes"], models, options)
    scored = score_capture(truth, "before", data, result, models)
    placed = len(truth["before"])
    return {
        "objects_placed": placed,
        "views": len(data.cameras),
        "points": len(data.points_env),
        "objects_found": len(result.objects),
        "inventory_s": round(wall, 2),
        "inventory_cpu_s": round(cpu, 2),
        "steps_s": result.stats.get("timings_s"),
        "reconstruction_s": (quality.get("timings_s") or {}).get("total"),
        "seconds_per_10_objects": round(10.0 * wall / max(placed, 1), 2),
        "cpu_seconds_per_10_objects": round(10.0 * cpu / max(placed, 1), 2),
        "load_average": os.getloadavg(),
        "scored": scored,
    }


def summarise(worlds: dict[str, Any]) -> dict[str, Any]:
    rows = [
        r
        for w in worlds.values()
        if "error" not in w
        for c in w["captures"].values()
        for r in c["objects"]
    ]
    visible = [r for r in rows if r["views_boxed"] >= MIN_VIEWS]
    found = [r for r in visible if r["found"]]
    posed = [r for r in found if r.get("translation_error_m") is not None]
    verified = [r for r in posed if r.get("verified")]
    false = sum(
        len(c["false_objects"])
        for w in worlds.values()
        if "error" not in w
        for c in w["captures"].values()
    )
    times = [
        (c["inventory_s"], c["inventory_cpu_s"], len(c["objects"]))
        for w in worlds.values()
        if "error" not in w
        for c in w["captures"].values()
    ]
    compare_s = [w["twin"]["compare_and_pose_s"] for w in worlds.values() if "error" not in w]
    twins = [w["twin"]["equals_truth"] for w in worlds.values() if "error" not in w]

    def med(v: list[float]) -> float | None:
        return float(statistics.median(v)) if v else None

    per10 = [10.0 * s / max(n, 1) for s, _, n in times]
    figures: dict[str, Any] = {
        "true_objects": len(rows),
        "visible_in_5_views": len(visible),
        "found_of_visible": len(found) / len(visible) if visible else None,
        "found_not_visible": sum(1 for r in rows if r["found"] and r["views_boxed"] < MIN_VIEWS),
        "false_objects": false,
        "posed": len(posed),
        "verified": len(verified),
        "translation_median_m": med([r["translation_error_m"] for r in posed]),
        "rotation_median_deg": med([r["rotation_error_deg"] for r in posed]),
        "translation_max_m": max((r["translation_error_m"] for r in posed), default=None),
        "rotation_max_deg": max((r["rotation_error_deg"] for r in posed), default=None),
        "verified_translation_max_m": max(
            (r["translation_error_m"] for r in verified), default=None
        ),
        "verified_rotation_max_deg": max((r["rotation_error_deg"] for r in verified), default=None),
        "twin_equals_truth": all(twins) if twins else None,
        "twins_equal_truth": f"{sum(twins)} of {len(twins)}",
        "inventory_s_median": med([t[0] for t in times]),
        "inventory_s_max": max((t[0] for t in times), default=None),
        "inventory_cpu_s_median": med([t[1] for t in times]),
        # wall seconds per 10 true objects of the worlds' captures (5 objects each); the
        # target's figure is the timing scene's (run_timing)
        "worlds_s_per_10_objects_max": max(per10, default=None),
        "baseline_compare_and_pose_s_median": med(compare_s),
    }
    verdicts = {}
    for key, target in TARGETS.items():
        value = figures.get(key)
        if value is None:
            verdicts[key] = "n/a"
        elif key == "found_of_visible":
            verdicts[key] = "met" if value >= target else "not met"
        elif key == "twin_equals_truth":
            verdicts[key] = "met" if value else "not met"
        else:
            verdicts[key] = "met" if value <= target else "not met"
    figures["targets"], figures["verdicts"] = TARGETS, verdicts
    return figures


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--set", choices=sorted(SETS), default="test")
    parser.add_argument("--worlds", help="a comma-separated subset of the set's worlds")
    parser.add_argument("--options", default="{}", help="inventory options JSON")
    parser.add_argument("--quick", action="store_true", help="24 views, fast reconstruction")
    parser.add_argument("--work", type=Path, default=TMP / "inventory")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--no-timing", action="store_true", help="skip the 10-object scene")
    args = parser.parse_args(argv)
    if not (ycb_dir() / "power_drill" / "textured.obj").is_file():
        print(f"skipped: YCB models not found under {ycb_dir()}")
        return 2
    worlds = SETS[args.set]
    if args.worlds:
        wanted = args.worlds.split(",")
        unknown = sorted(set(wanted) - {w.name for w in worlds})
        if unknown:
            print(f"unknown worlds of the {args.set} set: {', '.join(unknown)}", file=sys.stderr)
            return 2
        worlds = tuple(w for w in worlds if w.name in wanted)
    base, recon_preset = replace(PRESETS["bench"], path=PathOptions(n_views=30)), "default"
    if args.quick:
        base, recon_preset = replace(PRESETS["bench"], path=PathOptions(n_views=24)), "fast"
    base = replace(base, path=replace(PRESETS["bench"].path, n_views=base.path.n_views))
    options = inventory_options_from_json(json.loads(args.options))
    out = args.out or ROOT / "bench" / "results" / f"inventory_{args.set}.json"
    report: dict[str, Any] = {
        "what": f"inventory of both captures of the {args.set} worlds vs ground truth",
        "set": args.set,
        "rule": "tune on the tuning set only; the test set is reported, never tuned on",
        "n_views": base.path.n_views,
        "reconstruct_preset": recon_preset,
        "detection": vars(base.detection),
        "options": options.to_json(),
        "machine": machine(),
        "load_average": os.getloadavg(),
        "worlds": {},
    }
    failed = False
    for world in worlds:
        print(f"[inventory:{args.set}] {world.name} ...", flush=True)
        try:
            report["worlds"][world.name] = run_world(
                args.work, args.set, world, base, options, recon_preset
            )
        except Exception as exc:  # one failing world must not lose the others
            report["worlds"][world.name] = {"error": f"{type(exc).__name__}: {exc}"}
            failed = True
        report["summary"] = summarise(report["worlds"])
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(report, indent=1, default=float))
    if not args.no_timing:
        print("[inventory] timing scene (10 objects, 30 views) ...", flush=True)
        try:
            report["timing"] = run_timing(args.work, options, recon_preset)
            summary = report.setdefault("summary", {})
            per10 = report["timing"]["seconds_per_10_objects"]
            summary["inventory_s_per_10_objects"] = per10
            summary["inventory_cpu_s_per_10_objects"] = report["timing"][
                "cpu_seconds_per_10_objects"
            ]
            summary.setdefault("verdicts", {})["inventory_s_per_10_objects"] = (
                "met" if per10 <= TARGETS["inventory_s_per_10_objects"] else "not met"
            )
        except Exception as exc:
            report["timing"] = {"error": f"{type(exc).__name__}: {exc}"}
            failed = True
    report["load_average_end"] = os.getloadavg()
    out.write_text(json.dumps(report, indent=1, default=float))
    print(json.dumps(report.get("summary"), indent=1, default=float))
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
