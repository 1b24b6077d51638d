"""``clflow view``: a local web viewer (viser) of a 3DGS PLY file or of a simulation folder.

Everything is shown in the splat file's own units and axes ("scene units", the frame of
``object.select`` in a scene config), with the file's up axis up. A simulation folder
(``gaussians.npz`` of ``clflow simulate CONFIG``, simulation frame) is taken back to that
frame through its ``scale`` and ``up_rotation``: ``x_file = up_rotation^T x_sim / scale``.

The viewer has a frame slider and a play button (simulation folders), the guidance camera as
a frustum that browsers open behind (simulation folders), and a box (two corner gizmos and
min / max fields) whose bounds it prints as the ``object.select.box`` YAML of a scene config. Colours are the SH
degree-0 colours (``sh0_to_rgb``, clamped to [0, 1]): viser draws no view-dependent colour.
Only the viewer's own page reads it: requests need its Host, its Origin and the token of the
address it prints (:class:`Access`), so other web pages in the browser cannot.

viser is the optional extra ``clflow[view]``; it is imported only when a viewer starts.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import http
import http.cookies
import io
import math
import secrets
import socket
import threading
import time
import urllib.parse
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from clflow.errors import ClflowError, InputError

if TYPE_CHECKING:
    from clflow.splat.cameras import Camera

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8080
PLY_BOX_QUANTILE = 0.01  # a PLY's first box ignores this fraction of outlying centres per side
LOOPBACK_NAMES = ("127.0.0.1", "localhost", "[::1]")  # as they stand in a Host header


@dataclass
class ViewScene:
    """What the viewer shows, in scene units (the splat file's frame).

    means [T, n, 3] and covariances [T, n, 3, 3] (units^2): the Gaussians that move, per
    frame (a PLY: all of them, T = 1); static_means [S, 3], static_covariances [S, 3, 3]:
    those that do not; rgbs [n + S, 3] in [0, 1] and opacities [n + S] in [0, 1], moving
    ones first; fps (frames/s, None for one frame); camera: the guidance camera
    (:class:`clflow.splat.cameras.Camera`) or None; up [3]: the file's up direction;
    box: (low [3], high [3]), the box the viewer starts with; source: the file or folder shown.
    """

    means: np.ndarray
    covariances: np.ndarray
    static_means: np.ndarray
    static_covariances: np.ndarray
    rgbs: np.ndarray
    opacities: np.ndarray
    fps: float | None
    camera: Camera | None
    up: tuple[float, float, float]
    box: tuple[np.ndarray, np.ndarray]
    source: str

    @property
    def frame_count(self) -> int:
        return int(self.means.shape[0])

    @functools.cached_property
    def rest_means(self) -> np.ndarray:
        """[n + S, 3] every Gaussian's centre at frame 0 (what ``object.select`` picks from),
        computed once (the box widget counts them on every drag)."""
        return np.concatenate([self.means[0], self.static_means])

    def extent(self) -> float:
        """Diagonal of the centres' bounding box at frame 0 (scene units, > 0)."""
        means = self.rest_means
        return max(float(np.linalg.norm(means.max(0) - means.min(0))), 1e-6)


def load_scene(path: str | Path, up: str = "+y") -> ViewScene:
    """A :class:`ViewScene` of a 3DGS PLY file (``up``: its up axis) or of a simulation
    folder: one holding ``gaussians.npz``, or a results folder with ``simulation/`` in it, or a
    ``render4d`` folder inside a simulation folder."""
    path = Path(path)
    if path.is_dir():
        for folder in (path, path / "simulation", path.parent):
            if (folder / "gaussians.npz").is_file():
                return _simulation_scene(folder)
        raise InputError(
            f"{path}: no gaussians.npz here, in {path / 'simulation'} or in {path.parent}: "
            "give a PLY file or a folder written by `clflow simulate CONFIG`"
        )
    if not path.is_file():
        raise InputError(f"{path}: no such file or folder")
    from clflow.scene.config import UP_AXES
    from clflow.scene.load import up_rotation

    if up not in UP_AXES:
        raise InputError(f"up axis must be one of {', '.join(UP_AXES)}, got {up!r}")
    return _ply_scene(path, tuple(float(v) for v in up_rotation(up)[1]))  # R_up^T e_y: the file axis that is up


def _ply_scene(path: Path, up: tuple[float, float, float]) -> ViewScene:
    from clflow.splat.ply import load_ply, require_gaussians

    g = require_gaussians(load_ply(path), path)
    low, high = g.bounds(PLY_BOX_QUANTILE)
    f32 = lambda t: t.detach().float().numpy()  # noqa: E731
    return ViewScene(
        means=f32(g.means)[None],
        covariances=f32(g.covariances)[None],
        static_means=np.zeros((0, 3), np.float32),
        static_covariances=np.zeros((0, 3, 3), np.float32),
        rgbs=_rgb(g.sh, g.colors, str(path)),
        opacities=f32(g.opacities),
        fps=None,
        camera=None,
        up=up,
        box=(low.numpy(), high.numpy()),
        source=str(path),
    )


def _simulation_scene(folder: Path) -> ViewScene:
    import torch

    from clflow.pipeline.frames4d import load_frames
    from clflow.scene.load import to_file_camera, to_file_frame

    frames = load_frames(folder)
    a = frames.arrays
    if "scale" not in a or "up_rotation" not in a:
        raise InputError(f"{folder / 'gaussians.npz'}: no scale and up_rotation (written by an older clflow simulate?)")
    R_up, scale = np.asarray(a["up_rotation"], np.float64), float(a["scale"])
    f32 = lambda *arrays: (x.astype(np.float32) for x in arrays)  # noqa: E731
    means, covariances = f32(
        *to_file_frame(a["object_means"].astype(np.float64), a["object_covariances"].astype(np.float64), R_up, scale)
    )
    static_means, static_covariances = f32(
        *to_file_frame(a["static_means"].astype(np.float64), a["static_covariances"].astype(np.float64), R_up, scale)
    )
    sh, colors = a.get("sh"), a.get("colors")
    return ViewScene(
        means=means,
        covariances=covariances,
        static_means=static_means,
        static_covariances=static_covariances,
        rgbs=_rgb(
            None if sh is None else torch.from_numpy(sh),
            None if colors is None else torch.from_numpy(colors),
            str(folder),
        ),
        opacities=np.asarray(a["opacities"], np.float32),
        fps=frames.fps,
        camera=to_file_camera(frames.guidance_camera(), torch.from_numpy(R_up), scale),
        up=tuple(float(v) for v in R_up[1]),  # R_up^T e_y: the file axis that is up
        box=(means[0].min(0), means[0].max(0)),
        source=str(folder),
    )


def _rgb(sh, colors, where: str) -> np.ndarray:
    """[N, 3] colours in [0, 1]: the SH degree-0 colour (the rasteriser's convention, before its
    view-dependent terms), or 3-channel ``colors`` as they are."""
    from clflow.splat.sh import sh0_to_rgb

    if sh is not None:
        rgb = sh0_to_rgb(sh[:, 0, :]).numpy()
    elif colors.shape[1] == 3:
        rgb = colors.numpy()
    else:
        raise InputError(f"{where}: {colors.shape[1]} colour channels; the viewer shows RGB")
    return np.clip(rgb, 0.0, 1.0).astype(np.float32)


# -- the box --------------------------------------------------------------------------------


def box_decimals(extent: float) -> int:
    """Decimals that resolve 1/1000 of ``extent`` (scene units)."""
    return max(0, 3 - math.floor(math.log10(extent)))


def rounded_box(low, high, decimals: int) -> tuple[np.ndarray, np.ndarray]:
    """The box rounded outwards to ``decimals`` places (so it holds at least what it held),
    corners sorted per axis."""
    low, high = np.minimum(low, high), np.maximum(low, high)
    step = 10.0**-decimals
    low = np.round(np.floor(np.asarray(low, np.float64) / step) * step, decimals)
    high = np.round(np.ceil(np.asarray(high, np.float64) / step) * step, decimals)
    return low, np.where(high > low, high, low + step)  # min < max on every axis, as the config demands


def box_yaml(low, high) -> str:
    """The ``object.select.box`` entry of a scene config (scene units)."""
    text = lambda v: "[" + ", ".join(np.format_float_positional(float(x), trim="-") for x in v) + "]"  # noqa: E731
    return f"object:\n  select:\n    box:\n      min: {text(low)}\n      max: {text(high)}"


def count_inside(means: np.ndarray, low, high) -> int:
    """Centres [N, 3] inside the box, bounds inclusive (as ``object.select.box`` picks them)."""
    return int(((means >= low) & (means <= high)).all(axis=1).sum())


# -- the server -----------------------------------------------------------------------------


def import_viser():
    """The viser module, or one line saying which extra installs it."""
    try:
        import viser
    except ImportError:
        raise ClflowError("clflow view needs the optional extra 'view': pip install 'clflow[view]'") from None
    return viser


def check_port(host: str, port: int) -> None:
    """Refuse, with one line, a ``host:port`` that cannot be served (in use, not this machine's,
    unknown host) before the viewer starts (viser itself would quietly take the next port)."""
    try:
        addresses = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as exc:
        raise InputError(f"--host {host}: cannot resolve it ({exc.strerror})") from None
    for family, kind, proto, _, address in addresses:
        with socket.socket(family, kind, proto) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server binds
            try:
                probe.bind(address)
            except OSError as exc:
                if exc.errno == errno.EADDRINUSE:
                    raise _port_in_use(host, port) from None
                raise InputError(f"port {port} on {host} cannot be bound ({exc.strerror})") from None


def _port_in_use(host: str, port: int) -> InputError:
    return InputError(
        f"port {port} on {host} is in use (by another program or another clflow view); pick another with --port"
    )


def _url_host(host: str) -> str:
    """``host`` as it stands in a URL or a Host header (an IPv6 address in brackets)."""
    return f"[{host}]" if ":" in host else host


class Access:
    """Who may read the viewer, checked on each HTTP request and WebSocket handshake; any other
    gets 403. Its Host must be the viewer's own (a loopback name, ``host`` or the address the
    request came in on, with the port): a DNS-rebinding page sends its own name. Its Origin,
    if sent, must be ``http://`` one of those: another page's WebSocket sends that page's. And
    it must carry ``token``, as ``?token=`` or as the cookie every page served sets (viser's
    client opens its WebSocket without the page's query string; the browser adds the cookie)."""

    def __init__(self, host: str, token: str):
        self.token = token.encode()
        self.names = {*LOOPBACK_NAMES, _url_host(host)} - {"0.0.0.0", "[::]", ""}

    def hosts(self, connection) -> set[str]:
        """The Host headers accepted on ``connection`` (a websockets ``ServerConnection``)."""
        address, port = connection.local_address[:2]
        names = self.names | {_url_host(address)}
        return {f"{name}:{port}" for name in names} | (names if port == 80 else set())

    def cookie(self, connection) -> str:
        """The cookie's name: one per port, as browsers send a host's cookies to all its ports."""
        return f"clflow-view-{connection.local_address[1]}"

    def refusal(self, connection, request) -> str | None:
        """Why ``request`` (a websockets ``Request``) is refused, or None."""
        hosts = self.hosts(connection)
        host, origin = request.headers.get_all("Host"), request.headers.get_all("Origin")
        if len(host) != 1 or host[0].lower() not in hosts:
            return "this viewer answers to its own address only"
        if origin and (len(origin) != 1 or origin[0].lower() not in {f"http://{h}" for h in hosts}):
            return "this viewer answers to its own page only"
        tokens = urllib.parse.parse_qs(urllib.parse.urlsplit(request.path).query).get("token", [])
        cookies = http.cookies.SimpleCookie()
        with contextlib.suppress(http.cookies.CookieError):
            cookies.load("; ".join(request.headers.get_all("Cookie")))
        if self.cookie(connection) in cookies:
            tokens.append(cookies[self.cookie(connection)].value)
        if not any(secrets.compare_digest(t.encode(), self.token) for t in tokens):
            return "no token or a wrong one: open the address clflow view printed"
        return None

    def guard(self, serve_files):
        """A websockets ``process_request``: 403 for what :meth:`refusal` refuses, else
        ``serve_files`` (viser's: a file, or None to go on with a WebSocket handshake), the
        files with the token's cookie."""

        def process_request(connection, request):
            reason = self.refusal(connection, request)
            if reason is not None:
                return connection.respond(http.HTTPStatus.FORBIDDEN, f"{reason}\n")
            response = serve_files(connection, request)
            if response is not None:
                response.headers["Set-Cookie"] = (
                    f"{self.cookie(connection)}={self.token.decode()}; Path=/; HttpOnly; SameSite=Strict"
                )
            return response

        return process_request


_serve_lock = threading.Lock()


@contextlib.contextmanager
def _guarded_serve(access: Access):
    """While viser starts its server: websockets' ``serve`` with viser's ``process_request``
    (its file server, which sees every HTTP request and WebSocket handshake) behind
    ``access.guard``. viser 1.1 has no hook of its own for this. Yields a list that gets an
    entry each time viser serves through it: empty, viser serves some other way unguarded."""
    import websockets.asyncio.server as ws

    serve, used = ws.serve, []

    def guarded(*args, process_request, **kwargs):
        used.append(True)
        return serve(*args, process_request=access.guard(process_request), **kwargs)

    with _serve_lock:
        ws.serve = guarded
        try:
            yield used
        finally:
            ws.serve = serve


class Viewer:
    """A running viser server showing ``scene``; ``report(text)`` gets the box YAML each time
    the box is set (a field edited, a gizmo let go). ``port`` 0: any free port (``self.port``).
    Only requests that :class:`Access` lets through with this run's ``token`` are answered."""

    def __init__(
        self,
        scene: ViewScene,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        report: Callable[[str], None] = print,
    ):
        viser = import_viser()
        check_port(host, port)
        self.scene, self.report, self._closed = scene, report, False
        self._lock = threading.RLock()
        self.token = secrets.token_urlsafe(32)
        with _guarded_serve(Access(host, self.token)) as guarded, contextlib.redirect_stdout(io.StringIO()):
            self.server = viser.ViserServer(host=host, port=port, verbose=False)  # its banner: the caller says where
        if not guarded:  # a viser that no longer serves through websockets' serve(): fail closed
            self.close()
            raise ClflowError(
                f"viser {viser.__version__} serves in a way clflow view cannot check who connects; "
                "install the viser that clflow[view] names: pip install 'clflow[view]'"
            )
        self.port = self.server.get_port()
        if port and self.port != port:  # taken between the check and the bind
            self.close()
            raise _port_in_use(host, port)
        self.server.gui.configure_theme(control_width="large")
        self.server.scene.set_up_direction(scene.up)
        self._add_splats()
        self._set_initial_camera()
        self._add_camera()
        self._add_frame_controls()
        self._add_box()

    # scene nodes
    def _add_splats(self) -> None:
        s, n = self.scene, self.scene.means.shape[1]
        self.frame_shown = 0
        self.splats = self.server.scene.add_gaussian_splats(
            "/gaussians", s.means[0], s.covariances[0], s.rgbs[:n], s.opacities[:n, None]
        )
        self.static_splats = None
        if len(s.static_means):
            self.static_splats = self.server.scene.add_gaussian_splats(
                "/static", s.static_means, s.static_covariances, s.rgbs[n:], s.opacities[n:, None]
            )

    def _add_camera(self) -> None:
        self.frustum = None
        cam = self.scene.camera
        if cam is None:
            return
        from clflow.splat.geometry import rotmat_to_quat

        c2w = cam.camtoworld()
        self.frustum = self.server.scene.add_camera_frustum(
            "/guidance_camera",
            fov=cam.fov_y,
            aspect=cam.width / cam.height,
            scale=0.1 * self.scene.extent(),
            thickness=2.0,
            thickness_units="screen",
            color=(230, 120, 20),
            wxyz=rotmat_to_quat(c2w[None, :3, :3])[0].numpy(),
            position=c2w[:3, 3].numpy(),
        )

    def _set_initial_camera(self) -> None:
        """Browsers open behind the guidance camera (its frustum in view), looking where it looks,
        else looking down at the box from a diagonal."""
        low, high = self.scene.box
        center, up = (low + high) / 2, np.asarray(self.scene.up, np.float64)
        cam, initial = self.scene.camera, self.server.initial_camera
        if cam is not None:
            eye = cam.position.numpy()
            target = eye + cam.forward.numpy() * np.linalg.norm(center - eye)
            initial.position, initial.look_at, initial.fov = target + 1.6 * (eye - target), target, cam.fov_y
        else:
            side = next(a for a in np.eye(3) if abs(a @ up) < 0.5)  # a horizontal axis
            direction = 0.6 * up + side + np.cross(up, side)
            size = max(float(np.linalg.norm(high - low)), 1e-6)
            initial.position = center + 1.2 * size * direction / np.linalg.norm(direction)
            initial.look_at = center
        initial.up = up

    def _add_frame_controls(self) -> None:
        """A frame slider and a play / pause button, for more than one frame."""
        self.frame_slider = self.play_button = None
        self.playing = False
        count = self.scene.frame_count
        if count == 1:
            return
        gui = self.server.gui
        self.frame_slider = gui.add_slider("frame", min=0, max=count - 1, step=1, initial_value=0)
        self.play_button = gui.add_button("play")
        self.frame_slider.on_update(lambda _: self.show_frame(int(self.frame_slider.value)))
        self.play_button.on_click(lambda _: self._toggle_play())

    def _toggle_play(self) -> None:
        self.playing = not self.playing
        self.play_button.label = "pause" if self.playing else "play"

    def show_frame(self, t: int) -> None:
        """Move the moving Gaussians to frame t."""
        s, n = self.scene, self.scene.means.shape[1]
        t = min(max(int(t), 0), s.frame_count - 1)
        with self._lock:
            self.splats.set_gaussians(s.means[t], s.covariances[t], s.rgbs[:n], s.opacities[:n, None])
            self.frame_shown = t

    def tick(self) -> None:
        """One step of playback: the next frame (wrapping) when play is on."""
        if self.playing:
            self.frame_slider.value = (int(self.frame_slider.value) + 1) % self.scene.frame_count

    # the box
    def _add_box(self) -> None:
        extent = self.scene.extent()
        self.decimals = box_decimals(extent)
        step = 10.0**-self.decimals
        low, high = rounded_box(*self.scene.box, self.decimals)
        gui, scene = self.server.gui, self.server.scene
        with gui.add_folder("object.select.box (scene units)"):
            self.box_min = gui.add_vector3("min", initial_value=tuple(low), step=step)
            self.box_max = gui.add_vector3("max", initial_value=tuple(high), step=step)
            self.box_text = gui.add_markdown("")
        self.box_node = None
        self.corners = [
            scene.add_transform_controls(
                f"/box/{name}", scale=0.15 * extent, disable_rotations=True, depth_test=False, position=tuple(p)
            )
            for name, p in (("min", low), ("max", high))
        ]
        for corner in self.corners:
            corner.on_update(self._corner_moved)
        for field in (self.box_min, self.box_max):
            field.on_update(lambda _: self._fields_edited())
        self._syncing = False
        self.set_box(low, high, move_corners=False)

    def _corner_moved(self, event) -> None:
        a, b = (np.asarray(c.position, np.float64) for c in self.corners)
        self.set_box(a, b, move_corners=False, report=event.phase == "end")

    def _fields_edited(self) -> None:
        if not self._syncing:
            self.set_box(np.asarray(self.box_min.value), np.asarray(self.box_max.value))

    def set_box(self, low, high, *, move_corners: bool = True, report: bool = True) -> None:
        """Set the box (either corner order), rounded outwards as printed; update the fields,
        the wireframe, the YAML shown, and ``report`` it."""
        with self._lock:
            low, high = rounded_box(low, high, self.decimals)
            self.box = (low, high)
            self._syncing = True
            try:
                self.box_min.value, self.box_max.value = tuple(low), tuple(high)
            finally:
                self._syncing = False
            if move_corners:
                self.corners[0].position, self.corners[1].position = tuple(low), tuple(high)
            self.box_node = self.server.scene.add_box(
                "/box/outline",
                color=(230, 120, 20),
                dimensions=tuple(high - low),
                wireframe=True,
                position=tuple((low + high) / 2),
            )
            means = self.scene.rest_means
            inside = count_inside(means, low, high)
            self.yaml = box_yaml(low, high)
            self.box_text.content = (
                f"{inside:,} of {len(means):,} Gaussians inside (frame 0)\n\n```yaml\n{self.yaml}\n```"
            )
            if report:
                self.report(f"{self.yaml}\n# {inside:,} of {len(means):,} Gaussians inside")

    # life cycle
    def url(self) -> str:
        """The address to open: this viewer's, with its token."""
        host = self.server.get_host()
        host = "127.0.0.1" if host in ("0.0.0.0", "::", "") else host  # a wildcard: this machine
        return f"http://{_url_host(host)}:{self.port}/?token={self.token}"

    def serve_forever(self) -> None:
        """Play until interrupted (Ctrl-C: KeyboardInterrupt), then stop."""
        try:
            while True:
                time.sleep(1.0 / (self.scene.fps or 24.0))
                self.tick()
        finally:
            self.close()

    def close(self) -> None:
        """Stop the server (again: nothing)."""
        if self._closed:
            return
        self._closed = True
        with contextlib.redirect_stdout(io.StringIO()):  # "(viser) Server stopped"
            self.server.stop()


__all__ = [
    "DEFAULT_HOST",
    "DEFAULT_PORT",
    "Access",
    "ViewScene",
    "Viewer",
    "box_yaml",
    "check_port",
    "count_inside",
    "import_viser",
    "load_scene",
    "rounded_box",
]
