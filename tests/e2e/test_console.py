"""The operator console in a real browser (Playwright driving Debian's Chromium, headless,
software WebGL) against the real embedded service that processed a small generated scene
(16 views at 640x480, one moved object): sign-in, environments, the 3D view's pixels, the
twin table, the change panel's pose, the photo view's boxes, upload and cancel, a read key
that cannot upload, a wrong key. Screenshots of every page go to the test's folder and to
/tmp/console-shots/."""

from __future__ import annotations

import io
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from app.client import check, poll_job
from bench.console_browser import build_console, chromium, wait_for_cloud
from tests.e2e.console_fixtures import EMBEDDED_ADMIN_KEY as ADMIN_KEY
from tests.e2e.console_fixtures import SHOTS_DIR, ProcessedScene, create_key

# the first test also processes the scene (two reconstructions and a comparison, 2-4 min)
# unless the full flow did (they share conftest's small_scene)
pytestmark = [pytest.mark.slow, pytest.mark.e2e, pytest.mark.timeout(900)]
pytest.importorskip("playwright.sync_api")
CLEAR_RGB = np.array([0x14, 0x17, 0x1C])  # the viewer's clear colour (console/src/viewer.ts)


class Shots:
    """Screenshots saved under the test's folder and copied to /tmp/console-shots/."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)
        SHOTS_DIR.mkdir(parents=True, exist_ok=True)

    def take(self, page: Any, name: str) -> Path:
        path = self.folder / f"{name}.png"
        page.screenshot(path=str(path))
        shutil.copy(path, SHOTS_DIR / path.name)
        return path


@pytest.fixture(scope="module")
def api(embedded_api: httpx.Client) -> httpx.Client:
    """The session's embedded service (conftest's embedded_api) with the console built."""
    build_console()
    return embedded_api


@pytest.fixture(scope="module")
def service(api: httpx.Client, small_scene: ProcessedScene) -> tuple[httpx.Client, ProcessedScene]:
    """The service once it has processed the small generated scene."""
    return api, small_scene


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    try:
        with chromium() as b:
            yield b
    except RuntimeError as missing:
        pytest.fail(str(missing))


def new_page(browser: Any, width: int = 1280, height: int = 800) -> Any:
    context = browser.new_context(viewport={"width": width, "height": height})
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.errors = errors
    return page


def sign_in(page: Any, base: str, key: str, listed: bool = True) -> None:
    """Sign in with ``key``; with ``listed``, wait for the environments' list."""
    page.goto(f"{base}/ui/")
    page.get_by_test_id("signin-key").fill(key)
    page.get_by_test_id("signin-submit").click()
    if listed:
        page.get_by_test_id("env-list").wait_for()


