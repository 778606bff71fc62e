"""Which image pairs SfM matches beyond ``exhaustive_max_images``: sequential neighbours in
capture (name) order and, to close loops, each image's nearest images by a bag-of-words
retrieval over its own SIFT descriptors. The pair count grows linearly with the photos.

Indices are positions in the sorted list of image names; a pair is (i, j) with i < j.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

Pair = tuple[int, int]


def sequential_pairs(n_images: int, overlap: int, quadratic: bool = True) -> set[Pair]:
    """Each image with its next ``overlap`` images and, when ``quadratic``, the images
    2^k ahead (k < overlap), as COLMAP's sequential matcher pairs them."""
    pairs: set[Pair] = set()
    for i in range(n_images):
        ahead = [i + d for d in range(1, overlap + 1)]
        if quadratic:
            ahead += [i + 2**k for k in range(overlap)]
        pairs.update((i, j) for j in ahead if j < n_images)
    return pairs


def bag_of_words(
    descriptors: list[NDArray[np.uint8]],
    words: int = 256,
    per_image: int = 1000,
    seed: int = 0,
) -> NDArray[np.float32]:
    """(N, words) L2-normalised tf-idf histograms of each image's SIFT descriptors ((M, 128)
    uint8 each; at most ``per_image`` of them, a seeded sample), on a vocabulary clustered
    (k-means) from the capture's own descriptors; fewer words when there are fewer
    descriptors, all-zero rows when there are none."""
    rng = np.random.default_rng(seed)
    sampled = [
        d[rng.choice(len(d), per_image, replace=False)] if len(d) > per_image else d
        for d in descriptors
    ]
    stack = np.concatenate(sampled).astype(np.float32)
    if len(stack) == 0:
        return np.zeros((len(descriptors), 1), np.float32)
    words = min(words, len(stack))
    cv2.setRNGSeed(seed)
    criteria = (cv2.TERM_CRITERIA_MAX_ITER + cv2.TERM_CRITERIA_EPS, 20, 1.0)
    _, labels, _ = cv2.kmeans(
        stack,
        words,
        None,
        criteria,
        1,
        cv2.KMEANS_PP_CENTERS,  # type: ignore[call-overload]
    )
    labels = labels.ravel()
    counts = np.zeros((len(descriptors), words), np.float32)
    start = 0
    for i, d in enumerate(sampled):
        np.add.at(counts[i], labels[start : start + len(d)], 1.0)
        start += len(d)
    idf = np.log(len(descriptors) / np.maximum((counts > 0).sum(axis=0), 1)).astype(np.float32)
    hist = counts * idf
    return np.asarray(hist / np.maximum(np.linalg.norm(hist, axis=1, keepdims=True), 1e-12))


def retrieval_pairs(histograms: NDArray[np.float32], neighbours: int) -> set[Pair]:
    """Each image with its ``neighbours`` most similar images (cosine of the (N, words)
    histograms of :func:`bag_of_words`)."""
    sim = histograms @ histograms.T
    np.fill_diagonal(sim, -np.inf)
    k = min(neighbours, len(sim) - 1)
    pairs: set[Pair] = set()
    if k <= 0:
        return pairs
    nearest = np.argsort(-sim, axis=1)[:, :k]
    for i, row in enumerate(nearest):
        pairs.update((min(i, int(j)), max(i, int(j))) for j in row)
    return pairs


def matching_pairs(
    descriptors: list[NDArray[np.uint8]], overlap: int, loop_neighbours: int, seed: int = 0
) -> list[Pair]:
    """Sorted union of :func:`sequential_pairs` and, when ``loop_neighbours`` > 0,
    :func:`retrieval_pairs` on the images' descriptors (one (M, 128) uint8 array each)."""
    pairs = sequential_pairs(len(descriptors), overlap)
    if loop_neighbours > 0:
        pairs |= retrieval_pairs(bag_of_words(descriptors, seed=seed), loop_neighbours)
    return sorted(pairs)
