"""The viewer answers only its own page (issue 32): a real viewer on a free port, spoken to the way an attacking
page (or a script) would, over raw HTTP and viser's own websocket protocol.

Before the gate, a websocket with `Origin: http://evil.example.com` (and `Host: evil`) was let in, received every
training photo, and could drive the recorder so that it saved over the scene's transforms.json
(`test_recorder_over_the_websocket_stays_in_paths_dir` replays that attack with an admitted client).
"""

from __future__ import annotations

import json
import socket
import time
from pathlib import Path

import msgspec
import numpy as np
import pytest
import viser
import zstandard
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

import nerfpipe.stages.view as view
from nerfpipe.data.errors import UserError
from nerfpipe.stages.view.gate import Gate, gated
from nerfpipe.stages.view.recorder import PathRecorder
from tests.test_render_stage import sphere_scene

PROTOCOL = f"viser-v{viser.__version__}"


@pytest.fixture
def scene_dir(tmp_path) -> Path:
    sphere_scene(tmp_path / "scene", views=4, w=16, h=12)
    return tmp_path / "scene"


@pytest.fixture
def viewer(scene_dir):
    v = view.serve(view.Config(target=scene_dir, port=0))
    yield v
    v.stop()


def request(
    port: int, host: str, *, origin: str | None = None, path: str = "/", cookie: str | None = None, upgrade: bool = True
) -> tuple[int, dict[str, str], bytes]:
    """One raw HTTP request (a websocket upgrade unless `upgrade=False`) to 127.0.0.1:port with exactly these
    Host / Origin / Cookie headers -> (status, headers, body: at most 4 kB of it)."""
    lines = [f"GET {path} HTTP/1.1", f"Host: {host}"]
    if upgrade:
        lines += [
            "Upgrade: websocket",
            "Connection: Upgrade",
            "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==",
            "Sec-WebSocket-Version: 13",
            f"Sec-WebSocket-Protocol: {PROTOCOL}",
        ]
    lines += [f"Origin: {origin}"] * (origin is not None) + [f"Cookie: {cookie}"] * (cookie is not None)
    data = b""
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(("\r\n".join(lines) + "\r\n\r\n").encode())
        while b"\r\n\r\n" not in data and (chunk := s.recv(1 << 16)):
            data += chunk
        head, _, body = data.partition(b"\r\n\r\n")
        first, *fields = head.decode("latin-1").split("\r\n")
        headers = {k.strip().lower(): v.strip() for k, _, v in (f.partition(":") for f in fields)}
        while len(body) < min(4096, int(headers.get("content-length", 0))) and (chunk := s.recv(1 << 16)):
            body += chunk
    return int(first.split()[1]), headers, body


def token_query(v) -> str:
    return "/?" + v.url.partition("?")[2]


def test_foreign_origin_is_refused_before_any_message(viewer):
    port, q = viewer.port, token_query(viewer)
    for origin in ("http://evil.example.com", f"http://127.0.0.1:{port + 1}", "null"):
        status, _, body = request(port, f"127.0.0.1:{port}", origin=origin, path=q)
        assert status == 403 and body.startswith(b"nerfpipe view: refused: Origin"), (origin, status, body[:200])
    with pytest.raises(InvalidStatus) as refused:  # a websocket library, as a page's script would
        connect(f"ws://127.0.0.1:{port}{q}", origin="http://evil.example.com", subprotocols=[PROTOCOL])
    assert refused.value.response.status_code == 403
    assert viewer.server.get_clients() == {}


def test_foreign_host_is_refused(viewer):
    """DNS rebinding: a page of evil.example.com re-pointed at 127.0.0.1 is same-origin with itself, so its
    Origin matches its Host: the Host names another machine and is refused (websocket and page alike)."""
    port, q = viewer.port, token_query(viewer)
    assert request(port, "evil", origin="http://evil.example.com", path=q)[0] == 403
    for host in ("evil", f"evil.example.com:{port}"):
        status, _, body = request(port, host, origin=f"http://{host}", path=q)
        assert status == 403 and b"does not name this machine" in body, (host, body[:200])
        assert request(port, host, path=q, upgrade=False)[0] == 403
    assert viewer.server.get_clients() == {}