def busy_tiles(png: bytes, grid: int = 3, min_fraction: float = 0.05) -> list[float]:
    """The fraction of pixels of each tile (grid x grid) that differ from the clear colour by
    more than 40 (sum over RGB); the grid lines alone stay under min_fraction of a tile."""
    from PIL import Image

    rgb = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
    differs = np.abs(rgb - CLEAR_RGB).sum(axis=2) > 40
    h, w = differs.shape
    return [
        float(
            differs[i * h // grid : (i + 1) * h // grid, j * w // grid : (j + 1) * w // grid].mean()
        )
        for i in range(grid)
        for j in range(grid)
    ]


def test_console_shows_the_twin_the_change_and_its_photos(
    service: tuple[httpx.Client, ProcessedScene], browser: Any, tmp_path: Path
) -> None:
    client, scene = service
    base = str(client.base_url).rstrip("/")
    shots = Shots(tmp_path / "shots")
    comparison = check(client.get(f"/v1/comparisons/{scene.comparison_id}"), 200)
    moved_object = scene.truth["changes"][0]["object"]
    (change,) = [c for c in comparison["changes"] if c["object"] == moved_object]
    assert change["type"] == "moved"
    twin = check(client.get(f"/v1/environments/{scene.environment_id}/state"), 200)
    placed = {o["object"] for o in scene.truth["after"]}

    page = new_page(browser)
    page.goto(f"{base}/ui/")
    page.get_by_test_id("signin-key").wait_for()
    shots.take(page, "01-signin")
    sign_in(page, base, ADMIN_KEY)
    rows = page.get_by_test_id("env-row").filter(has_text="cell")
    assert rows.count() == 1
    shots.take(page, "02-environments")

    rows.first.click()
    wait_for_cloud(page)
    page.wait_for_function("window.__twindelta.modelsDrawn >= 1", timeout=30_000)
    page.get_by_test_id("twin-row").first.wait_for()
    page.wait_for_timeout(500)
    state = page.evaluate("window.__twindelta")
    assert state["cloudSource"] == "decimated" and 0 < state["cloudPoints"] <= 300_000
    canvas = page.get_by_test_id("viewer-canvas")
    tiles = busy_tiles(canvas.screenshot())
    assert sum(f > 0.05 for f in tiles) >= 5, tiles  # the cloud covers most of the view
    shots.take(page, "03-environment")

    # the table lists the twin's instances (every one an object placed in the scene), the
    # moved one marked with its change
    twin_rows = page.get_by_test_id("twin-row")
    listed = {
        (r.get_attribute("data-instance"), r.get_attribute("data-object")) for r in twin_rows.all()
    }
    assert listed == {(o["instance_id"], o["object"]) for o in twin["objects"]}
    assert {cls for _id, cls in listed} <= placed and moved_object in {cls for _id, cls in listed}
    moved_row = page.locator(f'[data-testid="twin-row"][data-object="{moved_object}"]')
    assert moved_row.get_attribute("data-change") == f"change:{change['id']}"
    timeline = page.get_by_test_id("timeline")
    assert timeline.get_by_test_id("snapshot-item").count() == 2
    assert "1 moved" in timeline.get_by_test_id("comparison-item").first.inner_text()

    moved_row.click()
    panel = page.get_by_test_id("change-panel")
    panel.wait_for()
    cells = panel.get_by_test_id("pose-matrix").locator("td").all_inner_texts()
    expected = [f"{v:.4f}" for row in change["pose"] for v in row]
    assert cells == expected
    assert (
        panel.get_by_test_id("ident-table")
        .locator("tr.selected")
        .inner_text()
        .startswith(moved_object)
    )
    panel.get_by_test_id("history-table").wait_for()
    shots.take(page, "04-change-panel")

    panel.get_by_test_id("views-button").click()
    page.get_by_test_id("view-item").first.click()
    photo = page.get_by_test_id("photo-view")
    photo.get_by_test_id("photo-box").first.wait_for()
    assert photo.get_by_test_id("photo-box").count() >= 1
    assert photo.get_by_test_id("photo-outline").count() == 1
    boxes = [b.get_attribute("data-class") for b in photo.get_by_test_id("photo-box").all()]
    assert moved_object in boxes
    shots.take(page, "05-photo")
    page.keyboard.press("Escape")
    assert page.get_by_test_id("photo-view").count() == 0

    tablet = new_page(browser, 820, 1180)
    sign_in(tablet, base, ADMIN_KEY)
    tablet.goto(f"{base}/ui/#/environments/{scene.environment_id}")
    wait_for_cloud(tablet)
    tablet.locator(f'[data-testid="twin-row"][data-object="{moved_object}"]').click()
    tablet.get_by_test_id("change-panel").wait_for()
    tablet.wait_for_timeout(500)
    shots.take(tablet, "06-environment-tablet")
    assert page.errors == [] and tablet.errors == []


def test_upload_then_cancel_from_the_console(
    service: tuple[httpx.Client, ProcessedScene], browser: Any, tmp_path: Path
) -> None:
    client, scene = service
    base = str(client.base_url).rstrip("/")
    shots = Shots(tmp_path / "shots")
    page = new_page(browser)
    sign_in(page, base, ADMIN_KEY)
    page.goto(f"{base}/ui/#/environments/{scene.environment_id}")
    page.get_by_test_id("upload-drop").wait_for()
    capture = scene.scene_dir / "after"
    page.get_by_test_id("upload-input").set_input_files(capture)
    page.get_by_text("uploaded: snapshot #3").wait_for(timeout=60_000)
    item = page.get_by_test_id("snapshot-item").filter(has=page.get_by_text("#3", exact=True))
    item.get_by_test_id("job-progress").wait_for(timeout=30_000)
    bar = f"li[data-id='{item.get_attribute('data-id')}'] [data-job]"
    page.wait_for_function(
        "bar => document.querySelector(bar)?.textContent.startsWith('running')",
        arg=bar,
        timeout=60_000,
    )
    # a poll that only moves the progress updates the bar in place: the cancel button is
    # the same node (a click pressed on one render and released on the next is lost)
    button = item.get_by_test_id("cancel-job").element_handle()
    page.wait_for_function(
        "([bar, shown]) => document.querySelector(bar)?.textContent !== shown",
        arg=[bar, page.locator(bar).inner_text()],
        timeout=60_000,
    )
    assert button.evaluate("el => el.isConnected")
    shots.take(page, "07-upload-progress")
    item.get_by_test_id("cancel-job").click()
    item.locator(".badge.cancelled").wait_for(timeout=60_000)
    snapshots = check(client.get(f"/v1/environments/{scene.environment_id}/snapshots"), 200)
    assert isinstance(snapshots, list) and snapshots[0]["seq"] == 3
    assert snapshots[0]["state"] == "cancelled"
    shots.take(page, "08-upload-cancelled")
    assert page.errors == []


def test_a_read_key_sees_but_cannot_upload(
    service: tuple[httpx.Client, ProcessedScene], browser: Any, tmp_path: Path
) -> None:
    client, scene = service
    base = str(client.base_url).rstrip("/")
    shots = Shots(tmp_path / "shots")
    read_key = create_key(client, "console reader", ["read"])
    page = new_page(browser)
    sign_in(page, base, read_key)
    page.get_by_test_id("env-row").first.click()
    page.get_by_test_id("twin-row").first.wait_for()
    assert page.get_by_test_id("upload-forbidden").is_visible()
    assert page.get_by_test_id("upload-drop").count() == 0
    assert page.get_by_test_id("rerun-comparison").count() == 0
    shots.take(page, "09-read-key")
    refused = httpx.post(
        f"{base}/v1/environments/{scene.environment_id}/snapshots",
        headers={"Authorization": f"Bearer {read_key}"},
        files=[("images", ("a.png", b"\x89PNG\r\n\x1a\n"))],
    )
    assert refused.status_code == 403, refused.text


def test_a_wrong_key_is_unauthorised(api: httpx.Client, browser: Any, tmp_path: Path) -> None:
    client = api
    base = str(client.base_url).rstrip("/")
    shots = Shots(tmp_path / "shots")
    page = new_page(browser)
    sign_in(page, base, "td_not_a_key_0123456789abcdef", listed=False)
    banner = page.get_by_test_id("error-banner")
    banner.wait_for()
    assert "Unauthorised" in banner.inner_text()
    assert page.evaluate("sessionStorage.length") == 0
    shots.take(page, "10-unauthorised")
    # a deep link without a key lands on the sign-in page
    page.goto(f"{base}/ui/#/environments/anything")
    page.get_by_test_id("signin-key").wait_for()


def test_empty_and_failed_states(api: httpx.Client, browser: Any, tmp_path: Path) -> None:
    """An environment without snapshots says so; a capture the reconstruction cannot use
    shows its job's error code and detail in the timeline."""
    from PIL import Image

    shots = Shots(tmp_path / "shots")
    base = str(api.base_url).rstrip("/")
    env = check(api.post("/v1/environments", json={"name": "empty", "classes": ["box"]}), 201)
    page = new_page(browser)
    sign_in(page, base, ADMIN_KEY)
    page.goto(f"{base}/ui/#/environments/{env['id']}")
    page.get_by_text("No snapshots yet.").wait_for()
    page.get_by_text("No reconstructed snapshot yet").wait_for()
    assert page.get_by_text("The twin has no objects yet.").is_visible()
    shots.take(page, "11-empty-environment")

    rng = np.random.default_rng(0)
    files = []
    for i in range(3):  # noise: nothing for structure from motion to match
        png = io.BytesIO()
        Image.fromarray(rng.integers(0, 255, (240, 320, 3), dtype=np.uint8)).save(png, "PNG")
        files.append(("images", (f"noise_{i}.png", png.getvalue(), "image/png")))
    accepted = check(api.post(f"/v1/environments/{env['id']}/snapshots", files=files), 202)
    job = poll_job(api, accepted["job"]["id"], "noise", 300, quiet=True)
    assert job["state"] == "failed", job
    banner = page.get_by_test_id("timeline").get_by_test_id("error-banner")
    banner.wait_for(timeout=30_000)  # the page looks for new snapshots every 10 s
    assert job["error"]["code"] in banner.inner_text()
    assert (job["error"]["detail"] or "")[:40] in banner.inner_text()
    shots.take(page, "12-failed-job")
    assert page.errors == []
