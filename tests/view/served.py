"""goi view on the demo scene (field-free: its RES mask files), served in this process, for the
tests of the server (tests/security/test_view.py, tests/view/test_browser.py)."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from pathlib import Path

from stages.query.pipeline import PromptSources
from stages.scene.scene import load_scene
from stages.view.session import ViewRun, ViewSession

DEMO = Path(__file__).resolve().parents[2] / "goi_cli" / "demo_scene"


def demo_session(out: Path, **run) -> ViewSession:  # noqa: ANN003
    return ViewSession(
        load_scene(DEMO),
        None,
        PromptSources(res_masks=DEMO / "res"),
        ViewRun(out=out, prompts=DEMO / "prompts.json", port=0, **run),
    )


class Log:
    """The viewer's log lines, kept."""

    def __init__(self) -> None:
        self.lines: list[str] = []

    def log(self, message: str) -> None:
        self.lines.append(message)

    def progress(self, items, label, length=None, show=None):  # noqa: ANN001, ANN201
        yield from items

    def has(self, text: str) -> bool:
        return any(text in line for line in self.lines)


@contextlib.contextmanager
def serving(session: ViewSession) -> Iterator[tuple[object, str, Log]]:
    """(the app, the page's address with its token, the log)."""
    from stages.view.app import ViewerApp

    log = Log()
    app = ViewerApp(session, log)
    url = app.start()
    try:
        yield app, url, log
    finally:
        app.stop()


def wait_for(predicate, what: str, timeout: float = 300.0) -> None:  # noqa: ANN001
    """Wait for a state (never for a time): the timeout only ends a test that hangs."""
    end = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > end:
            raise AssertionError(f"never: {what}")
        time.sleep(0.02)
