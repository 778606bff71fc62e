"""The console built with npm and opened in Debian's Chromium through Playwright: what the
console benchmark and the console's browser tests share."""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[1]
CONSOLE_DIR = REPO_ROOT / "console"
CONSOLE_DIST = CONSOLE_DIR / "dist"
CHROMIUM = "/usr/bin/chromium"
# Software WebGL in a headless browser (no GPU on the test machines).
CHROMIUM_ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"]


def console_sources_newer_than_build() -> bool:
    """Whether console/dist is missing or older than any source, config or the lock file."""
    index = CONSOLE_DIST / "index.html"
    if not index.exists():
        return True
    built = index.stat().st_mtime
    sources = [CONSOLE_DIR / "package-lock.json", CONSOLE_DIR / "index.html"]
    sources += [p for p in (CONSOLE_DIR / "src").rglob("*") if p.is_file()]
    sources += list(CONSOLE_DIR.glob("*.config.*")) + list(CONSOLE_DIR.glob("tsconfig*.json"))
    return any(p.stat().st_mtime > built for p in sources if p.exists())


def build_console() -> Path:
    """Build console/dist with npm (``npm ci`` when node_modules is missing) unless it is
    up to date; returns the dist folder. Raises RuntimeError naming what is missing."""
    if not console_sources_newer_than_build():
        return CONSOLE_DIST
    npm = shutil.which("npm")
    if npm is None:
        raise RuntimeError("npm is not installed: the console needs Node.js 20+ and npm")
    if not (CONSOLE_DIR / "node_modules").exists():
        subprocess.run([npm, "ci", "--no-audit", "--no-fund"], cwd=CONSOLE_DIR, check=True)
    subprocess.run([npm, "run", "build"], cwd=CONSOLE_DIR, check=True)
    return CONSOLE_DIST


@contextmanager
def chromium() -> Iterator[Any]:
    """Debian's Chromium, headless with software WebGL, launched by Playwright (a
    ``playwright.sync_api.Browser``), closed on exit. Raises RuntimeError when
    /usr/bin/chromium is missing; ImportError without the playwright package."""
    from playwright.sync_api import sync_playwright

    if not Path(CHROMIUM).exists():
        raise RuntimeError(f"{CHROMIUM} is missing: install Debian's chromium (make test-tools)")
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        try:
            yield browser
        finally:
            browser.close()


def wait_for_cloud(page: Any, timeout_s: float = 60) -> dict[str, Any]:
    """Wait until the page's 3D view has drawn its first frame with the cloud; returns the
    page's ``window.__twindelta`` (cloudReadyMs: ms from navigation start, cloudPoints,
    cloudTotalPoints, cloudSource 'decimated' or 'full', modelsDrawn). Raises Playwright's
    TimeoutError after ``timeout_s``."""
    page.wait_for_function(
        "window.__twindelta && window.__twindelta.cloudReadyMs !== null",
        timeout=timeout_s * 1000,
    )
    state: dict[str, Any] = page.evaluate("window.__twindelta")
    return state
