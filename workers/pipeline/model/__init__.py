"""Library objects prepared for pose estimation.

One module per step: ``load`` (read and sample a mesh or cloud file), ``describe``
(diameter, FPFH descriptors), ``detect_symmetry`` (the rotational symmetry group of the
surface), ``symmetry_group`` (the group's spec, its JSON form and the pose error modulo the
group), ``prepare`` (the work directory: :func:`prepare_model`, :func:`load_prepared`),
``options`` (:class:`ModelOptions` and presets), ``cli`` the command line.
"""

from workers.pipeline.model.describe import diameter_m, fpfh_features, make_cloud
from workers.pipeline.model.load import ModelFileError, check_model_header, load_surface
from workers.pipeline.model.options import MODEL_PRESETS, UNITS_TO_M, ModelOptions
from workers.pipeline.model.prepare import (
    FORMAT_VERSION,
    PreparedModel,
    load_prepared,
    prepare_model,
    with_symmetry,
)

__all__ = [
    "FORMAT_VERSION",
    "MODEL_PRESETS",
    "UNITS_TO_M",
    "ModelFileError",
    "ModelOptions",
    "PreparedModel",
    "check_model_header",
    "diameter_m",
    "fpfh_features",
    "load_prepared",
    "load_surface",
    "make_cloud",
    "prepare_model",
    "with_symmetry",
]
