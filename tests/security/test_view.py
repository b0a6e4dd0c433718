"""goi view as a security reviewer reads it: only its own pages drive it (Host, Origin, the
run's token), nothing leaves the machine (Share refused), and what a page that is not viser's
own sends is refused or dropped, never a traceback. The rules alone (stages.view.access) are
tested without a server; the rest on a real server, with websocket clients that send what
viser's page never sends."""

import urllib.error
import urllib.request

import numpy as np
import pytest

from stages.view.access import Access, server_names

TOKEN = "s3cret-token"
OWN = {"Host": "127.0.0.1:8080"}


def _check(headers, path="/", websocket=False, token=TOKEN):  # noqa: ANN001, ANN202
    return Access(token, server_names("127.0.0.1")).check(path, headers, 8080, websocket)


def test_a_page_needs_the_token_and_gets_a_cookie_for_its_websocket():
    assert not _check(OWN).ok
    assert not _check(OWN, "/?token=wrong").ok
    d = _check(OWN, f"/?token={TOKEN}")
    assert d.ok and d.set_cookie and d.set_cookie.startswith(f"goi-view-8080={TOKEN};")
    assert "HttpOnly" in d.set_cookie and "SameSite=Strict" in d.set_cookie
    assert _check({**OWN, "Cookie": f"goi-view-8080={TOKEN}"}).ok
    assert not _check({**OWN, "Cookie": f"goi-view-8081={TOKEN}"}).ok  # another viewer's


def test_a_websocket_from_another_origin_is_refused_even_with_the_token():
    ws = {**OWN, "Cookie": f"goi-view-8080={TOKEN}"}
    assert _check({**ws, "Origin": "http://127.0.0.1:8080"}, websocket=True).ok
    for origin in (None, "null", "http://evil.example", "http://127.0.0.1:3000",
                   "https://127.0.0.1:8080", "http://localhost:8080"):  # fmt: skip
        headers = ws if origin is None else {**ws, "Origin": origin}
        d = _check(headers, websocket=True)
        assert not d.ok and d.status == 403 and "origin" in d.reason, origin
    # --no-token keeps the origin check
    assert not _check({**OWN, "Origin": "http://evil.example"}, websocket=True, token=None).ok
    assert _check({**OWN, "Origin": "http://127.0.0.1:8080"}, websocket=True, token=None).ok


def test_a_rebound_dns_name_is_refused():
    """evil.example resolving to 127.0.0.1 serves its page at its own origin: Origin and Host
    agree, but the name is not one of this server's."""
    h = {"Host": "evil.example:8080", "Origin": "http://evil.example:8080"}
    assert not _check(h, websocket=True, token=None).ok
    assert not _check({"Host": "evil.example:8080"}, token=None).ok
    assert not _check({"Host": "127.0.0.1:9999"}, f"/?token={TOKEN}").ok  # another port
    assert not _check({}, f"/?token={TOKEN}").ok
    assert _check({"Host": "localhost:8080"}, f"/?token={TOKEN}").ok
    assert _check({"Host": "[::1]:8080"}, f"/?token={TOKEN}").ok


# -- on a real server -----------------------------------------------------------------------


@pytest.fixture
def served(tmp_path):
    pytest.importorskip("viser")
    from tests.view.served import demo_session, serving

    with serving(demo_session(tmp_path / "out", max_pages=2)) as s:
        yield s


def _page_goes_on(app, c) -> None:  # noqa: ANN001
    """The connection goes on after a drop: the page still takes what viser's page sends."""
    from tests.view.served import wait_for

    page = next(iter(app.pages.values()))
    before = page.client.camera.position
    c.report_camera(position=(0.5, 0.0, 0.0))
    wait_for(lambda: tuple(page.client.camera.position) != tuple(before), "camera moved")


def _client(url, **kw):  # noqa: ANN001, ANN003, ANN202
    from stages.testing.view_client import Client

    return Client(url, **kw)


def test_only_the_own_page_with_the_token_is_served(served):
    from websockets.exceptions import InvalidStatus

    app, url, log = served
    bare = url.split("?")[0]
    with pytest.raises(urllib.error.HTTPError) as e:
        urllib.request.urlopen(bare)
    assert e.value.code == 403 and b"token" in e.value.read()
    with urllib.request.urlopen(url) as r:
        assert r.status == 200 and r.headers["X-Frame-Options"] == "DENY"
        assert r.headers["Set-Cookie"].startswith(f"goi-view-{app.server.get_port()}=")
    for kw in ({"origin": "http://evil.example"}, {"origin": "http://127.0.0.1:1"}):
        with pytest.raises(InvalidStatus) as e:
            _client(url, **kw)
        assert e.value.response.status_code == 403
    with pytest.raises(InvalidStatus):
        _client(bare)
    assert not app.pages
    assert log.has("refused a websocket from another origin ('http://evil.example')")
    assert log.has("refused a websocket without the run's token")
    c = _client(url)
    try:
        from tests.view.served import wait_for

        wait_for(lambda: len(app.pages) == 1, "the page built")
    finally:
        c.close()