def test_own_page_gets_in_with_its_token(viewer):
    """The page at the printed URL loads (200) and sets the token's cookie; its websocket (no query, as viser's
    page opens it) gets in with that cookie, from 127.0.0.1, localhost or an SSH tunnel's port."""
    port, q = viewer.port, token_query(viewer)
    status, headers, _ = request(port, f"127.0.0.1:{port}", path=q, upgrade=False)
    assert status == 200 and "HttpOnly" in headers["set-cookie"] and "SameSite=Strict" in headers["set-cookie"]
    cookie = headers["set-cookie"].split(";")[0]
    for host in (f"127.0.0.1:{port}", f"localhost:{port}", "localhost:9999", f"[::1]:{port}"):
        assert request(port, host, origin=f"http://{host}", cookie=cookie)[0] == 101, host
    with connect(
        f"ws://localhost:{port}{q}", origin=f"http://localhost:{port}", subprotocols=[PROTOCOL], max_size=None
    ) as ws:
        assert "Save path" in ViewerPage(ws).gui


@pytest.mark.parametrize("host", ["127.0.0.1", "0.0.0.0"])
def test_every_request_needs_the_token(scene_dir, host, capsys):
    """Without the URL's token (or its cookie) nothing gets in, on a loopback or an open bind: not the page, not
    the websocket, not a wrong or a stale token."""
    v = view.serve(view.Config(target=scene_dir, host=host, port=0))
    try:
        port, q = v.port, token_query(v)
        assert "?token=" in v.url and len(v.gate.token) >= 32
        own = dict(host=f"127.0.0.1:{port}", origin=f"http://127.0.0.1:{port}")
        for path, cookie in (
            ("/", None),
            ("/?token=wrong", None),
            ("/", f"{v.gate.cookie}=wrong"),
            (q.replace("token=", "token=x"), None),
        ):
            assert request(port, **own, path=path, cookie=cookie)[0] == 403, (path, cookie)
            assert request(port, own["host"], path=path, cookie=cookie, upgrade=False)[0] == 403, (path, cookie)
        assert request(port, **own, path=q)[0] == 101
        assert request(port, own["host"], path=q, upgrade=False)[0] == 200
    finally:
        v.stop()
    assert "warning: view: refused a request from 127.0.0.1: no valid token" in capsys.readouterr().err


def test_the_gate_sits_in_visers_server_call():
    """viser starts its websockets server inside `gated`: when it no longer does (viser changed), the viewer
    refuses to start rather than serve unguarded; the patched name is restored either way."""
    import websockets.asyncio.server as ws_server

    original = ws_server.serve
    with pytest.raises(RuntimeError, match="access check"), gated(Gate(bind_host="127.0.0.1", port=1)):
        pass
    assert ws_server.serve is original


def test_recorder_writes_only_new_json_under_paths_dir(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "manifest.json").write_text("{}")
    rec = PathRecorder(paths_dir=run / "camera_paths")
    rec.add_browser_camera((1, 0, 0, 0), (3, 0, 0), 0.7, 4 / 3)
    rec.add_browser_camera((1, 0, 0, 0), (4, 0, 0), 0.7, 4 / 3)
    kw = dict(seconds=1.0, fps=2.0, height=8)
    for bad in (
        "../x.json",
        "../manifest.json",
        "a/b.json",
        "/tmp/x.json",
        ".hidden.json",
        "..json",
        "x y.json",
        "",
        "a\\b.json",
    ):
        with pytest.raises(UserError, match="camera path name"):
            rec.save(bad, **kw)
    assert rec.save("manifest.json", **kw) == run / "camera_paths" / "manifest.json"
    assert (run / "manifest.json").read_text() == "{}"  # the run's own file: outside paths_dir
    assert rec.save("orbit", **kw).name == "orbit.json"
    before = (run / "camera_paths" / "orbit.json").read_bytes()
    with pytest.raises(UserError, match="already exists"):
        rec.save("orbit.json", **kw)
    (run / "camera_paths" / "link.json").symlink_to(run / "manifest.json")
    with pytest.raises(UserError, match="already exists"):
        rec.save("link.json", **kw)
    assert (run / "camera_paths" / "orbit.json").read_bytes() == before
    assert (run / "manifest.json").read_text() == "{}"
    files = sorted(p.relative_to(run).as_posix() for p in run.rglob("*") if not p.is_dir())
    assert files == ["camera_paths/link.json", "camera_paths/manifest.json", "camera_paths/orbit.json", "manifest.json"]


