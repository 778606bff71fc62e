"""Typed failures of the reconstruct stage; each carries a stable ``code`` for the job row."""

from __future__ import annotations

from workers.pipeline.errors import ReconstructionError


class TooFewImages(ReconstructionError):
    """Fewer readable images than a reconstruction needs. Upload more overlapping photos."""

    code = "TooFewImages"


class ImagesDoNotOverlap(ReconstructionError):
    """Feature matching found no image pairs that share enough of the scene."""

    code = "ImagesDoNotOverlap"


class TooFewImagesRegistered(ReconstructionError):
    """Structure from motion registered too small a share of the images."""

    code = "TooFewImagesRegistered"


class MarkersNotFound(ReconstructionError):
    """Reference markers were given but too few were seen in at least two registered images."""

    code = "MarkersNotFound"


class NoReferenceFrame(ReconstructionError):
    """Neither reference markers nor camera poses define the environment frame and scale."""

    code = "NoReferenceFrame"


class DenseReconstructionFailed(ReconstructionError):
    """Multi-view stereo produced no usable depth (no well-conditioned pairs, or no texture)."""

    code = "DenseReconstructionFailed"
