"""The viser application: the scene's objects in the browser and the controls around them.

Layout: the browser draws every object of :class:`~omnire_viewer.scene.ViewerScene` as
Gaussian splats (one scene node per non-actor node and per actor, actors placed by their
box pose, the sky as a far shell of splats); the control panel holds the time slider, the
per-node and per-actor toggles, the selected actor's identity and edits (hide, move, turn),
the dataset cameras (click a frustum to look through it), the server render of the
current browser view next to it, and, for a run that learned LiDAR, its rendered sweep at
the slider's moment as a point cloud coloured by intensity or range (omnire_viewer/lidar.py). The scene shown is a simulation (``omnire_sim``): a
scenario file's edits, if the viewer was opened with one, and the panel's hide / move edits,
resolved by :class:`omnire_sim.Simulation` for the browser objects and the server render alike.

Scene updates run on one worker thread that always draws the newest requested state, so
dragging the time slider never queues stale frames.

Clients reach viser only through :class:`~omnire_viewer.gate.Gate` (token, message size and
shape). What a well-formed message may still ask beyond the panel's limits is refused here,
per client, before any work: a frame outside the log, a render width outside
:data:`MIN_RENDER_WIDTH`..:data:`MAX_RENDER_WIDTH`, an offset beyond :data:`MAX_OFFSET_M` or a
turn beyond :data:`MAX_TURN_DEG`, a second server render while one runs. The control goes back
to its last accepted value and the client gets a notification naming the field.
"""
from __future__ import annotations

import contextlib
import errno
import io
import math
import secrets
import socket
import threading
import time
from typing import Optional

import numpy as np

from omnire.api import UserError, rotmat_to_quat
from omnire_viewer.edits import ActorEdit
from omnire_viewer.gate import Gate, is_loopback
from omnire_viewer.lidar import COLOUR_BY, point_colours
from omnire_viewer.scene import ViewerScene, camera_from_view

BOX_COLOUR = (40, 160, 255)
SELECTED_COLOUR = (255, 140, 0)
MIN_RENDER_WIDTH, MAX_RENDER_WIDTH = 160, 1920
"""The server render's width range in pixels (the panel's slider; its height follows the
client's aspect, capped at the same maximum)."""
LIDAR_POINT_SIZE = 0.08
"""Diameter of a drawn LiDAR return (metres, in the scene)."""
MAX_OFFSET_M = 1000.0
"""Largest offset of a moved actor along each world axis (metres)."""
MAX_TURN_DEG = 360.0
"""Largest turn of an actor about its up axis (degrees, either way)."""
WILDCARD_HOSTS = ("0.0.0.0", "::", "")


class ViewerError(UserError):
    """The viewer cannot start (address not usable, nothing to show)."""


class PortInUseError(ViewerError):
    """The port asked for is taken."""


def check_port(host: str, port: int) -> None:
    """Raise :class:`PortInUseError` when ``host:port`` cannot be listened on because
    something else listens there, :class:`ViewerError` for any other reason."""
    if not 0 <= port <= 65535:
        raise ViewerError(f"--port {port}: expected 0..65535")
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as exc:
        raise ViewerError(f"--host {host!r}: cannot resolve ({exc.strerror})") from None
    for family, kind, proto, _, address in infos:
        with socket.socket(family, kind, proto) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server does
            try:
                s.bind(address)
            except OSError as exc:
                raise listen_error(host, port, exc) from None


def listen_error(host: str, port: int, exc: OSError) -> ViewerError:
    """The one-line error for a failed listen on ``host:port``."""
    if exc.errno == errno.EADDRINUSE:
        return PortInUseError(f"{host}:{port} is already in use (another viewer?); choose a free port with --port")
    return ViewerError(f"cannot listen on {host}:{port}: {exc.strerror or exc}")