def test_the_guard_refuses_to_serve_when_viser_bypasses_it(tmp_path, monkeypatch):
    """A viser that no longer serves through the call goi wraps is refused at start."""
    pytest.importorskip("viser")
    import contextlib

    from stages.core.errors import GoiError
    from stages.view import server
    from tests.view.served import demo_session, serving

    monkeypatch.setattr(server, "_websockets_seen_by_viser", lambda g: contextlib.nullcontext())
    with pytest.raises(GoiError, match="no longer serves through the call goi view guards"):
        with serving(demo_session(tmp_path / "out")):
            pass


def test_share_is_refused_and_no_tunnel_is_made(served, monkeypatch):
    from viser import _messages, _viser

    tunnels = []
    monkeypatch.setattr(_viser, "ViserTunnel", lambda *a, **k: tunnels.append(a))
    app, url, log = served
    c = _client(url)
    try:
        from tests.view.served import wait_for

        wait_for(lambda: app.pages, "the page built")
        c.send(_messages.ShareUrlRequest())
        wait_for(lambda: log.has("publish the viewer on the internet (Share)"), "the refusal")
    finally:
        c.close()
    assert tunnels == [] and app.server._share_tunnel is None


def test_frames_that_are_not_messages_are_dropped_with_one_line(served):
    import msgspec
    from viser import _messages

    from tests.view.served import wait_for

    app, url, log = served
    c = _client(url)
    try:
        wait_for(lambda: app.pages, "the page built")
        c.ws.send("not binary")
        c.ws.send(b"\x00\x01 not msgpack")
        c.ws.send(msgspec.msgpack.encode({"type": "NoSuchMessage"}))
        bad = _messages.ViewerCameraMessage(
            wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.0, float("nan"), 0.0), fov=0.9, near=0.01,
            far=1000.0, image_height=800, image_width=1280, look_at=(0.0, 0.0, 1.0),
            up_direction=(0.0, -1.0, 0.0),
        )  # fmt: skip
        c.send(bad)
        wait_for(lambda: log.has("dropped a frame"), "the drop logged")
        # the connection goes on: the page still answers what viser's page sends
        _page_goes_on(app, c)
    finally:
        c.close()
    assert sum("dropped a frame" in line for line in log.lines) == 1
    assert not any("Traceback" in line for line in log.lines)


@pytest.mark.parametrize(
    "event, why",
    [
        (dict(event_type="rect-select", ray_origin=None, ray_direction=None,
              screen_pos=((0.1, 0.2),)), "not a point of the canvas"),
        (dict(event_type="click", ray_origin=None, ray_direction=None,
              screen_pos=((0.1, 0.2),)), "ray is not finite"),
        (dict(event_type="click", ray_origin=(0.0, 0.0, float("inf")),
              ray_direction=(0.0, 0.0, 1.0), screen_pos=((0.5, 0.5),)), "ray is not finite"),
        (dict(event_type="double-click", ray_origin=None, ray_direction=None,
              screen_pos=((0.1, 0.2),)), "no known kind"),
        (dict(event_type="click", ray_origin=(0.0, 0.0, 0.0), ray_direction=(0.0, 0.0, 1.0),
              screen_pos=((0.5, 0.5),), modifier="ctrl+super"), "key modifier"),
    ],
)  # fmt: skip
def test_a_click_or_box_that_is_not_a_point_is_dropped_on_the_wire(served, event, why):
    """What viser's page never sends as a scene click or box (viser's own handler would fail
    on it, a traceback in the log) is dropped with one line; the page goes on."""
    from viser import _messages

    from tests.view.served import wait_for

    app, url, log = served
    c = _client(url)
    try:
        wait_for(lambda: app.pages, "the page built")
        c.send(_messages.ScenePointerMessage(**{"modifier": None, **event}))
        wait_for(lambda: log.has(why), "the drop logged")
        _page_goes_on(app, c)
    finally:
        c.close()
    assert not any("Traceback" in line for line in log.lines)


def test_pages_past_the_cap_are_refused(served):
    from websockets.exceptions import InvalidStatus

    from tests.view.served import wait_for

    app, url, log = served
    a, b = _client(url), _client(url)
    try:
        wait_for(lambda: len(app.pages) == 2, "two pages built")
        with pytest.raises(InvalidStatus) as e:
            _client(url)
        assert e.value.response.status_code == 503
        assert log.has("2 pages open")
    finally:
        a.close()
    wait_for(lambda: len(app.pages) == 1, "the closed page gone")
    c = _client(url)  # a place is free again
    try:
        wait_for(lambda: len(app.pages) == 2, "the new page built")
    finally:
        b.close()
        c.close()


