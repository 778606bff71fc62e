"""Small shared pieces of the reconstruct stage: progress type, image listing and loading."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from workers.pipeline.errors import InputError

Progress = Callable[[str, float], None]
IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png"}


def no_progress(stage: str, fraction: float) -> None:
    """The default progress callback: does nothing."""


def list_images(images_dir: Path) -> list[str]:
    """Sorted names of the JPEG/PNG files directly in ``images_dir``; InputError if missing."""
    if not Path(images_dir).is_dir():
        raise InputError(f"images folder {images_dir} does not exist")
    return sorted(p.name for p in Path(images_dir).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def read_image(path: Path) -> NDArray[np.uint8]:
    """(H, W, 3) uint8 BGR image; raises InputError when unreadable."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise InputError(f"cannot read image {Path(path).name}")
    return np.asarray(img, dtype=np.uint8)