class ViewerPage:
    """viser's websocket protocol, spoken as its page does: the GUI's controls by label, camera updates, control
    updates (a button's click is an update of its value) and the notifications shown."""

    def __init__(self, ws) -> None:
        self.ws, self.gui, self.photos = ws, {}, 0
        deadline = time.monotonic() + 20
        while "Save path" not in self.gui and time.monotonic() < deadline:
            self.receive()

    def receive(self) -> list[dict]:
        raw = self.ws.recv(timeout=20)
        size = int.from_bytes(raw[8:16], "little")
        messages = msgspec.msgpack.decode(zstandard.ZstdDecompressor().decompress(raw[16 : 16 + size]))["messages"]
        for m in messages:
            props = m.get("props") if isinstance(m.get("props"), dict) else {}
            if "label" in props:
                self.gui[props["label"]] = m["uuid"]
            self.photos += m["type"] == "CameraFrustumMessage" and props.get("_image_data") is not None
        return messages

    def send(self, **message) -> None:
        self.ws.send(msgspec.msgpack.encode(message))

    def set(self, label: str, value) -> None:
        self.send(type="GuiUpdateMessage", uuid=self.gui[label], updates={"value": value})

    def camera(self, position) -> None:
        self.send(
            type="ViewerCameraMessage",
            wxyz=[1.0, 0, 0, 0],
            position=list(position),
            fov=0.7,
            near=0.01,
            far=100.0,
            image_height=48,
            image_width=64,
            look_at=[0.0, 0, 0],
            up_direction=[0, 0, 1],
        )

    def notification(self) -> dict:
        """The next notification's props (title, body)."""
        while not (shown := [m for m in self.receive() if m["type"] == "NotificationShowMessage"]):
            pass
        return shown[0]["props"]


def test_recorder_over_the_websocket_stays_in_paths_dir(viewer, scene_dir):
    """The issue's attack, by an admitted client: keyframes, then "Save path" as ../scene/transforms.json
    (refused, nothing written), as transforms.json (saved in scene/camera_paths/), and, after one more keyframe,
    that name again (refused: the first file stays). The scene's transforms.json is the same bytes throughout."""
    transforms = (scene_dir / "transforms.json").read_bytes()
    port, q = viewer.port, token_query(viewer)
    with connect(
        f"ws://127.0.0.1:{port}{q}", origin=f"http://127.0.0.1:{port}", subprotocols=[PROTOCOL], max_size=None
    ) as ws:
        page = ViewerPage(ws)
        assert page.photos == 4  # an admitted page sees the photos: hence the gate

        def add_keyframe(x: float) -> None:
            n = len(viewer.recorder.keyframes)
            page.camera((x, 0.0, 0.0))
            page.set("Add keyframe (this view)", True)
            deadline = time.monotonic() + 10
            while len(viewer.recorder.keyframes) == n and time.monotonic() < deadline:
                time.sleep(0.02)

        def save_as(name: str) -> dict:
            page.set("File", name)
            page.set("Save path", True)
            return page.notification()

        add_keyframe(3.0)
        add_keyframe(3.5)
        shown = save_as("../scene/transforms.json")
        assert shown["title"] == "Not saved" and "no folder" in shown["body"], shown
        assert not (scene_dir / "camera_paths").exists()
        assert save_as("transforms.json")["title"] == "Camera path saved"
        saved = scene_dir / "camera_paths" / "transforms.json"
        first = saved.read_bytes()
        add_keyframe(4.0)
        shown = save_as("transforms.json")
        assert shown["title"] == "Not saved" and "already exists" in shown["body"], shown
    assert (scene_dir / "transforms.json").read_bytes() == transforms
    assert saved.read_bytes() == first
    doc = json.loads(first)
    assert doc["format"] == "nerfpipe-camera-path"
    assert np.allclose([k["world_from_cam"][0][3] for k in doc["keyframes"]], [3.0, 3.5])
    assert sorted(p.name for p in (scene_dir / "camera_paths").iterdir()) == ["transforms.json"]
