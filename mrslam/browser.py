"""A headless browser on the operator console: the demo's screenshot at the end of a run, the
console's benchmark (``bench/console.py``) and its tests.

Debian's ``chromium`` (``deploy/bootstrap.sh`` installs it with the dev extra), driven by
``playwright`` (dev extra); playwright's own browser download is never used. One thread uses
a ``ConsolePage`` (playwright's synchronous API).
"""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path
from typing import Any

CHROMIUM = "/usr/bin/chromium"


class BrowserUnavailable(RuntimeError):
    """No browser to drive: what is missing, and how to install it."""


def chromium_path() -> str:
    """The chromium to launch, or ``BrowserUnavailable`` saying what to install."""
    path = os.environ.get("MRSLAM_CHROMIUM") or (CHROMIUM if Path(CHROMIUM).exists()
                                                 else shutil.which("chromium"))
    if not path:
        raise BrowserUnavailable("no chromium (sudo apt-get install -y chromium)")
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError as e:
        raise BrowserUnavailable("no playwright (pip install -e '.[dev]')") from e
    return path


class ConsolePage:
    """The console's page at ``url`` in ``browsers`` headless chromiums of their own (one
    playwright, which allows one per thread): ``page`` is the first one's, ``pages`` all."""

    def __init__(self, url: str, width: int = 1500, height: int = 950,
                 must_load: bool = True, browsers: int = 1) -> None:
        """``must_load`` False: a page the server refuses (chromium fails to load an error
        with no body) is no error here; ``last_status`` and ``load_error`` say what came."""
        from playwright.sync_api import Error, sync_playwright

        exe = chromium_path()
        self._pw = sync_playwright().start()
        self.browsers: list[Any] = []
        self.pages: list[Any] = []
        statuses: list[int] = []
        self.load_error = ""
        try:
            args = ["--no-sandbox"] if os.geteuid() == 0 else []   # chromium refuses root
            for _ in range(browsers):
                browser = self._pw.chromium.launch(executable_path=exe, headless=True,
                                                   args=[*args, "--disable-gpu"])
                self.browsers.append(browser)
                page = browser.new_page(viewport={"width": width, "height": height})
                self.pages.append(page)
                page.on("response", lambda r: statuses.append(r.status)
                        if r.request.is_navigation_request() else None)
                try:
                    page.goto(url)
                except Error as e:
                    if must_load:
                        raise
                    self.load_error = str(e)
        except Exception:
            self.close()
            raise
        self.page = self.pages[0]
        #: the HTTP status the page itself was served with (the last browser's)
        self.last_status = statuses[-1] if statuses else None

    def stats(self, index: int = 0) -> dict[str, Any]:
        """A page's own counters (``window.mrslam.stats``)."""
        return dict(self.pages[index].evaluate("() => window.mrslam.stats"))

    def wait_for(self, js: str, timeout_s: float, every_s: float = 0.05) -> Any:
        """Wait until the expression ``js`` is truthy on the first page (polled from here:
        the page's content security policy forbids the evaluated strings a wait inside the
        page would need); its value, or ``TimeoutError``."""
        deadline = time.monotonic() + timeout_s
        while True:
            value = self.page.evaluate(f"() => ({js})")
            if value:
                return value
            if time.monotonic() > deadline:
                raise TimeoutError(f"the page never had {js} within {timeout_s:.0f} s")
            self.page.wait_for_timeout(every_s * 1000)

    def screenshot(self, path: Path) -> Path:
        self.page.screenshot(path=str(path), full_page=True)
        return path

    def close(self) -> None:
        try:
            for b in self.browsers:
                b.close()
        finally:
            self.browsers = []
            self._pw.stop()

    def __enter__(self) -> ConsolePage:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
