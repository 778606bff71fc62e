"""The pycolmap CUDA dense path (PatchMatch stereo + stereo fusion) on a GPU machine,
against the CPU multi-view stereo, on the reconstruct bench's scene.

On a GPU machine with a CUDA build of pycolmap (``pycolmap-cuda12``) and no Open3D:

    python bench/cuda_dense_bench.py run --images DIR --sfm-model DIR --cameras FILE --out DIR

runs the stage's own ``_cuda_dense`` and ``fusion.colmap_dense`` (their source taken from
this checkout, so what is measured is the code the stage runs where ``pycolmap.has_cuda``),
times every pycolmap step and writes the fused cloud as ``pts_K.npy`` chunks (float32, env
frame, metres) with ``timing.json``. ``--sfm-model`` is ``<work>/sfm/model`` and
``--cameras`` the ``cameras.json`` of a CPU reconstruction of the same images (SfM +
markers), from which the env frame is taken. Back on the CPU machine:

    python bench/cuda_dense_bench.py evaluate --scene DIR --cloud-dir DIR [--out FILE]

scores that cloud against the scene's true surfaces with the reconstruct bench's metrics
and writes ``bench/results/reconstruct_cuda.json``.
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import shutil
import sys
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from app.formats.cameras import load_cameras_file  # noqa: E402 (stdlib only)


def _source_function(path: Path, name: str, namespace: dict[str, Any]) -> Any:
    """The module-level function ``name`` of ``path``, executed alone in ``namespace``."""
    src = path.read_text()
    node = next(n for n in ast.parse(src).body if isinstance(n, ast.FunctionDef) and n.name == name)
    code = "from __future__ import annotations\n" + str(ast.get_source_segment(src, node))
    exec(compile(code, str(path), "exec"), namespace)
    return namespace[name]


def _read_binary_ply(path: Path) -> np.ndarray:
    """(N, 3) float32 vertices of a binary little-endian PLY (COLMAP's fused.ply)."""
    raw = path.read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    lines = raw[:end].decode().splitlines()
    n = int(next(line.split()[2] for line in lines if line.startswith("element vertex")))
    types = {"float": "<f4", "double": "<f8", "uchar": "u1"}
    fields = [(ln.split()[2], types[ln.split()[1]]) for ln in lines if ln.startswith("property")]
    arr = np.frombuffer(raw[end:], dtype=np.dtype(fields), count=n)
    return np.stack([arr["x"], arr["y"], arr["z"]], 1).astype(np.float32)


def run(args: argparse.Namespace) -> None:
    import pycolmap

    from workers.pipeline.geometry import umeyama_similarity  # NumPy only

    steps: dict[str, float] = {}

    def timed(name: str) -> Any:
        call = getattr(pycolmap, name)

        def wrapper(*a: Any, **k: Any) -> Any:
            t = time.perf_counter()
            out = call(*a, **k)
            steps[name] = round(time.perf_counter() - t, 2)
            print("step", name, steps[name], flush=True)
            return out

        return wrapper

    # colmap_dense imports pycolmap itself: time its steps on the module
    for name in ("undistort_images", "patch_match_stereo", "stereo_fusion"):
        setattr(pycolmap, name, timed(name))
    ns: dict[str, Any] = {
        "Path": Path,
        "pycolmap": pycolmap,
        "np": np,
        "umeyama_similarity": umeyama_similarity,
        "read_ply": lambda p: p,
    }
    pipeline = ROOT / "workers" / "pipeline" / "reconstruct"
    colmap_dense = _source_function(pipeline / "fusion.py", "colmap_dense", dict(ns))
    ns["fusion"] = SimpleNamespace(colmap_dense=colmap_dense)
    cuda_dense = _source_function(pipeline / "stage.py", "_cuda_dense", ns)
    poses = load_cameras_file(args.cameras).poses
    views = [
        SimpleNamespace(name=name, centre=np.asarray(m, float)[:3, 3])
        for name, m in sorted(poses.items())
    ]
    work = Path(args.work)
    shutil.rmtree(work, ignore_errors=True)
    shutil.copytree(args.sfm_model, work / "sfm" / "model")
    print("pycolmap", pycolmap.__version__, "has_cuda", pycolmap.has_cuda, flush=True)
    t0 = time.perf_counter()
    fused = cuda_dense(args.images, work, SimpleNamespace(views=views))
    total = round(time.perf_counter() - t0, 2)
    pts = _read_binary_ply(Path(fused))
    args.out.mkdir(parents=True, exist_ok=True)
    chunk = 1_000_000
    for k in range(0, max(len(pts), 1), chunk):
        np.save(args.out / f"pts_{k // chunk}.npy", pts[k : k + chunk])
    timing = {"total_s": total, "steps_s": steps, "points": len(pts), "cpus": os.cpu_count()}
    (args.out / "timing.json").write_text(json.dumps(timing))
    print(json.dumps(timing), flush=True)


def evaluate(args: argparse.Namespace) -> None:
    from bench.reconstruct_bench import cloud_metrics, visible_surface_samples
    from workers.pipeline.synth import load_true_surfaces

    pts = np.concatenate([np.load(f) for f in sorted(args.cloud_dir.glob("pts_*.npy"))])
    gt = json.loads((args.scene / "ground_truth.json").read_text())
    raw = dict(json.loads((args.scene / "before" / "cameras.json").read_text()))
    raw.setdefault("poses", gt["camera_poses"]["before"])
    meshes = load_true_surfaces(args.scene, "before")
    metrics = cloud_metrics(pts.astype(np.float64), meshes, visible_surface_samples(meshes, raw))
    timing = json.loads((args.cloud_dir / "timing.json").read_text())
    result = {"what": "pycolmap CUDA PatchMatch + fusion, default options", **timing, **metrics}
    args.out.write_text(json.dumps(result, indent=1))
    print(json.dumps(result, indent=1))


def main() -> int:
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("--images", type=Path, required=True)
    r.add_argument("--sfm-model", type=Path, required=True)
    r.add_argument("--cameras", type=Path, required=True)
    r.add_argument("--work", type=Path, default=Path("/tmp/cuda_dense_work"))
    r.add_argument("--out", type=Path, required=True)
    e = sub.add_parser("evaluate")
    e.add_argument("--scene", type=Path, required=True)
    e.add_argument("--cloud-dir", type=Path, required=True)
    e.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "reconstruct_cuda.json")
    args = parser.parse_args()
    run(args) if args.cmd == "run" else evaluate(args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
