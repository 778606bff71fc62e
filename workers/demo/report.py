"""The demo's HTML report: per change, images with the cluster's re-projected box and the
detector's boxes (the thesis's overlap figures), the distance histograms with thresholds
(its distribution figures), and the pose errors."""

from __future__ import annotations

import html
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from PIL import Image, ImageDraw

from workers.demo.evaluate import Match

CLUSTER_COLOUR = (255, 40, 40)
DETECTION_COLOUR = (40, 200, 255)


def _boxes_image(
    image_path: Path,
    labels_path: Path,
    classes: list[str],
    cluster_box: list[float] | None,
    object_name: str | None,
    out: Path,
) -> None:
    with Image.open(image_path) as source:
        img = source.convert("RGB")
    draw = ImageDraw.Draw(img)
    w, h = img.size
    if labels_path.exists():
        for line in labels_path.read_text().splitlines():
            parts = line.split()
            if len(parts) < 5:
                continue
            cid, cx, cy, bw, bh = int(parts[0]), *map(float, parts[1:5])
            name = classes[cid] if cid < len(classes) else str(cid)
            width = 3 if name == object_name else 1
            box = [(cx - bw / 2) * w, (cy - bh / 2) * h, (cx + bw / 2) * w, (cy + bh / 2) * h]
            draw.rectangle(box, outline=DETECTION_COLOUR, width=width)
            draw.text((box[0] + 2, box[1] + 2), name, fill=DETECTION_COLOUR)
    if cluster_box is not None:
        draw.rectangle(cluster_box, outline=CLUSTER_COLOUR, width=3)
    img.thumbnail((480, 360))
    img.save(out)


def _histogram_svg(side: str, stats: dict[str, Any], thresholds: dict[str, float]) -> str:
    hist = stats.get("histogram")
    if not hist:
        return ""
    counts, width_m = hist["counts"], hist["bin_width_m"]
    top = max(max(counts), 1)
    w, h, bar = 480, 160, 480 / len(counts)
    bars = "".join(
        f'<rect x="{i * bar:.1f}" y="{h - 140 * c / top:.1f}" width="{bar - 1:.1f}" '
        f'height="{140 * c / top:.1f}" fill="#6a8caf"/>'
        for i, c in enumerate(counts)
    )
    span = width_m * len(counts)
    lines = "".join(
        f'<line x1="{min(t / span, 1) * w:.1f}" x2="{min(t / span, 1) * w:.1f}" y1="10" y2="{h}" '
        f'stroke="{colour}" stroke-width="2"/>'
        f'<text x="{min(t / span, 1) * w + 3:.1f}" y="{22 + 12 * i}" '
        f'font-size="10" fill="{colour}">{html.escape(name)} {t * 1000:.1f} mm</text>'
        for i, ((name, t), colour) in enumerate(
            zip(thresholds.items(), ["#999", "#777", "#c60", "#a00", "#0a0"], strict=False)
        )
    )
    return (
        f"<figure><svg width='{w}' height='{h + 20}' style='background:#fafafa'>{bars}{lines}"
        f"<text x='0' y='{h + 15}' font-size='10'>0</text><text x='{w - 60}' y='{h + 15}' "
        f"font-size='10'>{span * 1000:.0f} mm</text></svg><figcaption>{side}: C2C distance "
        f"histogram (log-free counts), mean {stats['mean'] * 1000:.1f} mm, std "
        f"{stats['std'] * 1000:.1f} mm</figcaption></figure>"
    )


def _distance_section(comparison: dict[str, Any]) -> list[str]:
    """Per side, the C2C histogram with the candidate thresholds and the one used (metres)."""
    parts = ["<h2>Distances and thresholds</h2>"]
    for side in ("added", "removed"):
        stats = comparison["distances"].get(side)
        if stats:
            m, s = stats["mean"], stats["std"]
            thresholds = {
                "mean": m,
                "mean+0.5σ": m + 0.5 * s,
                "mean+1σ": m + s,
                "mean+1.5σ": m + 1.5 * s,
                "used": stats["threshold"],
            }
            parts.append(_histogram_svg(side, stats, thresholds))
    return parts


