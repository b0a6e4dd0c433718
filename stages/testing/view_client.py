"""A page of `goi view` on the wire, without a browser: a websocket client that connects as
viser's web client does, reports a camera, and records what arrives (time and size), for the
viewer's tests and benchmarks."""

from __future__ import annotations

import threading
import time


class Client:
    """A page on the wire: connects to a goi view server, reports a camera, records messages."""

    def __init__(self, url: str, width: int = 1280, height: int = 800, origin: str | None = None):
        """`url`: the page's address as goi view prints it (http://HOST:PORT/?token=...); the
        websocket is opened as the page opens it, from the page's own origin (or `origin`)."""
        from urllib.parse import urlsplit

        import viser
        from websockets.sync.client import connect
        from websockets.typing import Subprotocol

        protocol = Subprotocol(f"viser-v{viser.__version__}")  # the web client's
        parts = urlsplit(url)
        ws_url = f"ws://{parts.netloc}/" + (f"?{parts.query}" if parts.query else "")
        own = f"http://{parts.netloc}"
        self.ws = connect(
            ws_url,
            subprotocols=[protocol],
            max_size=None,
            origin=origin or own,  # type: ignore[arg-type]
        )
        self.t_open = time.perf_counter()
        self.received: list[tuple[float, int]] = []
        self._stop = threading.Event()
        self.width, self.height = width, height
        self.report_camera()
        self.thread = threading.Thread(target=self._loop, daemon=True)
        self.thread.start()

    def send(self, message: object) -> None:
        """A viser message, as the page sends it."""
        import msgspec

        self.ws.send(
            msgspec.msgpack.encode(
                {"type": type(message).__name__, **message.as_serializable_dict()}  # type: ignore[attr-defined]
            )
        )

    def report_camera(
        self,
        wxyz: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0),
        position: tuple[float, float, float] = (0.0, 0.0, 0.0),
        fov: float = 0.9,
    ) -> None:
        """Report the page's camera, as the browser does whenever it moves."""
        from viser import _messages

        x, y, z = position
        look = (x, y, z + 1.0)
        self.send(
            _messages.ViewerCameraMessage(
                wxyz=wxyz,
                position=position,
                fov=fov,
                near=0.01,
                far=1000.0,
                image_height=self.height,
                image_width=self.width,
                look_at=look,
                up_direction=(0.0, -1.0, 0.0),
            )  # fmt: skip
        )

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                m = self.ws.recv(timeout=0.2)
            except TimeoutError:
                continue
            except Exception:
                return
            self.received.append((time.perf_counter(), len(m)))

    def first_after(self, t: float, timeout: float = 30.0) -> float:
        """When the first message after perf_counter time `t` arrived."""
        end = time.perf_counter() + timeout
        while time.perf_counter() < end:
            later = [r for r, _ in self.received if r >= t]
            if later:
                return later[0]
            time.sleep(0.002)
        raise TimeoutError("no message arrived")

    def settled(self, quiet: float = 2.0, timeout: float = 600.0) -> tuple[float, int]:
        """(time of the last message, bytes received) once nothing arrived for `quiet` s."""
        end = time.perf_counter() + timeout
        while time.perf_counter() < end:
            time.sleep(0.2)
            if self.received and time.perf_counter() - self.received[-1][0] > quiet:
                break
        return self.received[-1][0], sum(n for _, n in self.received)

    def close(self) -> None:
        self._stop.set()
        self.ws.close()
        self.thread.join(5)