def look_at_pose(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(position (3,), wxyz (4,)) of an OpenCV camera-to-world matrix (4, 4)."""
    return np.asarray(c2w[:3, 3], np.float64), np.asarray(rotmat_to_quat(np.asarray(c2w[:3, :3], np.float64)))


class Viewer:
    """A viser server showing ``scene``.

    Args:
        scene: what to show.
        host, port: where to listen (port 0: any free port; see :attr:`port`).
        title: shown at the top of the panel.
        frame: the initial moment.
        verbose: let viser log its connections (its address banner, which names its internal port, is never shown).
        token: asked of every client (see :mod:`omnire_viewer.gate`); None: none on a loopback
            address, a new random one on any other (:attr:`token`, part of :attr:`url`).
    """

    def __init__(self, scene: ViewerScene, host: str = "127.0.0.1", port: int = 8080, title: str = "omnire",
                 frame: float = 0.0, verbose: bool = True, token: Optional[str] = None) -> None:
        import viser

        check_port(host, port)
        if token is not None and not token.strip():
            raise ViewerError("the viewer token is empty: give a non-empty --token (or OMNIRE_VIEW_TOKEN)")
        if token is None and not is_loopback(host):
            token = secrets.token_urlsafe(18)  # reachable from other machines: never without a token
        self.scene = scene
        self.token = token
        with contextlib.redirect_stdout(io.StringIO()):  # viser's banner names its internal port, not ours
            self.server = viser.ViserServer(host="127.0.0.1", port=0, verbose=verbose)  # reached through the gate
        try:
            self.gate = Gate(host, port, self.server.get_port(), token, log=self._log)
        except OSError as exc:  # taken between check_port and here
            self.server.stop()
            raise listen_error(host, port, exc) from None
        self.host, self.port = host, self.gate.port
        self.refusals: list[str] = []
        self._render_lock = threading.Lock()
        self.server.scene.set_up_direction("+z")
        self._handles: dict[str, tuple[object, int]] = {}
        self._boxes: dict[str, object] = {}
        self._frusta: dict[str, object] = {}
        self._sky_handle = None
        self._lidar_handle = None
        self._lidar_colour = COLOUR_BY[0]
        self._lidar_key: Optional[tuple] = None  # what the drawn sweep was rendered for
        self._lidar_sweep: Optional[tuple[np.ndarray, np.ndarray]] = None
        self._lidar_drawn_colour: Optional[str] = None
        self._lidar_seconds = 0.0
        self.selected: Optional[str] = None
        self._stop = threading.Event()
        self._dirty = threading.Event()
        self._idle = threading.Event()
        self._sync_lock = threading.Lock()
        self._select_lock = threading.RLock()
        self._build_gui(title, frame)
        self._set_initial_camera(frame)
        self.refresh()
        self._worker = threading.Thread(target=self._update_loop, name="omnire-viewer-updates", daemon=True)
        self._worker.start()
        self._player = threading.Thread(target=self._play_loop, name="omnire-viewer-play", daemon=True)
        self._player.start()

    # ------------------------------------------------------------------ properties
    @property
    def url(self) -> str:
        """Where to open the viewer: the address listened on (this machine's name for a
        wildcard address), with the token when one is asked."""
        host = socket.gethostname() if self.host in WILDCARD_HOSTS else self.host
        host = f"[{host}]" if ":" in host else host
        return f"http://{host}:{self.port}/" + (f"?token={self.token}" if self.token else "")

    @property
    def frame(self) -> float:
        """The time slider's frame (its last accepted value while a refused one is undone)."""
        value = float(self.gui_frame.value)
        return value if self._frame_error(value) is None else self._good_frame

    def _frame_error(self, value: float) -> Optional[str]:
        last = self.scene.num_frames - 1
        if not (math.isfinite(value) and 0.0 <= value <= last):
            return f"Frame {value}: expected 0..{last}"
        return None

    # ------------------------------------------------------------------ refusals
    def _log(self, line: str) -> None:
        print(f"omnire view: {line}", flush=True)

    def refuse(self, client, handle, good, reason: str) -> None:
        """Undo a refused value of ``handle`` (back to ``good``; None: leave it) and tell
        ``client`` (None: nobody connected) why."""
        self.refusals.append(reason)
        self._log(f"refused: {reason}")
        if handle is not None and good is not None:
            handle.value = good
        if client is not None:
            client.add_notification("Refused", reason, color="red", auto_close_seconds=10.0)

    def hidden_nodes(self) -> frozenset[str]:
        return frozenset(n for n, box in self.gui_nodes.items() if not box.value)

    # ------------------------------------------------------------------ GUI
    def _build_gui(self, title: str, frame: float) -> None:
        gui, sc = self.server.gui, self.scene
        gui.configure_theme(show_share_button=False, control_width="medium")
        self.gui_info = gui.add_markdown(self._info_text(title))
        self._title = title
        F = sc.num_frames
        with gui.add_folder("Time"):
            self.gui_frame = gui.add_slider("Frame", min=0.0, max=float(max(F - 1, 1)), step=0.1,
                                            initial_value=float(min(max(frame, 0), F - 1)), disabled=F < 2)
            self._good_frame = float(self.gui_frame.value)
            self.gui_seconds = gui.add_markdown("")
            self.gui_play = gui.add_checkbox("Play", False, hint="Advance one frame every 0.25 s")
        with gui.add_folder("Show"):
            self.gui_nodes = {}
            for name, kind in sc.node_kinds.items():
                label = f"{name} ({kind})"
                self.gui_nodes[name] = gui.add_checkbox(label, True)
            self.gui_boxes = gui.add_checkbox("Actor boxes", True)
            self.gui_cameras = gui.add_checkbox("Dataset cameras", True,
                                                hint="Frusta of the recorded cameras; click one to look through it")
        with gui.add_folder("Actors"):
            options = ["(none)"] + sorted(sc.actors)
            self.gui_actor = gui.add_dropdown("Selected", options, initial_value="(none)",
                                              hint="Or click an actor's box in the scene")
            self.gui_actor_info = gui.add_markdown("Click an actor's box, or choose one above.")
            self.gui_actor_visible = gui.add_checkbox("Visible", True, disabled=True)
            self.gui_actor_offset = gui.add_vector3("Offset (m)", (0.0, 0.0, 0.0), step=0.1, disabled=True)
            self.gui_actor_yaw = gui.add_number("Turn (deg)", 0.0, step=1.0, disabled=True,
                                                hint="About the box's up axis through its centre")
            self.gui_actor_reset = gui.add_button("Reset edits of all actors")
            self.gui_actor_toggles = {}
            with gui.add_folder("Visibility per actor", expand_by_default=False):
                for tid in sorted(sc.actors):
                    self.gui_actor_toggles[tid] = gui.add_checkbox(tid, True)
        with gui.add_folder("Server render"):
            self.gui_render_button = gui.add_button("Render this view on the server",
                                                    hint="The real rasterizer: SH and sky included")
            self.gui_render_width = gui.add_slider("Width (px)", min=MIN_RENDER_WIDTH, max=MAX_RENDER_WIDTH, step=16,
                                                   initial_value=640)
            self.gui_render_note = gui.add_markdown("")
            self.gui_render_image = gui.add_image(np.zeros((9, 16, 3), np.uint8), label="server render",
                                                  visible=False)
            self.gui_recolour = gui.add_button("Recolour splats for this view",
                                               hint="Evaluate the view-dependent (SH) colours from here")
        with gui.add_folder("LiDAR"):
            can = sc.renders_lidar
            self.gui_lidar = gui.add_checkbox(
                "Rendered sweep", False, disabled=not can,
                hint="The LiDAR the run learned, rendered at this moment with the edits: one point per return")
            self.gui_lidar_colour = gui.add_dropdown("Colour by", COLOUR_BY, initial_value=COLOUR_BY[0],
                                                     disabled=not can)
            self.gui_lidar_note = gui.add_markdown(
                "" if can else "This run learned no LiDAR (train it with `--method.lidar.enabled`).")

        def redraw(_event=None) -> None:
            self._dirty.set()

        def frame_changed(event) -> None:
            value = float(self.gui_frame.value)
            error = self._frame_error(value)
            if error is not None:
                self.refuse(event.client, self.gui_frame, self._good_frame, error)
                return
            self._good_frame = value
            self._dirty.set()

        self.gui_frame.on_update(frame_changed)
        for box in self.gui_nodes.values():
            box.on_update(redraw)
        self.gui_boxes.on_update(redraw)
        self.gui_cameras.on_update(redraw)
        self.gui_actor.on_update(self._actor_chosen)
        self.gui_actor_visible.on_update(lambda e: self._edit_selected(e.client))
        self.gui_actor_offset.on_update(lambda e: self._edit_selected(e.client))
        self.gui_actor_yaw.on_update(lambda e: self._edit_selected(e.client))
        self.gui_actor_reset.on_click(lambda _e: self.reset_edits())
        for tid, box in self.gui_actor_toggles.items():
            box.on_update(lambda _e, tid=tid: self.set_hidden(tid, not self.gui_actor_toggles[tid].value))
        self.gui_lidar.on_update(self._lidar_toggled)
        self.gui_lidar_colour.on_update(self._lidar_colour_chosen)
        self.gui_render_button.on_click(lambda event: self.render_for_client(event.client))
        self.gui_recolour.on_click(lambda event: self.recolour(event.client))

        @self.server.scene.on_click()
        def _(event) -> None:
            tid = self.scene.pick(event.ray_origin, event.ray_direction, self.frame)
            if tid is not None:
                self.select(tid)

    def _lidar_toggled(self, event) -> None:
        if self.gui_lidar.value and not self.scene.renders_lidar:  # a disabled box set anyway
            self.refuse(event.client, self.gui_lidar, False, "Rendered sweep: this run learned no LiDAR")
            return
        self._dirty.set()

    def _lidar_colour_chosen(self, event) -> None:
        value = self.gui_lidar_colour.value
        if value not in COLOUR_BY:
            self.refuse(event.client, self.gui_lidar_colour, self._lidar_colour,
                        f"Colour by {str(value)[:40]!r}: expected one of {', '.join(COLOUR_BY)}")
            return
        self._lidar_colour = value
        self._dirty.set()

    def _info_text(self, title: str, extra: str = "") -> str:
        sc = self.scene
        text = (f"**{title}**  \n{sc.scene.name}: {sc.num_frames} frames, {len(sc.scene.cameras)} cameras, "
                f"{sc.recon.num_gaussians():,} Gaussians, step {sc.recon.step}")
        if sc.base.actors or sc.base.inserts:
            text += (f"  \nscenario {sc.base.source}: {len(sc.base.actors)} actor edit(s), "
                     f"{len(sc.base.inserts)} inserted actor(s)")
        return text + (f"  \n{extra}" if extra else "")

    def _set_initial_camera(self, frame: float) -> None:
        _name, c2w, K, _W, H = self.scene.cameras_at(frame)[0]
        position, _ = look_at_pose(c2w)
        ic = self.server.initial_camera
        ic.position = tuple(position)
        ic.look_at = tuple(position + 10.0 * np.asarray(c2w[:3, 2]))
        ic.up = (0.0, 0.0, 1.0)
        ic.fov = 2.0 * math.atan(0.5 * H / K[1, 1])

    # ------------------------------------------------------------------ selection and edits
    def select(self, track_id: Optional[str]) -> None:
        """Select an actor (None: nothing): show its identity and edits. The panel is
        updated before :attr:`selected` changes, so whoever sees the new selection sees
        its description too."""
        if track_id is not None and track_id not in self.scene.actors:
            return
        with self._select_lock:
            enabled = track_id is not None
            if enabled:
                info = self.scene.actors[track_id]
                edit = self.scene.edits.get(track_id)
                self.gui_actor_info.content = info.describe()
                self._syncing = True
                try:
                    self.gui_actor_visible.value = not edit.hidden
                    self.gui_actor_offset.value = edit.offset
                    self.gui_actor_yaw.value = edit.yaw
                finally:
                    self._syncing = False
            else:
                self.gui_actor_info.content = "Click an actor's box, or choose one above."
            for handle in (self.gui_actor_visible, self.gui_actor_offset, self.gui_actor_yaw):
                handle.disabled = not enabled
            if self.gui_actor.value != (track_id or "(none)"):
                self.gui_actor.value = track_id or "(none)"
            self.selected = track_id
        self._dirty.set()

    _syncing = False

    def _actor_chosen(self, event) -> None:
        value = self.gui_actor.value
        if value != "(none)" and value not in self.scene.actors:
            self.refuse(event.client, self.gui_actor, self.selected or "(none)",
                        f"Selected {value!r}: no such actor in this scene")
            return
        self.select(None if value == "(none)" else value)

    def _edit_selected(self, client=None) -> None:
        # under the selection lock: the fields and the selection they belong to change together
        with self._select_lock:
            if self._syncing or self.selected is None:
                return
            offset = tuple(float(v) for v in self.gui_actor_offset.value)
            yaw = float(self.gui_actor_yaw.value)
            current = self.scene.edits.get(self.selected)
            if not all(math.isfinite(v) and abs(v) <= MAX_OFFSET_M for v in offset):
                self.refuse(client, self.gui_actor_offset, current.offset,
                            f"Offset (m) {offset}: expected finite values within +-{MAX_OFFSET_M:g} m")
                return
            if not (math.isfinite(yaw) and abs(yaw) <= MAX_TURN_DEG):
                self.refuse(client, self.gui_actor_yaw, current.yaw,
                            f"Turn (deg) {yaw}: expected a finite angle within +-{MAX_TURN_DEG:g} degrees")
                return
            self.edit_actor(self.selected, ActorEdit(hidden=not self.gui_actor_visible.value, offset=offset, yaw=yaw))

    def edit_actor(self, track_id: str, edit: ActorEdit) -> None:
        """Set the panel's edit of ``track_id`` (a track id or an inserted actor's id) and
        redraw: the scene re-resolves its simulation with it."""
        self.scene.set_edit(track_id, edit)
        toggle = self.gui_actor_toggles.get(track_id)
        if toggle is not None and toggle.value == edit.hidden:
            toggle.value = not edit.hidden
        self._dirty.set()

    def set_hidden(self, track_id: str, hidden: bool) -> None:
        edit = self.scene.edits.get(track_id)
        if edit.hidden != hidden:
            self.edit_actor(track_id, ActorEdit(hidden, edit.offset, edit.yaw))
            if track_id == self.selected:
                self.select(track_id)

    def reset_edits(self) -> None:
        self.scene.clear_edits()
        for box in self.gui_actor_toggles.values():
            if not box.value:
                box.value = True
        self.select(self.selected)

    # ------------------------------------------------------------------ camera actions
    def look_through(self, client, c2w: np.ndarray, K: np.ndarray, height: int) -> None:
        """Put ``client``'s view at a dataset camera (pose and vertical field of view)."""
        position, wxyz = look_at_pose(c2w)
        with client.atomic():
            client.camera.fov = 2.0 * math.atan(0.5 * height / K[1, 1])
            client.camera.position = position
            client.camera.wxyz = wxyz

    def client_camera(self, client, max_width: Optional[int] = None):
        """The :class:`Camera` of ``client``'s current view (canvas aspect; scaled to at most
        ``max_width`` pixels wide and :data:`MAX_RENDER_WIDTH` high)."""
        cam = client.camera
        W, H = int(cam.image_width), int(cam.image_height)
        if W <= 0 or H <= 0:
            W, H = 640, 360
        scale = min(1.0, (max_width or W) / W, MAX_RENDER_WIDTH / H)
        if scale < 1.0:
            W, H = max(1, round(W * scale)), max(1, round(H * scale))
        return camera_from_view(cam.position, cam.wxyz, float(cam.fov), W, H, self.scene.recon.device)

    def render_for_client(self, client) -> Optional[np.ndarray]:
        """Render ``client``'s view on the server and show it in the panel; returns (H, W, 3),
        or None when refused (a width outside the slider's range, a render already running)."""
        width = self.gui_render_width.value
        if not (isinstance(width, int) and MIN_RENDER_WIDTH <= width <= MAX_RENDER_WIDTH):
            self.refuse(client, self.gui_render_width, 640,
                        f"Width (px) {width}: expected {MIN_RENDER_WIDTH}..{MAX_RENDER_WIDTH}")
            return None
        if not self._render_lock.acquire(blocking=False):
            self.refuse(client, None, None, "a server render is already running; try again when it is shown")
            return None
        try:
            camera = self.client_camera(client, width)
            t0 = time.perf_counter()
            rgb = self.scene.render(camera, self.frame, self.hidden_nodes())
            dt = time.perf_counter() - t0
        finally:
            self._render_lock.release()
        image = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
        self.gui_render_image.image = image
        self.gui_render_image.visible = True
        self.gui_render_note.content = (f"{camera.width}x{camera.height} at frame {self.frame:.1f} in {dt:.2f} s "
                                        f"({self.scene.recon.rasterizer_name} rasterizer)")
        return rgb

    def recolour(self, client) -> None:
        self.scene.set_eye(client.camera.position)
        self._dirty.set()

    # ------------------------------------------------------------------ drawing
    def refresh(self) -> None:
        """Bring the browser scene up to date with the current state (objects present at the
        frame, their poses and contents, toggles, boxes, cameras)."""
        with self._sync_lock:
            frame = self.frame
            sc = self.scene
            t = sc.time(frame)
            self.gui_seconds.content = time_line(t.seconds - float(sc.scene.frame_timestamps[0]), frame, sc.num_frames)
            objects = sc.objects_at(frame)
            hidden = self.hidden_nodes()
            api = self.server.scene
            for name, obj in objects.items():
                handle, version = self._handles.get(name, (None, -1))
                if handle is None or version != obj.version:
                    s = obj.splats
                    handle = api.add_gaussian_splats(name, s.centers, s.covariances, s.rgbs, s.opacities,
                                                     position=obj.position, wxyz=obj.wxyz)
                    self._handles[name] = (handle, obj.version)
                else:
                    handle.position = obj.position
                    handle.wxyz = obj.wxyz
                handle.visible = obj.node not in hidden
            for name in [n for n in self._handles if n not in objects]:
                self._handles.pop(name)[0].remove()
            self._draw_sky(hidden)
            self._draw_lidar(frame)
            self._draw_boxes(frame, hidden)
            self._draw_cameras(frame)

    def _draw_sky(self, hidden: frozenset[str]) -> None:
        env = self.scene.environment_nodes()
        if not env:
            return
        if self._sky_handle is None:
            sky = self.scene.sky()
            if sky is None:
                return
            self._sky_handle = self.server.scene.add_gaussian_splats("/sky", sky.centers, sky.covariances, sky.rgbs,
                                                                     sky.opacities)
        self._sky_handle.visible = env[0] not in hidden

    def _draw_lidar(self, frame: float) -> None:
        """The rendered sweep at ``frame`` as a point cloud (``/lidar``) while its box is
        ticked: rendered again when the moment, the edits or the scene changed, recoloured
        alone when only the colour choice did. The node toggles hide splats, not returns
        (the sweep alone is shown with every node off)."""
        if not (self.gui_lidar.value and self.scene.renders_lidar):
            if self._lidar_handle is not None:
                self._lidar_handle.visible = False
            return
        key = (frame, self.scene.edits.version, id(self.scene.recon))
        if key != self._lidar_key:
            t0 = time.perf_counter()
            self._lidar_sweep = self.scene.lidar_sweep(frame)
            self._lidar_seconds = time.perf_counter() - t0
            self._lidar_key, self._lidar_drawn_colour = key, None
        if self._lidar_drawn_colour != self._lidar_colour:
            points, sensor = self._lidar_sweep
            colours, scale = point_colours(points, sensor, self._lidar_colour)
            xyz = np.stack([points["x"], points["y"], points["z"]], axis=-1).astype(np.float32)
            if self._lidar_handle is not None:
                self._lidar_handle.remove()
            self._lidar_handle = self.server.scene.add_point_cloud("/lidar", xyz, colours, point_size=LIDAR_POINT_SIZE,
                                                                   point_shape="circle", precision="float32")
            self._lidar_drawn_colour = self._lidar_colour
            self.gui_lidar_note.content = (f"{len(points):,} points at frame {frame:.1f}, rendered in "
                                           f"{self._lidar_seconds:.2f} s; colour: {scale}")
        self._lidar_handle.visible = True

    def _draw_boxes(self, frame: float, hidden: frozenset[str]) -> None:
        boxes = self.scene.actor_boxes(frame) if self.gui_boxes.value else {}
        api = self.server.scene
        for tid, (R, c, size) in boxes.items():
            colour = SELECTED_COLOUR if tid == self.selected else BOX_COLOUR
            key = (tuple(size), colour)
            handle = self._boxes.get(tid)
            if handle is None or getattr(handle, "_omnire_key", None) != key:
                if handle is not None:
                    handle.remove()
                handle = api.add_box(f"/boxes/{tid}", colour, tuple(float(v) for v in size), wireframe=True,
                                     cast_shadow=False, receive_shadow=False)
                handle._omnire_key = key
                self._boxes[tid] = handle
            handle.position = c
            handle.wxyz = rotmat_to_quat(R)
            info = self.scene.actors[tid]
            handle.visible = info.inserted or info.node not in hidden
        for tid in [t for t in self._boxes if t not in boxes]:
            self._boxes.pop(tid).remove()

    def _draw_cameras(self, frame: float) -> None:
        api = self.server.scene
        cams = self.scene.cameras_at(frame) if self.gui_cameras.value else []
        seen = set()
        for name, c2w, K, W, H in cams:
            key = f"/cameras/{name or 'camera'}"
            seen.add(key)
            position, wxyz = look_at_pose(c2w)
            handle = self._frusta.get(key)
            if handle is None:
                handle = api.add_camera_frustum(key, fov=2.0 * math.atan(0.5 * H / K[1, 1]), aspect=W / H, scale=0.4,
                                                color=(200, 40, 40))
                self._frusta[key] = handle

                @handle.on_click
                def _(event, name=name) -> None:
                    for cname, c2w_now, K_now, _W, H_now in self.scene.cameras_at(self.frame):
                        if cname == name:
                            self.look_through(event.client, c2w_now, K_now, H_now)

            handle.position = position
            handle.wxyz = wxyz
        for key in [k for k in self._frusta if k not in seen]:
            self._frusta.pop(key).remove()

    # ------------------------------------------------------------------ scene swaps (training)
    def set_recon(self, recon, note: str = "") -> None:
        """Show another state of the scene (a training snapshot); redraws everything."""
        self.scene.set_recon(recon)
        self.gui_info.content = self._info_text(self._title, note)
        self._dirty.set()

    def wait_idle(self, timeout: float = 60.0) -> bool:
        """Block until every requested update has been drawn (tests, scripts)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if not self._dirty.is_set() and self._idle.is_set():
                return True
            time.sleep(0.02)
        return False

    # ------------------------------------------------------------------ threads
    def _update_loop(self) -> None:
        while not self._stop.is_set():
            self._idle.set()
            if not self._dirty.wait(0.2):
                continue
            self._idle.clear()
            self._dirty.clear()
            try:
                self.refresh()
            except Exception as exc:  # noqa: BLE001 - keep the viewer alive; show what failed
                self.gui_render_note.content = f"update failed: {type(exc).__name__}: {exc}"

    def _play_loop(self) -> None:
        while not self._stop.wait(0.25):
            if self.gui_play.value and self.scene.num_frames > 1:
                nxt = math.floor(self.frame) + 1
                self.gui_frame.value = float(nxt if nxt <= self.scene.num_frames - 1 else 0)
                self._dirty.set()

    def close(self) -> None:
        self._stop.set()
        self.gate.close()
        self.server.stop()


def time_line(seconds: float, frame: float, num_frames: int) -> str:
    """The time slider's caption: seconds since the first frame (the clock of ``omnire sim``
    and of scenario files) and the frame."""
    return f"frame {frame:.1f} of 0-{num_frames - 1}  \nt = {seconds:.3f} s since the first frame"