@dataclass(frozen=True)
class _Scene:
    """Where one change's figures come from and go: the generated scene, the comparison's
    clusters by id, the class names, and the report's folder."""

    scene_dir: Path
    clusters: dict[str | None, dict[str, Any]]
    classes: list[str]
    out_dir: Path


def _change_section(n: int, match: Match, scene: _Scene) -> list[str]:
    """One true change: missed, or its identification, pose errors and up to four images
    with the cluster's box (written as ``change{n}_{i}.png``)."""
    found, truth = match.found, match.truth
    parts = [f"<h3>{html.escape(truth['type'])} {html.escape(truth['object'])}</h3>"]
    if found is None:
        parts.append("<p><b>missed</b>: no change of this type and object was found.</p>")
        return parts
    err = (
        f"translation error {match.translation_error_m * 1000:.1f} mm, rotation error "
        f"{match.rotation_error_deg:.2f}°"
        if match.translation_error_m is not None
        else "no pose"
    )
    ident = found.get("identification") or {}
    parts.append(
        f"<p>identification metric {ident.get('metric', 0):.2f} "
        f"(IoU {ident.get('iou', 0):.2f}, "
        f"{ident.get('overlaps', 0)}/{ident.get('occurrences', 0)} images); {err}; "
        f"pose quality {html.escape(str(found.get('pose_quality')))[:300]}</p>"
    )
    cluster = scene.clusters.get((found.get("cluster") or {}).get("id"))
    side = (found.get("cluster") or {}).get("side", "added")
    capture = scene.scene_dir / ("after" if side == "added" else "before")
    boxes = (cluster or {}).get("boxes", {})
    for i, (image_name, box) in enumerate(sorted(boxes.items())[:4]):
        png = scene.out_dir / f"change{n}_{i}.png"
        _boxes_image(
            capture / "images" / image_name,
            capture / "labels" / (Path(image_name).stem + ".txt"),
            scene.classes,
            box,
            found.get("object"),
            png,
        )
        parts.append(f"<img src='{png.name}'>")
    return parts


def write_report(
    out_dir: Path,
    scene_dir: Path,
    comparison: dict[str, Any],
    matches: list[Match],
    extra: list[dict[str, Any]],
    classes: list[str],
    timings: dict[str, float],
    console_url: str | None = None,
) -> Path:
    """Write ``out_dir/report.html`` (with its PNGs) and return its path; ``console_url``
    (the demo environment in the operator console) is linked at the top."""
    out_dir.mkdir(parents=True, exist_ok=True)
    scene = _Scene(scene_dir, {c["id"]: c for c in comparison["clusters"]}, classes, out_dir)
    parts = [
        "<html><head><meta charset='utf-8'><title>twindelta demo</title><style>"
        "body{font-family:sans-serif;margin:2em} img{margin:4px;border:1px solid #ccc}"
        "table{border-collapse:collapse} td,th{border:1px solid #ccc;padding:4px 8px}"
        "</style></head><body><h1>twindelta demo report</h1>"
    ]
    if console_url:
        url = html.escape(console_url, quote=True)
        parts.append(
            f"<p>Open the demo environment in the operator console: <a href='{url}'>{url}</a> "
            "(while the service runs: <code>make demo KEEP=1</code>; sign in with the key the "
            "demo printed).</p>"
        )
    parts.append(
        "<p>Red: the changed cluster re-projected into the capture's images. Blue: the "
        "detector's boxes (thick: the identified class).</p>"
    )
    parts += _distance_section(comparison)
    parts.append("<h2>Changes</h2>")
    for n, match in enumerate(matches):
        parts += _change_section(n, match, scene)
    if extra:
        parts.append("<h2>Changes with no ground truth (false changes)</h2><ul>")
        parts += [
            f"<li>{html.escape(e['type'])} {html.escape(str(e.get('object')))}</li>" for e in extra
        ]
        parts.append("</ul>")
    parts.append(
        "<h2>Timings</h2><table>"
        + "".join(
            f"<tr><td>{html.escape(k)}</td><td>{v:.1f} s</td></tr>" for k, v in timings.items()
        )
        + "</table>"
    )
    parts.append("</body></html>")
    path = out_dir / "report.html"
    path.write_text("\n".join(parts))
    return path
