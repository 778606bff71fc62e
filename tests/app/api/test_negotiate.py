"""Accept negotiation (RFC 9110 §12.5.1): the most specific matching range weighs a type,
q=0 refuses it, ties go to the first offer, and nothing acceptable is a 406."""

from __future__ import annotations

import pytest

from app.api.negotiate import NotAcceptable, choose

OFFERS = ["application/json", "model/gltf-binary"]


@pytest.mark.parametrize(
    ("accept", "chosen"),
    [
        (None, "application/json"),
        ("", "application/json"),
        ("*/*", "application/json"),
        ("model/gltf-binary", "model/gltf-binary"),
        ("MODEL/GLTF-BINARY", "model/gltf-binary"),
        ("model/*", "model/gltf-binary"),
        ("application/json;q=0.4, model/gltf-binary;q=0.8", "model/gltf-binary"),
        ("model/gltf-binary;q=0.5, application/json", "application/json"),
        ("application/json;q=0, */*", "model/gltf-binary"),
        ("*/*;q=0.9, model/gltf-binary;q=0.1", "application/json"),  # the specific range wins
        ("text/html, application/xhtml+xml, */*;q=0.8", "application/json"),  # a browser
        ("model/gltf-binary;q=nan, application/json;q=0.2", "application/json"),
    ],
)
def test_the_preferred_offer_is_chosen(accept: str | None, chosen: str) -> None:
    assert choose(accept, OFFERS) == chosen


@pytest.mark.parametrize(
    "accept", ["text/html", "application/json;q=0, model/gltf-binary;q=0", "*/*;q=0"]
)
def test_nothing_acceptable_is_406_naming_the_offers(accept: str) -> None:
    with pytest.raises(NotAcceptable, match="model/gltf-binary") as caught:
        choose(accept, OFFERS)
    assert caught.value.status_code == 406
