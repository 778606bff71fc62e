"""The operator console's files at ``/ui/``: the built front-end (``make console`` writes
``console/dist``; the folder is the setting ``TWINDELTA_CONSOLE_DIR``), same origin as the
API, no CDN. Until it is built, every ``/ui/`` path answers 503 with a page saying how to
build it. The console routes by URL hash (``/ui/#/environments/{id}``), so the server needs
no fallback for deep links."""

from __future__ import annotations

from pathlib import Path

from starlette.responses import HTMLResponse
from starlette.staticfiles import StaticFiles
from starlette.types import Receive, Scope, Send

NOT_BUILT = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>twindelta console: not built</title></head>
<body style="font-family: sans-serif; max-width: 40em; margin: 4em auto">
<h1>The console is not built</h1>
<p>Build it once from the repository with <code>make console</code> (it needs Node.js and
npm; <code>make serve</code> and <code>make demo</code> build it too), then reload this page.</p>
<p>The service looks for it in <code>{directory}</code> (setting
<code>TWINDELTA_CONSOLE_DIR</code>).</p>
</body></html>
"""


class ConsoleFiles:
    """ASGI app for the console's folder: its files (``index.html`` for ``/ui/``), or 503
    with :data:`NOT_BUILT` while ``index.html`` is missing."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self.files = StaticFiles(directory=directory, html=True, check_dir=False)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and not (self.directory / "index.html").is_file():
            page = NOT_BUILT.replace("{directory}", str(self.directory))
            response = HTMLResponse(page, status_code=503, headers={"Cache-Control": "no-store"})
            await response(scope, receive, send)
            return
        await self.files(scope, receive, send)