# -- what cannot be served is refused at start, before any work ------------------------------


@pytest.mark.parametrize(
    "args, message",
    [
        (["--host", "no-such-host.invalid"], "--host: no-such-host.invalid does not resolve"),
        (["--host", "203.0.113.7"], "--host: 203.0.113.7 is not an address of this machine"),
        (["--port", "65535"], "--port: ports 65535 to 65535 are all in use"),
        (["--for-seconds", "nan"], "--for-seconds: nan is not a finite number"),
        (["--for-seconds", "inf"], "--for-seconds: inf is not a finite number"),
    ],
)
def test_a_viewer_that_cannot_be_served_is_refused_before_any_work(args, message, tmp_path, capsys):
    import socket

    from goi_cli.main import main
    from tests.view.served import DEMO

    pytest.importorskip("viser")
    busy = socket.socket()
    try:
        busy.bind(("127.0.0.1", 65535))  # the top of the range, taken
        busy.listen()
    except OSError:
        pass  # taken already
    try:
        argv = ["view", "--scene", str(DEMO), "--res-masks", str(DEMO / "res"),
                "--out", str(tmp_path / "out"), *args]  # fmt: skip
        assert main(argv) == 2
    finally:
        busy.close()
    err = capsys.readouterr().err
    assert message in err, err
    assert len(err.strip().splitlines()) == 1, err  # the refusal alone: no line of work first
    assert not (tmp_path / "out").exists()


# -- what goi view writes: inside --out, atomic, recorded, nothing left that blocks ---------


@pytest.fixture(scope="module")
def demo_answer(tmp_path_factory):
    pytest.importorskip("viser")
    from tests.view.served import demo_session

    session = demo_session(tmp_path_factory.mktemp("demo") / "out")
    return session, session.answer("sofa", "lifted_fieldless")


