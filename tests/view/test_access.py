"""clflow view answers only its own page: other origins, other Host names (DNS rebinding) and
requests without the run's token get 403, over HTTP and on the websocket, as a plain client
sends them; the printed address and the cookie its page sets (as a browser) get the viewer."""

import http.client
import socket
from types import SimpleNamespace

import pytest

from clflow.errors import ClflowError
from clflow.view import Access, load_scene
from tests.view._helpers import scene_messages, write_ply

pytest.importorskip("viser")


@pytest.fixture(scope="module")
def viewer(tmp_path_factory):
    from clflow.view import Viewer

    path = tmp_path_factory.mktemp("access") / "scene.ply"
    write_ply(path, n=20)
    viewer = Viewer(load_scene(path), port=0, report=lambda text: None)
    yield viewer
    viewer.close()


def get(viewer, path, **headers):
    """(status, headers, body) of GET ``path`` from the viewer, ``headers`` sent as given."""
    conn = http.client.HTTPConnection("127.0.0.1", viewer.port, timeout=5)
    try:
        conn.request("GET", path, headers={k.replace("_", "-"): v for k, v in headers.items()})
        response = conn.getresponse()
        return response.status, response.headers, response.read()
    finally:
        conn.close()


def handshake_status(url, **options):
    """The HTTP status the viewer answers a websocket handshake to ``url`` with: 101 when it
    opens (and the scene's splats come), else the refusal's (the viewer's reason checked)."""
    from websockets.exceptions import InvalidStatus

    try:
        messages = scene_messages(url, **options)
    except InvalidStatus as exc:
        assert b"this viewer answers" in exc.response.body or b"no token" in exc.response.body
        return exc.response.status_code
    assert any(m["type"] == "GaussianSplatsMessage" for m in messages)
    return 101


def test_the_printed_address_opens_the_page_and_sets_the_cookie(viewer):
    token, port = viewer.token, viewer.port
    status, headers, page = get(viewer, f"/?token={token}")
    assert status == 200 and b"<html" in page
    assert headers["Set-Cookie"] == f"clflow-view-{port}={token}; Path=/; HttpOnly; SameSite=Strict"
    for host in (f"localhost:{port}", f"[::1]:{port}"):  # the viewer's other loopback names
        assert get(viewer, f"/?token={token}", Host=host)[0] == 200
    # the page's websocket, as the browser opens it: no query string, the page's origin, the cookie
    origin, cookie = f"http://127.0.0.1:{port}", f"clflow-view-{port}={token}"
    assert handshake_status(f"ws://127.0.0.1:{port}/", origin=origin, additional_headers={"Cookie": cookie}) == 101
    assert handshake_status(viewer.url(), origin=origin) == 101  # the token in the URL, as a script may
    assert handshake_status(viewer.url()) == 101  # no Origin: not a browser page
    assert get(viewer, "/", Cookie=cookie)[0] == 200


def test_without_the_token_nothing_is_served(viewer):
    port = viewer.port
    for path in ("/", "/?token=", "/?token=wrong", "/index.html"):
        status, headers, body = get(viewer, path)
        assert status == 403 and b"<html" not in body and "Set-Cookie" not in headers
    assert get(viewer, "/", Cookie=f"clflow-view-{port + 1}={viewer.token}")[0] == 403  # another port's cookie
    origin = f"http://127.0.0.1:{port}"
    assert handshake_status(f"ws://127.0.0.1:{port}/", origin=origin) == 403
    assert handshake_status(f"ws://127.0.0.1:{port}/?token=wrong", origin=origin) == 403
    bad_cookie = {"Cookie": f"clflow-view-{port}=wrong"}
    assert handshake_status(f"ws://127.0.0.1:{port}/", origin=origin, additional_headers=bad_cookie) == 403


def test_other_origins_are_refused_even_with_the_token(viewer):
    port = viewer.port
    for origin in ("http://evil.example", f"http://evil.example:{port}", f"http://127.0.0.1:{port + 1}", "null"):
        assert handshake_status(viewer.url(), origin=origin) == 403
    assert get(viewer, f"/?token={viewer.token}", Origin="http://evil.example")[0] == 403


def test_other_host_names_are_refused_even_with_the_token(viewer):
    """A DNS-rebinding page reaches 127.0.0.1 under its own name: the Host header says so."""
    port, path = viewer.port, f"/?token={viewer.token}"
    for host in (f"evil.example:{port}", "evil.example", f"127.0.0.1:{port + 1}", f"127.0.0.1.evil.example:{port}"):
        assert get(viewer, path, Host=host)[0] == 403
    # the websocket of a page at http://evil.example:PORT whose name now points at 127.0.0.1
    sock = socket.create_connection(("127.0.0.1", port), timeout=5)
    url = f"ws://evil.example:{port}{path}"
    assert handshake_status(url, origin=f"http://evil.example:{port}", sock=sock) == 403


def test_hosts_are_the_loopback_names_the_host_given_and_the_address_reached():
    conn = SimpleNamespace(local_address=("192.168.1.5", 8080))
    hosts = {"127.0.0.1:8080", "localhost:8080", "[::1]:8080", "192.168.1.5:8080"}
    assert Access("0.0.0.0", "t").hosts(conn) == hosts  # another machine reaches it by this address
    assert Access("myhost", "t").hosts(conn) == hosts | {"myhost:8080"}
    assert Access("::1", "t").hosts(SimpleNamespace(local_address=("::1", 80, 0, 0))) == {
        *("127.0.0.1", "localhost", "[::1]"),
        *("127.0.0.1:80", "localhost:80", "[::1]:80"),
    }  # port 80: browsers leave it out of Host


def test_a_viser_that_serves_around_the_guard_is_not_started(tmp_path, monkeypatch):
    """The guard wraps websockets' serve() as viser 1.1 calls it; a viser that binds another
    way would serve unchecked: the viewer refuses to start instead."""
    import websockets
    import websockets.asyncio.server
    from viser.infra import _infra

    class Forward:
        def __init__(self, real, **override):
            self.real, self.override = real, override

        def __getattr__(self, name):
            return self.override.get(name, getattr(self.real, name))

    from clflow.view import Viewer

    unguarded = Forward(websockets.asyncio.server, serve=websockets.asyncio.server.serve)  # bound before the guard
    monkeypatch.setattr(
        _infra, "websockets", Forward(websockets, asyncio=Forward(websockets.asyncio, server=unguarded))
    )
    write_ply(tmp_path / "scene.ply", n=5)
    with pytest.raises(ClflowError, match="cannot check who connects"):
        Viewer(load_scene(tmp_path / "scene.ply"), port=0, report=lambda text: None)
