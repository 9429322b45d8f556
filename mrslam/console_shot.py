"""The demo's operator console: served by its server, kept open in a headless browser, and
photographed as the run ends (``console.png``)."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)


class ConsoleShot:
    """The demo's console: the server serves it on ``port`` (a free one for 0) with a token
    made here (or ``MRSLAM_CONSOLE_TOKEN``'s), the address is printed, and a headless
    browser keeps the page open through the run, so that the page as it ended is saved
    (``console.png``) even when the server has already stopped. Without a browser
    (``mrslam.browser``) the screenshot is left out, with a warning."""

    def __init__(self, port: int | None) -> None:
        self.args: list[str] = []
        self.env: dict[str, str] = {}
        self.url = ""
        self._page: Any = None
        if port is None:
            return
        from server.console.service import TOKEN_ENV, new_token

        if port == 0:     # chosen here: a restarted server must come back on the same one
            import socket

            with socket.socket() as s:
                s.bind(("127.0.0.1", 0))
                port = int(s.getsockname()[1])
        token = os.environ.get(TOKEN_ENV) or new_token()
        self.args, self.env = ["--console", str(port)], {TOKEN_ENV: token}
        self.url = f"http://127.0.0.1:{port}/?token={token}"

    def open(self, console: Any) -> None:
        if not self.url:
            return
        console.print(f"[bold]console[/]: {self.url}")
        from mrslam.browser import BrowserUnavailable, ConsolePage

        try:
            self._page = ConsolePage(self.url)
        except BrowserUnavailable as e:
            log.warning("no screenshot of the console at the end: %s", e)
        except Exception as e:   # the run does not depend on it
            log.warning("no screenshot of the console at the end: the browser failed (%s)", e)

    def close(self, path: Path) -> None:
        if self._page is None:
            return
        try:
            self._page.screenshot(path)
            log.info("the console as the run ended: %s", path)
        except Exception as e:
            log.warning("the console's screenshot failed: %s", e)
        finally:
            self._page.close()
            self._page = None
