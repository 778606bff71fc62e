"""The real compare stage with a scan as the earlier snapshot: a capture without cameras or
detections (what a scan snapshot is to the comparison) against a photo capture. The object
the photos' detector sees is found added and identified; the one gone from the scan's scene
is a removed-side cluster (the scan has no images to identify it in, and the twin that a
scan starts is empty)."""

from __future__ import annotations

import dataclasses

from tests.workers.pipeline.compare_scene import BASE, CAMS, capture, cart, crate, run


def test_a_photo_capture_compared_with_a_scan() -> None:
    scan = dataclasses.replace(capture(BASE, CAMS, seed=1), cameras=(), detections={})
    result = run(scan, [crate(-0.8, 0.5), cart(0.2, 0.9)], twin=[])
    added = [c for c in result.changes if c.type == "added"]
    assert [c.object_name for c in added] == ["cart"]
    removed_side = [c for c in result.clusters if c.side == "removed"]
    assert len(removed_side) == 1 and removed_side[0].object_name is None
    bin_centre = BASE[1].centroid
    assert abs(removed_side[0].centroid[0] - bin_centre[0]) < 0.1
    assert abs(removed_side[0].centroid[1] - bin_centre[1]) < 0.1
