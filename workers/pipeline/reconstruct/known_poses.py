"""Sparse structure when every camera's pose is given: ORB matches between nearby views,
filtered by the known epipolar geometry and triangulated with the given poses.

Gives the MVS stage what SfM would: shared points per view pair (overlap) and the depth
range. No pose is estimated; the given env_from_cam define the frame.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from workers.pipeline.reconstruct.mvs import DenseView
from workers.pipeline.reconstruct.options import ReconstructOptions

FloatArray = NDArray[np.float64]


def _candidate_pairs(
    views: list[DenseView], per_view: int, max_angle_deg: float
) -> set[tuple[int, int]]:
    centres = np.stack([v.env_from_cam[:3, 3] for v in views])
    axes = np.stack([v.env_from_cam[:3, 2] for v in views])
    pairs: set[tuple[int, int]] = set()
    for i in range(len(views)):
        cos = axes @ axes[i]
        dist = np.linalg.norm(centres - centres[i], axis=1)
        ok = (cos >= np.cos(np.radians(max_angle_deg))) & (np.arange(len(views)) != i)
        for j in [int(j) for j in np.argsort(dist) if ok[j]][:per_view]:
            pairs.add((min(i, j), max(i, j)))
    return pairs


def triangulate_known(
    views: list[DenseView], options: ReconstructOptions, pairs_per_view: int = 5
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Sparse env-frame points (N, 3) and their (N, V) visibility from given poses.

    Matches keep only pairs within 2 px of their epipolar line, positive depth in both views
    and reprojection error ≤ 2 px. Each point is seen by exactly the two views of its pair.
    """
    orb = cv2.ORB.create(nfeatures=1000, fastThreshold=10)
    feats = []
    for v in views:
        gray = cv2.cvtColor(v.image, cv2.COLOR_BGR2GRAY)
        kps, desc = orb.detectAndCompute(gray, None)
        pts = np.array([kp.pt for kp in kps], dtype=np.float64).reshape(-1, 2)
        feats.append((pts, desc))
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
    all_pts: list[FloatArray] = []
    all_vis: list[NDArray[np.bool_]] = []
    for i, j in sorted(_candidate_pairs(views, pairs_per_view, options.max_viewing_angle_deg)):
        (pi, di), (pj, dj) = feats[i], feats[j]
        if di is None or dj is None or len(pi) < 8 or len(pj) < 8:
            continue
        matches = matcher.match(di, dj)
        if len(matches) < 8:
            continue
        xi = pi[[m.queryIdx for m in matches]]
        xj = pj[[m.trainIdx for m in matches]]
        proj_i = views[i].k_matrix @ views[i].cam_from_env[:3]
        proj_j = views[j].k_matrix @ views[j].cam_from_env[:3]
        # fundamental matrix from the known poses
        j_from_i = views[j].cam_from_env @ views[i].env_from_cam
        t = j_from_i[:3, 3]
        tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
        fmat = (
            np.linalg.inv(views[j].k_matrix).T
            @ tx
            @ j_from_i[:3, :3]
            @ np.linalg.inv(views[i].k_matrix)
        )
        hi = np.hstack([xi, np.ones((len(xi), 1))])
        hj = np.hstack([xj, np.ones((len(xj), 1))])
        lines = hi @ fmat.T
        epi = np.abs(np.sum(lines * hj, axis=1)) / (np.linalg.norm(lines[:, :2], axis=1) + 1e-12)
        keep = epi < 2.0
        if keep.sum() < 8:
            continue
        xh = cv2.triangulatePoints(proj_i, proj_j, xi[keep].T, xj[keep].T)
        p = (xh[:3] / xh[3]).T
        good = np.ones(len(p), bool)
        for proj, x in ((proj_i, xi[keep]), (proj_j, xj[keep])):
            q = np.hstack([p, np.ones((len(p), 1))]) @ proj.T
            with np.errstate(divide="ignore", invalid="ignore"):
                err = np.linalg.norm(q[:, :2] / q[:, 2:3] - x, axis=1)
            good &= (q[:, 2] > 0) & (err < 2.0)
        if good.sum() == 0:
            continue
        vis = np.zeros((int(good.sum()), len(views)), bool)
        vis[:, [i, j]] = True
        all_pts.append(p[good])
        all_vis.append(vis)
    if not all_pts:
        return np.zeros((0, 3)), np.zeros((0, len(views)), bool)
    return np.concatenate(all_pts), np.concatenate(all_vis)