def test_a_symlinked_directory_inside_out_is_never_written_through(demo_answer, tmp_path):
    from stages.core.errors import GoiError
    from stages.view.cameras import browser_camera
    from tests.view.served import demo_session

    _, ans = demo_answer
    session = demo_session(tmp_path / "out")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    session.out.root.mkdir()
    (session.out.root / ans.prompt.name).symlink_to(elsewhere)
    for what in ("selection", "subset", "masks"):
        with pytest.raises(GoiError, match="symbolic link"):
            session.export(ans, what)
    (session.out.root / "cameras").symlink_to(elsewhere)
    cam = browser_camera("b", (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.9, 64, 48)
    with pytest.raises(GoiError, match="symbolic link"):
        session.save_camera(cam)
    assert list(elsewhere.iterdir()) == []


def test_an_interrupted_export_leaves_nothing_that_blocks_the_next(
    demo_answer, tmp_path, monkeypatch
):
    import stages.query.lift_files as lift_files
    from tests.view.served import demo_session

    _, ans = demo_answer
    session = demo_session(tmp_path / "out")
    real, calls = lift_files.write_png, []

    def dies(path, image, force=False):  # noqa: ANN001, ANN202
        calls.append(path)
        if len(calls) == 3:
            raise KeyboardInterrupt  # Ctrl-C, or the process killed, half-way
        real(path, image, force)

    monkeypatch.setattr(lift_files, "write_png", dies)
    with pytest.raises(KeyboardInterrupt):
        session.export(ans, "masks")
    monkeypatch.setattr(lift_files, "write_png", real)
    d = session.answer_dir(ans) / "masks"
    assert not d.exists() or not list(d.iterdir())
    files = session.export(ans, "masks")  # the next export is not blocked
    assert files and all(f.is_file() for f in files)
    import json

    listed = json.loads((session.out.root / "goi-view.json").read_text())["files"]
    assert {str(f.relative_to(session.out.root)) for f in files} <= set(listed)


def test_an_export_past_the_budget_is_refused(demo_answer, tmp_path):
    from stages.core.errors import GoiError
    from tests.view.served import demo_session

    _, ans = demo_answer
    session = demo_session(tmp_path / "out", max_out_mib=1)
    with pytest.raises(GoiError, match="--max-out-mib"):
        session.export(ans, "invert")  # the scene without the sofa: several MiB
    assert not session.answer_dir(ans).exists()
    session.export(ans, "selection")  # small: within it


# -- values a page sends that viser's own page never sends ----------------------------------


def test_malformed_values_from_a_page_are_refused_there_and_the_page_goes_on(served, capfd):
    from viser import _messages

    from tests.view.served import wait_for

    app, url, log = served
    c = _client(url)
    try:
        wait_for(lambda: app.pages, "the page built")
        page = next(iter(app.pages.values()))

        def send(handle, value):  # noqa: ANN001, ANN202
            c.send(_messages.GuiUpdateMessage(handle._impl.uuid, {"value": value}))

        def refused(text, times=1):  # noqa: ANN001, ANN202
            # each value's callback runs on a thread of its own: wait for this refusal's own
            # log line (the n-th of its text) before the next value, so that a late refusal
            # cannot replace the next one's line in the page
            lines = lambda: sum(text in line for line in log.lines)  # noqa: E731
            wait_for(lambda: lines() >= times, f"the log says {text!r} ({times})")
            wait_for(lambda: text in page.status.content, f"the page says {text!r}")
            assert "#b00020" in page.status.content  # shown as an error

        send(page.mode_box, "sparkle")
        refused("highlight: one of tint, isolate, hide")
        send(page.color_box, [1, 2])
        refused("tint: three integers")
        send(page.color_box, [1, 2, 300])
        refused("tint: three integers", times=2)
        wait_for(lambda: page.color_box.value == (255, 0, 140), "the tint put back")
        send(page.route_box, "the fastest")
        refused("route: not one of the routes")
        send(page.history_box, "an answer never given")
        refused("history: not one of the answers")
        send(page.prompt_box, "x" * 5000)  # past any page input: dropped on the wire
        send(page.color_box, "abc")  # text for a colour: viser's own handler fails on it
        c.report_camera(fov=1e-308)  # a field of view that is no angle: dropped
        wait_for(lambda: log.has("input value of over 4096"), "the long value dropped")
        # the page's state is intact and it goes on
        assert page.mode == "tint" and tuple(page.color_box.value) == (255, 0, 140)
        send(page.mode_box, "hide")
        wait_for(lambda: page.mode == "hide", "a good value taken")
        cam = page.browser_camera()
        assert cam is not None and np.isfinite(cam.fx)
    finally:
        c.close()
    err = capfd.readouterr().err
    assert "Traceback" not in err and not any("Traceback" in line for line in log.lines), err


def test_a_swallowed_ctrl_c_still_stops_the_viewer(monkeypatch):
    """A KeyboardInterrupt raised where it is swallowed (a weakref callback, another library)
    is recorded by goi's handler: the serving loop stops at its next step, not in an hour."""
    import math

    import stages.core.interrupts as interrupts
    from goi_cli.view_commands import serve_until

    monkeypatch.setattr(interrupts, "_pending", True)
    with pytest.raises(KeyboardInterrupt):
        serve_until(math.inf)


@pytest.mark.slow
def test_ctrl_c_stops_goi_view(tmp_path):
    import os
    import re
    import signal
    import subprocess
    import sys

    from tests.view.served import DEMO

    pytest.importorskip("viser")
    cmd = [sys.executable, "-m", "goi_cli", "view", "--scene", str(DEMO), "--res-masks",
           str(DEMO / "res"), "--out", str(tmp_path / "out"), "--port", "0"]  # fmt: skip
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONFAULTHANDLER": "1"}

    # a user's shell delivers Ctrl-C; a test run started in the background (nohup, `&`)
    # ignores SIGINT, and a child that starts ignoring it keeps ignoring it (as goi must)
    def as_a_shell_starts_it() -> None:
        signal.signal(signal.SIGINT, signal.SIG_DFL)

    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True, env=env,
                            preexec_fn=as_a_shell_starts_it)  # fmt: skip
    assert proc.stderr is not None
    for line in proc.stderr:  # the server is up once it prints its address
        if re.search(r"goi view: http://", line):
            break
    proc.send_signal(signal.SIGINT)
    try:
        code = proc.wait(timeout=120)
    except subprocess.TimeoutExpired:  # say where it hung: every thread's stack (faulthandler)
        proc.send_signal(signal.SIGABRT)
        try:
            proc.wait(timeout=30)
        finally:
            proc.kill()
        pytest.fail(f"goi view did not stop within 120 s of a Ctrl-C; its log after: "
                    f"{proc.stderr.read()[-6000:]}")  # fmt: skip
    assert code == 130


def test_a_flood_of_refusals_does_not_flood_the_log():
    from stages.view.server import LOG_LINES, Guard

    lines: list[str] = []
    guard = Guard(Access(TOKEN, server_names("127.0.0.1")), 8, 4096, lines.append)
    for i in range(1000):
        guard.log(f"refused request {i}")
    assert len(lines) == LOG_LINES + 1 and "are not logged" in lines[-1]
