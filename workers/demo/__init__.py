"""``make demo``: the whole service on a generated before/after scene, driven over HTTP through
:mod:`app.client` as a capture station would (:mod:`.run`), scored against the scene's ground
truth (:mod:`.evaluate`, shared with the scenario benchmark and the e2e tests), with an HTML
report (:mod:`.report`)."""
