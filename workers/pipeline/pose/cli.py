"""``python -m workers.pipeline pose``: estimate one object's pose from the command line."""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from workers.pipeline.errors import InputError, RegistrationError, ShapeError
from workers.pipeline.model import load_prepared
from workers.pipeline.pose.crop import SceneCloud
from workers.pipeline.pose.estimate import estimate_pose
from workers.pipeline.pose.options import POSE_PRESETS


def _vec3(text: str) -> NDArray[np.float64]:
    parts = [float(x) for x in text.split(",")]
    if len(parts) != 3:
        raise argparse.ArgumentTypeError("expected x,y,z")
    return np.asarray(parts, dtype=np.float64)


def cli(argv: list[str]) -> int:
    """``python -m workers.pipeline pose --model DIR --scene cloud.ply --center x,y,z``."""
    ap = argparse.ArgumentParser(prog="python -m workers.pipeline pose")
    ap.add_argument("--model", type=Path, required=True, help="work dir of `model`")
    ap.add_argument("--scene", type=Path, required=True, help="scene cloud, env frame, metres")
    ap.add_argument(
        "--center",
        "--centre",
        type=_vec3,
        required=True,
        help="cluster centre x,y,z in metres (write --center=-0.1,0.2,0.8 for negatives)",
    )
    ap.add_argument(
        "--viewpoint",
        type=_vec3,
        default=None,
        help="camera x,y,z of a single depth frame: normals missing from --scene face it "
        "(default: away from the cluster, as in the service)",
    )
    ap.add_argument("--previous", type=Path, default=None, help="JSON 4×4 previous pose")
    ap.add_argument("--preset", default="default", choices=sorted(POSE_PRESETS))
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    try:
        model = load_prepared(args.model)
        scene = SceneCloud.from_file(args.scene, args.viewpoint)
        previous = None if args.previous is None else json.loads(args.previous.read_text())
        result = estimate_pose(
            model,
            scene,
            centre_env=args.center,
            previous_env_from_object=previous,
            options=replace(POSE_PRESETS[args.preset], seed=args.seed),
        )
    except (InputError, RegistrationError, ShapeError) as exc:
        print(exc)
        return 2
    out = {
        "env_from_object": result.env_from_object.tolist(),
        "pose_quality": result.quality_json(),
        "rejections": list(result.rejections),
        "chosen_by": result.chosen_by,
        "source": result.source,
        "trials": [
            {"source": t.source, "score": t.score, "fitness": t.fitness, "seconds": t.seconds}
            for t in result.trials
        ],
        "timings_s": result.timings_s,
    }
    print(json.dumps(out, indent=2))
    return 0
