"""The option schema the API checks posted options against matches the workers' options."""

from __future__ import annotations

import dataclasses

import pytest

from app.core.errors import InvalidInput
from app.core.options import check_stage_options, schema
from workers.pipeline.compare.options import PRESETS as COMPARE_PRESETS
from workers.pipeline.compare.options import options_from_json
from workers.pipeline.errors import InputError
from workers.pipeline.inventory.options import INVENTORY_PRESETS, inventory_options_from_json
from workers.pipeline.option_schema import option_schema
from workers.pipeline.reconstruct.options import PRESETS as RECONSTRUCT_PRESETS
from workers.pipeline.reconstruct.options import options_from_preset


def test_the_stored_schema_is_the_workers_own() -> None:
    """app/core/option_schema.json is what the workers' option classes give now (make lint
    checks the same; `make option-schema` rewrites it)."""
    assert schema() == option_schema()


def test_every_preset_written_out_in_full_passes_the_api_check() -> None:
    """Each preset of both stages, every option written out as JSON, passes the API's check,
    and the stage rebuilds the same options from it."""
    for name, opts in RECONSTRUCT_PRESETS.items():
        full = {
            k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(opts).items()
        }
        check_stage_options("reconstruct", {"preset": name, **full})
        assert options_from_preset("default", **full) == opts
    for name, copts in COMPARE_PRESETS.items():
        full = copts.to_json()
        check_stage_options("compare", {"preset": name, **full})
        assert options_from_json("default", full) == copts


@pytest.mark.parametrize(
    ("stage", "options"),
    [
        ("reconstruct", {"cuda_dense": "yes"}),
        ("reconstruct", {"planar_min_points": 2.5}),
        ("reconstruct", {"nope": 1}),
        ("compare", {"nope": 1}),
        ("compare", {"threshold": {"kind": "mean_std", "sigma": 1.0}}),
    ],
)
def test_what_the_api_refuses_the_stage_refuses_too(stage: str, options: dict[str, object]) -> None:
    with pytest.raises(InvalidInput):
        check_stage_options(stage, options)
    with pytest.raises(InputError):
        if stage == "reconstruct":
            options_from_preset("default", **options)
        else:
            options_from_json("default", options)


def test_every_inventory_preset_written_out_in_full_passes_the_api_check() -> None:
    """Each inventory preset as JSON (its compare overrides and pose options included)
    passes the API's check and rebuilds the same options; what the stage refuses in its
    nested options, the API refuses too."""
    for name, iopts in INVENTORY_PRESETS.items():
        full = iopts.to_json()
        check_stage_options("inventory", {"preset": name, **full})
        assert inventory_options_from_json(full) == iopts
    for bad in (
        {"compare": {"preset": "lod"}},
        {"compare": {"threshold": {"kind": "mean_std", "sigma": 1.0}}},
        {"pose": {"n_seed": 4}},
        {"band_min_m": "4 mm"},
    ):
        with pytest.raises(InvalidInput):
            check_stage_options("inventory", bad)
        with pytest.raises(InputError):
            inventory_options_from_json(bad).compare_options()
