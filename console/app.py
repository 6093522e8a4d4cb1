"""The operator console: a viser server over a running :class:`~trackmeter.pipeline.pipeline.Pipeline`.

Threads (DESIGN.md section 4 and 8):

- viser's callbacks (a thread pool) only turn a click or a widget change into a pipeline
  :class:`~trackmeter.pipeline.snapshot.Command` and remember its reply future;
- the tracking thread calls :meth:`Console._on_snapshot` per snapshot, which only appends the
  pose/error rows of the live plots (a deque append);
- the publisher thread (:meth:`Console._publish_loop`) reads the newest snapshot at
  ``publish_hz``, draws the overlays into the left image, JPEG-encodes it once for every
  client, and pushes image, 3D scene, numbers and plots under ``server.atomic()``. It also
  turns finished command replies into notifications for the browser that sent them.

Everything the console shows lives in viser's shared scene and GUI state, so several browsers
see the same thing and a browser that connects late gets the current state at once.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import logging
import re
import threading
import time
from collections import deque
from collections.abc import Callable, Coroutine, Sequence
from concurrent.futures import Future
from html import escape
from pathlib import Path
from typing import Any, cast

import numpy as np
import viser
import viser.uplot
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from console.overlay import (STATUS_RGB, LostTargets, Trails, box_half_px, box_segments, draw_matches,
                             draw_overlays, image_view, node_rgb_for, pixel_to_plane, ray_to_pixel, to_rgb,
                             view_band, view_in_band)
from console.series import PLOTS, PlotData
from trackmeter.core.features import METHODS
from trackmeter.core.stereo import StereoRig
from trackmeter.core.targets import TargetState
from trackmeter.core.tracking import REMOVE_NEAREST_PX
from trackmeter.core.transforms import invert_transform, matrix_to_quat_wxyz
from trackmeter.errors import counted, quoted_name
from trackmeter.pipeline.engine import MODEL_NOT_TARGETED, SelectModelPoints
from trackmeter.pipeline.pipeline import Pipeline, RecordingStats
from trackmeter.pipeline.snapshot import (
    AcquireModel,
    ClearTargets,
    Command,
    CommandReply,
    LoadModel,
    RemoveNearest,
    RestartSource,
    SelectPoint,
    SetAuto,
    SetCase,
    SetFilterCutoff,
    SetPaused,
    SetRecording,
    Snapshot,
    StepOnce,
)
from trackmeter.pipeline.views import SwappedViewsWatch
from trackmeter.sources.base import StereoFrame

log = logging.getLogger(__name__)

#: The model-point dropdown's first option: the next click makes an ordinary (unnamed) target.
NEW_TARGET = "a new target"


def shown_text(text: str) -> str:
    """``text`` as the browser can be sent it: a file name's bytes that are not UTF-8 (held
    by Python as lone surrogates, PEP 383) written as ``\\xff`` escapes. viser's messages are
    UTF-8; one such character makes every message fail, and no page connects."""
    try:
        return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
    except UnicodeEncodeError:  # a surrogate that stands for no byte (a YAML "\\ud800" escape)
        return text.encode("utf-8", "backslashreplace").decode("utf-8")


def typed_text(text: str) -> str:
    """The inverse of :func:`shown_text` for a file name typed back (or edited) in a field:
    ``\\x80``-``\\xff`` escapes stand for those bytes (PEP 383's lone surrogates), so the
    Folder field's shown name means the folder itself, not one named with backslashes."""
    return re.sub(r"\\x([89a-fA-F][0-9a-fA-F])", lambda m: chr(0xDC00 + int(m.group(1), 16)), text)


def new_target_option(model_ids: Sequence[str]) -> str:
    """The "Next click is" option for a click that makes a new target: :data:`NEW_TARGET`,
    unless a model point has that id (the browser's dropdown refuses duplicate options, and
    the page goes blank), then one no model point has."""
    option = NEW_TARGET
    while option in model_ids:
        option += " (no model point)"
    return option


#: Scene units per image pixel of the image planes (726 px → 7.26 units).
UNITS_PER_PX = 0.01
#: Where the 3D view (the left camera frame) sits in the scene, left of the image.
SCENE3D_OFFSET = (-8.0, 0.0, -3.0)
#: The automatic selection methods offered: the paper's (2.B) and the Shi-Tomasi baseline.
AUTO_METHODS = METHODS
# The operator widget each toggle command comes from (Console._mirror), by command name.
_WIDGETS_OF_COMMAND = {"SetAuto": ("auto", "auto_count", "auto_method"), "SetRecording": ("record",), "SetCase": ("case",),
                       "SetFilterCutoff": ("cutoff",)}
#: What a command's pop-up is titled: the control the operator used, not the command's class.
_COMMAND_TITLES = {"SetAuto": "Automatic selection", "SetRecording": "Record", "SetCase": "Case",
                   "SetFilterCutoff": "Filter cutoff", "ClearTargets": "Clear targets", "RemoveTarget": "Remove target",
                   "AcquireModel": "Acquire model", "LoadModel": "Load model", "SetPaused": "Pause",
                   "StepOnce": "Step", "RestartSource": "Restart", "ResetTracking": "Reset tracking",
                   "SelectModelPoints": "Click the model points"}


def _on_event_loop(callback: Callable[[Any], None]) -> Callable[[Any], Coroutine[Any, Any, None]]:
    """``callback`` as a coroutine function, so that viser runs it on its event loop at once.

    viser stores a browser's new value on the widget, then hands a plain callback to a thread
    pool: on a loaded machine it ran later, after a push had put the tracker's old value back
    on the widget, and read and sent that (a cutoff typed just as the previous one was refused
    was lost); and two clicks handed to the pool could reach the tracker the other way round.
    Run on the loop, the callback reads the value that arrived, and callbacks run in the order
    their messages came (viser's own advice for stateful gestures). ``callback`` must only read
    widgets and the latest snapshot and enqueue: it runs on the loop, which must never block.
    """

    async def on_loop(event: Any) -> None:
        callback(event)

    return on_loop


def decimal_of(text: str) -> float | None:
    """A number typed by an operator, with a decimal point or a decimal comma ("0.5", "0,5");
    None for an empty field. ValueError, with the text, for anything else (two marks, a unit,
    "nan", "inf"): a guess would send a value the operator did not mean."""
    typed = text.strip()
    if not typed:
        return None
    digits = typed.replace(",", ".", 1) if typed.count(",") == 1 and "." not in typed else typed
    if re.fullmatch(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?", digits) is None:
        raise ValueError(f"{typed!r} is not a number: type it as 0.5 or 0,5")
    return float(digits)


def whole_number_of(text: str, low: int, high: int) -> int | None:
    """A whole number from ``low`` to ``high`` typed by an operator; None for an empty field.
    ValueError, with the text and the range, for anything else ("1e9", "2.5", "0,5", "abc"):
    a guess would send a count the operator did not mean."""
    typed = text.strip()
    if not typed:
        return None
    if re.fullmatch(r"[+-]?\d+", typed) is None or not low <= int(typed) <= high:
        raise ValueError(f"{typed!r} is not a whole number from {low} to {high}")
    return int(typed)


def _hz_text(hz: float) -> str:
    """A frequency as the cutoff field shows it: 2 Hz as "2", 0.55 as "0.55", 11.875 and
    1.2345678 whole (typed back as shown, it is the value the tracker holds)."""
    return f"{hz:.15g}"


def _pixel_text(uv: tuple[float, float]) -> str:
    """``(u, v)`` to the whole pixel; a click on the border (-0.5) reads 0, not "-0"."""
    return f"({round(uv[0])}, {round(uv[1])})"


#: How long a pop-up answering a command stays up, s: a confirmation, a refusal (read longer).
POPUP_OK_S = 4.0
POPUP_REFUSED_S = 8.0
#: ... after which the console closes it itself, this much later (the browser's own timer
#: stops while the pointer rests on it).
POPUP_GRACE_S = 0.5

#: A typed filter cutoff or target count is sent once the field has held it this long, s:
#: viser sends every keystroke of a field, and "0.5" passes 0, which the filter refuses
#: (each accepted value also rebuilds the filter), "16" passes 1.
EDIT_SETTLE_S = 0.8
SERIES_COLOURS = ("#e6194b", "#3cb44b", "#4363d8", "#111111")
#: Line thickness of the operator targets' boxes drawn over the left image, image px.
OPERATOR_BOX_PX = 2.0
#: Boxes for the operator's targets built ahead, parked (more are added when needed).
OPERATOR_MARKS_RESERVED = 4
#: In front of the image plane (scene units; the image is seen from -z).
OVERLAY_Z = -0.01
#: Colour of the measured 3D points in the 3D view: tracking, or measured again after a loss.
POINT_COLOURS = {"tracking": (60, 230, 60), "other": (255, 200, 0)}
#: A plot's padding around its axes, CSS px (top, right, bottom, left): viser's default top of 0
#: cut the label of a tick at the top of the y range in half.
PLOT_PADDING_PX = (10, 24, 0, 0)
#: The live numbers' fixed height (see Console._status_html): six status lines, the source's
#: line wrapped to two and the pose's to three (:data:`STATUS_CLAMP_LINES`), the six-row table
#: and the attitude error, at line-height 1.45.
STATUS_HEIGHT_EM = 27.0
#: Lines the source's line (its warning), the targets' line (why automatic selection started
#: none) and the pose's line (its reason) may take in the live numbers before they are cut with
#: an ellipsis (the whole text shows on hover): a long warning (six images skipped, each named)
#: took the box's height and hid the pose and rates below it.
STATUS_CLAMP_LINES = {"source": 2, "targets": 2, "pose": 3}
#: Rows of the target list (the rest counted in one more).
TARGET_LIST_ROWS = 40
#: How often the publisher hands the C heap's free pages back to the system (see :func:`release_free_heap`).
TRIM_EVERY_S = 10.0


def _load_malloc_trim() -> Any:
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        trim = libc.malloc_trim
    except (OSError, AttributeError):  # not glibc (macOS, musl without it, Windows)
        return None
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    return trim


_MALLOC_TRIM = _load_malloc_trim()

#: glibc mallopt(3) parameters (malloc.h).
_M_MMAP_THRESHOLD = -3
_M_ARENA_MAX = -8
#: Allocations at least this large are served by mmap and returned to the system when freed.
MMAP_THRESHOLD_BYTES = 256 * 1024


def pin_mmap_threshold(threshold_bytes: int = MMAP_THRESHOLD_BYTES, arena_max: int = 2) -> bool:
    """Keep image-sized buffers out of the heap arenas (glibc); False where unavailable.

    Why: glibc starts with a 128 kB mmap threshold and RAISES it (up to 32 MB) each time an
    mmapped block is freed, so after the first published frame every 1 MB overlay, JPEG and
    message buffer comes from the per-thread arenas, which keep the freed pages (see
    :func:`release_free_heap`). Setting the threshold explicitly turns that dynamic raise off
    (mallopt(3)): every buffer of at least ``threshold_bytes`` is mmapped and unmapped on free.
    ``arena_max`` bounds the number of arenas the publisher, tracking, acquisition and web
    threads can spread their free memory over. Call it before the threads start.
    """
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    ok = mallopt(_M_MMAP_THRESHOLD, int(threshold_bytes)) == 1
    if arena_max > 0:
        ok = mallopt(_M_ARENA_MAX, int(arena_max)) == 1 and ok
    return ok


def release_free_heap() -> bool:
    """Return the C heap's free pages to the system (glibc ``malloc_trim(0)``); False where unavailable.

    Why: every publish allocates and frees image-sized buffers (the RGB overlay, 726x512x3 =
    1.1 MB, the JPEG, the serialised messages) on several threads. glibc raises its mmap
    threshold once such a buffer is freed (mallopt(3), M_MMAP_THRESHOLD), so later ones most
    likely come from the per-thread arenas, which keep freed pages. Measured on the ``sim``
    console with two browsers connected: the resident set grew in steps of 20-50 MB while
    the bytes in use stayed flat (mallinfo2 ``uordblks`` ~95-105 MB); the growth was all
    ``fordblks``, free memory the allocator held. ``malloc_trim(0)`` took the process from
    336 to 282 MB.
    """
    if _MALLOC_TRIM is None:
        return False
    _MALLOC_TRIM(0)
    return True


def add_plot(gui: viser.GuiApi, title: str, labels: tuple[str, ...]) -> viser.GuiUplotHandle:
    """One live time plot as the console shows it: x the frame time in s, a line per label."""
    series = (viser.uplot.Series(label="t [s]"),) + tuple(
        viser.uplot.Series(label=lab, stroke=SERIES_COLOURS[i % len(SERIES_COLOURS)], width=1.5)
        for i, lab in enumerate(labels))
    data = (np.array([0.0, 1e-3]),) + tuple(np.zeros(2) for _ in labels)
    handle = gui.add_uplot(data, series, title=title, aspect=1.6, padding=PLOT_PADDING_PX,
                           scales={"x": viser.uplot.Scale(time=False, auto=True)})
    # viser needs rows to make the plot; no values yet (no pose): null, not a line at 0.
    set_uplot_data(handle, uplot_data((data[0],) + tuple(np.full(2, np.nan) for _ in labels)))
    return handle


def uplot_data(arrays: tuple[NDArray[np.float64], ...]) -> tuple[NDArray[np.float64] | list[float | None], ...]:
    """A plot window's arrays (``console.series``: NaN marks a gap) as uPlot must get them.

    uPlot breaks a line only at ``null``. A NaN goes to ``Path2D.lineTo``, which ignores it, so
    the line runs straight from the point before to the point after; a NaN first value even
    empties the auto-ranged y axis. A Float64Array cannot hold ``null``, so a y array with NaN
    travels as a list with None there (msgpack nil, ``null`` in the browser); the others stay
    numpy (sent as binary). No NaN reaches the browser. The x array never has NaN.
    """
    out: list[NDArray[np.float64] | list[float | None]] = [arrays[0]]
    for a in arrays[1:]:
        if np.isnan(a).any():
            out.append([None if v != v else v for v in a.tolist()])  # v != v: NaN
        else:
            out.append(a)
    return tuple(out)


def set_uplot_data(handle: viser.GuiUplotHandle, data: tuple[NDArray[np.float64] | list[float | None], ...]) -> None:
    """Show ``data`` (:func:`uplot_data`) in the browsers' plot ``handle``.

    viser's ``.data`` setter casts every element to a float64 array (None becomes NaN again, and
    the line is joined across the gap), so data holding None is stored in the handle's props
    and queued for the browsers as that setter does it, minus the cast (viser 1.1; checked by
    tests/browser/test_plots.py). A browser that connects later gets the stored props, gaps
    included.
    """
    if all(isinstance(a, np.ndarray) for a in data):
        handle.data = data  # type: ignore[assignment]
        return
    handle._impl.props.data = data  # type: ignore[attr-defined]  # viser 1.1: its props Protocol declares only 'order'
    handle._queue_update("data", data)


def _wxyz(R: np.ndarray) -> tuple[float, float, float, float]:
    """viser's ``wxyz`` of a rotation matrix (3,3)."""
    w, x, y, z = (float(c) for c in matrix_to_quat_wxyz(R))
    return w, x, y, z


class _OperatorMarks:
    """The operator's targets over the left image: one box (in its status colour) with an ``id*``
    label per target, scene nodes under ``root`` in the image plane's frame.

    A mark is moved by its node's position only: viser's client applies a node's pose in the
    frame that receives it, whereas a change of its geometry or colour goes through a React
    render and shows one frame later (in software WebGL ~100 ms a frame). So the marks are a
    pool of boxes built once around their own origin; a target takes a free one, which is
    moved onto it, recoloured only when the status changes, and parked out of sight when the
    target goes: just behind the image, which hides it, but inside the view, so the browser
    draws it (three.js compiles a shader when an object is first drawn, ~0.5 s in software
    WebGL, which a box parked outside the view would leave for the operator's first click).
    """

    PARK = (0.0, 0.0, 0.05)

    def __init__(self, scene: Any, root: str, patch_px: int) -> None:
        self.scene = scene
        self.root = root
        self.half_px = box_half_px(patch_px, operator=True)
        self.slots: list[tuple[Any, Any, list[Any]]] = []  # (box, label, [target id, status])
        self.of_target: dict[str, int] = {}
        self._geometry: tuple[tuple[int, int], tuple[float, float]] | None = None

    def _box(self, image_size: tuple[int, int], render_size: tuple[float, float]) -> NDArray[np.float32]:
        centre = (image_size[0] / 2.0, image_size[1] / 2.0)
        seg = box_segments([centre], self.half_px, image_size, render_size, OVERLAY_Z)
        seg[:, :, :2] -= pixel_to_plane([centre], image_size, render_size)[0].astype(np.float32)
        return seg

    def reserve(self, n: int, image_size: tuple[int, int], render_size: tuple[float, float]) -> None:
        """Build ``n`` parked boxes ahead, so that the operator's first clicks find them built
        and drawn once."""
        self._geometry = (image_size, render_size)
        while len(self.slots) < n:
            self._new_slot(image_size, render_size)

    def update(self, targets: list[Any], image_size: tuple[int, int], render_size: tuple[float, float]) -> None:
        """Show ``targets`` (the operator's, with their ``uv`` in pixels of the image)."""
        shown = {t.id: t for t in targets if np.all(np.isfinite(t.uv))}
        if self._geometry != (image_size, render_size):  # a new image size: rebuild the boxes
            self._geometry = (image_size, render_size)
            box = self._box(image_size, render_size)
            for node, label, _ in self.slots:
                node.points = box
                label.position = self._label_position(image_size, render_size)
        for tid in [i for i in self.of_target if i not in shown]:
            node, label, state = self.slots[self.of_target.pop(tid)]
            node.position = self.PARK
            label.text = ""
            state[0] = None
        free = [k for k, (_, _, state) in enumerate(self.slots) if state[0] is None]
        for tid, t in shown.items():
            k = self.of_target.get(tid)
            if k is None:
                k = free.pop(0) if free else self._new_slot(image_size, render_size)
                self.of_target[tid] = k
                self.slots[k][2][0] = tid
                self.slots[k][1].text = f"{tid}*"
            node, _, state = self.slots[k]
            if state[1] != t.status:
                state[1] = t.status
                node.colors = self._colours(t.status)
            x, y = pixel_to_plane([t.uv], image_size, render_size)[0]
            node.position = (float(x), float(y), 0.0)

    def _label_position(self, image_size: tuple[int, int], render_size: tuple[float, float]) -> tuple[float, float, float]:
        per_px = render_size[0] / image_size[0]  # beside the box's top-right corner
        return ((self.half_px + 2.0) * per_px, -self.half_px * per_px, OVERLAY_Z)

    @staticmethod
    def _colours(status: str) -> NDArray[np.uint8]:
        # Per vertex: viser's client takes those as linear (what node_rgb_for models), but a
        # single colour as sRGB.
        rgb = np.array(node_rgb_for(STATUS_RGB.get(status, (255, 255, 255))), np.uint8)
        return np.broadcast_to(rgb, (4, 2, 3)).copy()

    def _new_slot(self, image_size: tuple[int, int], render_size: tuple[float, float]) -> int:
        k = len(self.slots)
        node = self.scene.add_line_segments(f"{self.root}/{k}", self._box(image_size, render_size),
                                            self._colours("tracking"),
                                            thickness=OPERATOR_BOX_PX * UNITS_PER_PX, position=self.PARK)
        label = self.scene.add_label(f"{self.root}/{k}/label", "", position=self._label_position(image_size, render_size),
                                     anchor="bottom-left", font_screen_scale=0.8,
                                     depth_test=True)  # parked behind the image: hidden by it
        self.slots.append((node, label, [None, "tracking"]))
        return k


def _sigma_text(cov_pose: Any) -> str:
    """``", 1σ 12.3 mm, 0.41°"``: a pose's standard deviation in its worst direction, of the
    position and of the attitude (from its (6,6) covariance, m and rad), or "" when it has
    none. A pose valid within its bounds (``pose.max_*_sigma_*``) may still be tens of mm
    uncertain with a few points: said beside it."""
    cov = np.asarray(cov_pose, dtype=float)
    if cov.shape != (6, 6) or not np.all(np.isfinite(cov)):
        return ""
    position_m, rotation_rad = (float(np.sqrt(max(np.linalg.eigvalsh(block).max(), 0.0)))
                                for block in (cov[:3, :3], cov[3:, 3:]))
    return f", 1σ {position_m * 1e3:.1f} mm, {np.degrees(rotation_rad):.2f}°"


class Console:
    """Builds the scene and GUI on ``server`` and keeps them in step with ``pipeline``.

    Args:
        server: a started viser server.
        pipeline: the running pipeline (the console only submits commands and reads snapshots).
        rig: the stereo rig (frustums, image size); defaults to ``pipeline.rig``.
        mockup_mesh: ``(vertices (V,3) body m, faces (F,3), colours (F,3) or (V,3) uint8)`` of the
            mock-up, drawn at the estimated pose (and as a ghost at the true pose).
        publish_hz: UI update rate (images, scene, numbers).
        plot_every: update the plots every Nth publish (they carry ~1000 points each).
        text_every: update the live numbers and the target list every Nth publish, and at once
            when the operator's targets change (text read by a person needs no 12 Hz; each update
            is a re-layout of the panel in every browser, on the thread that also draws).
        jpeg_quality: JPEG quality of the image planes.
        record_root: default parent folder of recordings started from the UI.
        patch_px: patch side drawn around each target, px.
    """

    def __init__(
        self,
        server: viser.ViserServer,
        pipeline: Pipeline,
        *,
        rig: StereoRig | None = None,
        mockup_mesh: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
        source_label: str = "",
        publish_hz: float = 12.0,
        plot_every: int = 3,
        text_every: int = 3,
        jpeg_quality: int = 85,
        record_root: str | Path = "runs",
        patch_px: int = 8,
    ) -> None:
        self.server = server
        self.pipeline = pipeline
        self.rig = rig if rig is not None else pipeline.rig
        self.mockup_mesh = mockup_mesh
        self.source_label = source_label
        self.publish_hz = float(publish_hz)
        self.plot_every = max(1, int(plot_every))
        self.text_every = max(1, int(text_every))
        self.jpeg_quality = int(jpeg_quality)
        self.record_root = Path(record_root)
        self._record_dir_shown: str | None = None  # the recording's folder last put in the Folder field
        self.patch_px = patch_px
        self.plots = PlotData()
        self._trails = Trails()
        self._pending: deque[tuple[Future[CommandReply], Any, str]] = deque()
        self._pending_lock = threading.Lock()
        # A click named after a model point, until its reply: the choice it used (_click_at).
        self._model_point_clicks: dict[Future[CommandReply], str] = {}
        self._next_click_owner: int | None = None  # client id of the browser whose choice "Next click is" shows
        self._views: dict[int, list[Any]] = {}  # client id -> [client, preset, aspect framed for]
        self._popups: dict[int, Any] = {}  # client id -> the pop-up it shows last
        self._popup_close_at: dict[int, float] = {}  # client id -> when its pop-up is closed (monotonic s)
        self._stop = threading.Event()
        # Set when what the page should show changed on the console's side (a widget to show the
        # tracker's value again, the right image shown): paused or ended, no new snapshot comes
        # to push it, so the publisher pushes the latest one again (_publish_loop).
        self._repush = threading.Event()
        self._thread: threading.Thread | None = None
        self._unsubscribe: Any = None
        self._image_size: tuple[int, int] | None = self.rig.image_size if self.rig is not None else None
        # Observability for tests and benchmarks (read-only from outside).
        self.images_pushed = 0
        self.last_pushed_sequence = 0
        self.last_pushed_target_ids: tuple[str, ...] = ()
        self.last_pushed_time = 0.0
        self.last_push: tuple[float, int, tuple[str, ...]] = (0.0, 0, ())
        self.notifications: deque[tuple[str, str]] = deque(maxlen=50)
        self.push_ms: deque[float] = deque(maxlen=200)  # publisher cost of recent pushes
        # (time.monotonic(), target ids shown) of the recent image pushes (benchmarks/console.py).
        self.image_pushes: deque[tuple[float, tuple[str, ...]]] = deque(maxlen=200)
        self._loop_said = False  # the pop-up that the source loops, once (again after a Restart)
        self._shortfall_said = False  # why automatic selection started none, popped up once (_say_shortfall)
        # left and right images given the wrong way round, popped up once (_say_views)
        self._views_watch = SwappedViewsWatch(self.rig) if self.rig is not None else None
        self._views_seen_sequence = -1  # the snapshot whose frame _say_views looked at last
        self._lost_targets = LostTargets()  # a lost target's mark is left out after a while
        # Ids of targets not drawn (lost too long): a shift-click does not remove what it cannot
        # see. Set by the publisher, read by the click handler: one reference, replaced whole.
        self._hidden_ids: frozenset[str] = frozenset()
        self._plot_version: dict[str, int] = {}
        self._omega_shown = False
        self._pushed_operator_ids: set[str] = set()
        # The tracker's state each operator widget last mirrored, by widget (see _mirror).
        self._mirrored: dict[str, Any] = {}
        # Typed values waiting to settle, by widget: (command maker, browser, when typed).
        self._edits: dict[str, tuple[Any, Any, float]] = {}
        self.edit_callbacks: dict[str, Any] = {}
        self._build_scene()
        self._build_gui()
        server.on_client_connect(self._on_connect)
        server.on_client_disconnect(self._on_disconnect)

    # ------------------------------------------------------------------ life cycle
    def start(self) -> Console:
        self._unsubscribe = self.pipeline.subscribe(self._on_snapshot)
        self._thread = threading.Thread(target=self._publish_loop, name="console-publisher", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)
        if self._unsubscribe is not None:
            self._unsubscribe()
        # The page keeps what it was last sent ("running · frame N · REC") once the server is
        # gone, with only viser's small disconnected icon to tell: say it, before the server stops.
        status = getattr(self, "status_html", None)
        if status is not None:
            try:
                status.content = ('<div style="padding:0 0.75rem"><b>stopped</b>: the console server was shut '
                                  'down; reload this page once it runs again</div>')
                self.server.flush()
            except Exception:  # a server already stopped: nothing to tell
                log.debug("could not show the stop on the page", exc_info=True)

    # ------------------------------------------------------------------ scene
    @property
    def render_size(self) -> tuple[float, float]:
        w, h = self._image_size or (640, 480)
        return w * UNITS_PER_PX, h * UNITS_PER_PX

    def _build_scene(self) -> None:
        scene = self.server.scene
        scene.set_up_direction("-y")
        # No shadows: viser's default directional light renders three cascaded 1024x1024 shadow
        # maps before every frame (measured in headless Chromium: 3 extra framebuffer passes per
        # frame), and a console in space has nothing to cast them on. The client renders
        # continuously while images stream in (each update opens a 250 ms render window), so
        # this is paid at the browser's frame rate, not at the image rate.
        scene.configure_default_lights(enabled=True, cast_shadow=False)
        w, h = self._image_size or (640, 480)
        rw, rh = self.render_size
        blank = np.zeros((h, w, 3), np.uint8)
        self.left_image = scene.add_image("/left", blank, rw, rh, format="jpeg", jpeg_quality=self.jpeg_quality,
                                          cast_shadow=False, receive_shadow=False)
        self.right_image = scene.add_image("/right", blank, rw, rh, format="jpeg", jpeg_quality=self.jpeg_quality,
                                           position=(rw + 0.2, 0.0, 0.0), visible=False,
                                           cast_shadow=False, receive_shadow=False)
        # The operator's targets are drawn over the image as scene nodes, not into it: a click's
        # answer then shows in the browser's next frame instead of waiting for a new image to be
        # decoded and uploaded (in software WebGL ~200 ms, and viser drops an image still loading
        # when a newer one arrives). Automatic targets, many and coming and going, stay drawn
        # into the image, in step with it.
        self.operator_marks = _OperatorMarks(scene, "/left/operator_marks", self.patch_px)
        if self._image_size is not None:
            self.operator_marks.reserve(OPERATOR_MARKS_RESERVED, self._image_size, self.render_size)
        self.left_image.on_click(_on_event_loop(self._on_click))
        for modifier in ("shift", "cmd/ctrl", "alt"):
            self.left_image.on_click(modifier=modifier)(_on_event_loop(self._on_remove_click))
        # Every click is answered: one on the right image says where targets are set, and one
        # beside both images (the view's blank margin) too.
        self.right_image.on_click(_on_event_loop(self._on_right_click))
        # viser 1.1 runs a coroutine callback here too (_dispatch_callback), but SceneApi.on_click is hinted for None only
        scene.on_click()(_on_event_loop(self._on_scene_click))  # type: ignore[arg-type]

        root = scene.add_frame("/scene3d", show_axes=False, position=SCENE3D_OFFSET)
        self.scene3d = root
        if self.rig is not None:
            cam = self.rig.left
            fov = 2.0 * np.arctan2(cam.height / 2.0, cam.K[1, 1])
            aspect = cam.width / cam.height
            scene.add_camera_frustum("/scene3d/cam0", fov, aspect, scale=0.15, color=(40, 120, 255))
            R, T = np.asarray(self.rig.R), np.asarray(self.rig.T).reshape(3)
            scene.add_camera_frustum("/scene3d/cam1", fov, aspect, scale=0.15, color=(255, 120, 40),
                                     wxyz=_wxyz(R.T), position=tuple(-R.T @ T))
        scene.add_frame("/scene3d/cam_axes", axes_length=0.2, axes_radius=0.008)
        # One cloud per status, each of one fixed colour, and only their positions are ever
        # updated: viser's client builds a new point material (a shader program to compile)
        # whenever a cloud's colours are assigned, and software WebGL (SwiftShader) compiled one
        # per publish, ~12 a second, which took most of a headless browser's CPU.
        self.points = {status: scene.add_point_cloud(f"/scene3d/points_{status}", np.zeros((1, 3), np.float32),
                                                     POINT_COLOURS[status], point_size=0.03, precision="float32",
                                                     visible=False)
                       for status in POINT_COLOURS}
        self.body = scene.add_frame("/scene3d/body", axes_length=0.4, axes_radius=0.01, visible=False)
        self.truth = scene.add_frame("/scene3d/truth", axes_length=0.3, axes_radius=0.005, visible=False,
                                     origin_color=(180, 180, 180))
        self.omega = scene.add_frame("/scene3d/omega_root", show_axes=False, visible=False)
        # The spin arrow; like the point cloud it is created once and updated in place.
        self.omega_arrow = scene.add_arrows("/scene3d/omega", np.zeros((1, 2, 3), np.float32), (255, 0, 200),
                                            shaft_radius=0.01, head_radius=0.03, head_length=0.06, visible=False)
        # The mock-up at the estimated pose, its mesh in the true body frame: drawn through the
        # body alignment the live errors use (case (a)'s and (c)'s own frames are not the
        # mock-up's; drawn at the bare pose it stood turned away from the truth while the
        # errors read 0.07 deg), hidden while no alignment is known.
        self.mockup = scene.add_frame("/scene3d/body/mockup", show_axes=False, visible=False)
        if self.mockup_mesh is not None:
            self._add_mesh("/scene3d/body/mockup", opacity=None)
            self._add_mesh("/scene3d/truth/ghost", opacity=0.25)

    def _add_mesh(self, name: str, opacity: float | None) -> None:
        assert self.mockup_mesh is not None
        vertices, faces, colours = self.mockup_mesh
        vertices = np.asarray(vertices, np.float32)
        faces = np.asarray(faces, np.int32)
        colours = np.asarray(colours, np.uint8)
        if colours.shape[0] != faces.shape[0]:  # per-vertex: colour each face by its first vertex
            colours = colours[faces[:, 0]]
        # add_mesh_simple has one colour per mesh: one mesh per colour.
        keys, inverse = np.unique(colours.reshape(-1, 3), axis=0, return_inverse=True)
        for k, rgb in enumerate(keys):
            sel = faces[inverse.reshape(-1) == k]
            self.server.scene.add_mesh_simple(f"{name}/part{k}", vertices, sel,
                                              color=cast("tuple[int, int, int]", tuple(int(c) for c in rgb)),
                                              opacity=opacity, side="front", flat_shading=True,
                                              cast_shadow=False, receive_shadow=False)

    def _update_scene3d(self, snap: Snapshot) -> None:
        for status, cloud in self.points.items():
            pts = [t.point_cam for t in snap.targets
                   if t.measured and (t.status == "tracking") == (status == "tracking") and np.all(np.isfinite(t.point_cam))]
            if pts:
                # Update the handle in place: re-adding the node at every publish replaced it (a
                # new handle, a purge of its buffered state, a create message) ~12 times a second.
                cloud.points = np.array(pts, np.float32)
                cloud.visible = True
            elif cloud.visible:
                cloud.visible = False
        pose = snap.pose
        if pose.valid:
            T = np.asarray(pose.T_cam_body)
            self.body.wxyz = _wxyz(T[:3, :3])
            self.body.position = tuple(T[:3, 3])
            self.body.visible = True
        else:
            self.body.visible = False
        X = (snap.errors or {}).get("T_bodytrue_bodyest")
        if pose.valid and X is not None:
            T_bodyest_bodytrue = invert_transform(np.asarray(X, float))
            self.mockup.wxyz = _wxyz(T_bodyest_bodytrue[:3, :3])
            self.mockup.position = tuple(T_bodyest_bodytrue[:3, 3])
            self.mockup.visible = True
        elif self.mockup.visible:
            self.mockup.visible = False
        omega_body = np.asarray(pose.omega_body_rad_s)
        if pose.valid and np.all(np.isfinite(omega_body)):
            # The spin axis in the camera frame from the body origin; 1 deg/s is drawn 0.1 m long.
            tip = T[:3, 3] + (T[:3, :3] @ omega_body) * np.degrees(1.0) * 0.1
            self.omega_arrow.points = np.array([[T[:3, 3], tip]], np.float32)
            self.omega_arrow.visible = True
            self._omega_shown = True
        elif self._omega_shown:
            self.omega_arrow.visible = False
            self._omega_shown = False
        truth = snap.frame.truth if snap.frame is not None else None
        if truth is not None:
            T = np.asarray(truth.T_cam_body)
            self.truth.wxyz = _wxyz(T[:3, :3])
            self.truth.position = tuple(T[:3, 3])
            self.truth.visible = True
        else:
            self.truth.visible = False

    # ------------------------------------------------------------------ GUI
    def _build_gui(self) -> None:
        gui = self.server.gui
        try:
            gui.main_panel.dock_right()
        except Exception:  # older viser: the panel floats, which is fine
            pass
        gui.configure_theme(dark_mode=False, show_logo=False)
        self.status_html = gui.add_html('<div style="padding:0 0.75rem">TV-Trackmeter — starting …</div>')
        with gui.add_folder("Source"):
            self.pause_button = gui.add_button("Pause")
            self.step_button = gui.add_button("Step")
            self.restart_button = gui.add_button("Restart")
        with gui.add_folder("Targets"):
            self.auto_checkbox = gui.add_checkbox("Automatic selection", initial_value=False)
            # Up to the tracker's limit: a larger count would be refused. Text, not viser's
            # slider and its number field, which took "1e9" as 19 and "0,5" as 5 and left "abc"
            # blank, none of it said (an outside monkey probe). Read by whole_number_of.
            most = int(getattr(self.pipeline.engine, "max_targets", 64))
            self.auto_count_max = most
            self.auto_count = gui.add_text("Count", initial_value=str(min(16, most)),
                                           hint=f"1 to {most}: automatic selection tops the tracked targets (all "
                                                "of them) up to this many; a lower count removes none")
            method = str(getattr(self.pipeline.engine, "auto_method", AUTO_METHODS[0]))
            methods = AUTO_METHODS if method in AUTO_METHODS else (*AUTO_METHODS, method)
            self.auto_method = gui.add_dropdown("Method", methods, initial_value=method,
                                                hint="gabor: a directional Gabor bank (paper 2.B); centroid: one "
                                                     "point a bright region, its centroid; shi_tomasi: the baseline")
            self.clear_button = gui.add_button("Clear targets")
            gui.add_markdown("Click the left image to add a target; shift-, ctrl- or alt-click removes the nearest "
                             f"within {REMOVE_NEAREST_PX:g} px.")
        # Open where the pose waits on it: case (b)'s status line sends the operator "under
        # Model" to bind the points (an outside probe looked for the folder first).
        with gui.add_folder("Model", expand_by_default=getattr(self.pipeline.engine, "case", "a") == "b"):
            self.case_dropdown = gui.add_dropdown("Case", ("a", "b", "c"), initial_value="a")
            # Case (b) binds targets to the a-priori model by id: the operator names the next
            # click after a model point (the options follow the model loaded).
            self._model_ids: tuple[str, ...] = ()
            self._shown_case: str | None = None  # the case the last synced snapshot ran
            self._new_target = NEW_TARGET  # the "Next click is" option of a new target (new_target_option)
            self.model_point_dropdown = gui.add_dropdown("Next click is", (NEW_TARGET,), initial_value=NEW_TARGET)
            self.select_model_button = gui.add_button("Click the model points (simulator)")
            self.acquire_button = gui.add_button("Acquire model (object still)")
            self.model_path = gui.add_text("Model file", initial_value="")
            self.load_model_button = gui.add_button("Load model")
        with gui.add_folder("Output", expand_by_default=False):
            engine = self.pipeline.engine
            # The field's range is the filter's (a slow source takes less than the 2 Hz default,
            # which the filter clips), and viser refuses a start value outside the range.
            top = float(getattr(engine, "max_filter_cutoff_hz", 12.5))
            low = min(float(getattr(engine, "min_filter_cutoff_hz", 0.01)), top)  # the tracker's own range
            start = min(max(float(getattr(engine, "filter_cutoff_hz", 2.0)), low), top)
            self.cutoff_range_hz = (low, top)
            # Text, not viser's number field: that one dropped a pasted comma, and "0,5" (the
            # decimal point of much of Europe) reached the filter as 5 Hz. Read by decimal_of.
            self.cutoff = gui.add_text("Filter cutoff (Hz)", initial_value=_hz_text(start),
                                       hint=f"{_hz_text(low)} to {_hz_text(top)} Hz; 0.5 or 0,5")
        with gui.add_folder("Recording", expand_by_default=False):
            self.record_dir = gui.add_text("Folder", initial_value=shown_text(str(self.record_root / "recording")))
            self.record_checkbox = gui.add_checkbox("Record", initial_value=False)
            self.record_md = gui.add_markdown("")
        with gui.add_folder("View"):
            self.view_buttons = gui.add_button_group("Preset", ("image", "3D", "both"))
            self.right_checkbox = gui.add_checkbox("Show right image", initial_value=False)
        with gui.add_folder("Plots", expand_by_default=True):
            self.uplots = {name: add_plot(gui, title, labels) for name, (title, labels) in PLOTS.items()}
        # Last in the panel: its height follows the number of targets, which changes every few
        # frames, and nothing below it can move.
        with gui.add_folder("Target list"):
            self.targets_html = gui.add_html("")
        self.pause_button.on_click(self._cb(lambda e: SetPaused(not self.pipeline.latest().paused)))
        self.step_button.on_click(self._cb(lambda e: StepOnce()))
        self.restart_button.on_click(self._cb(lambda e: RestartSource()))
        self.clear_button.on_click(self._cb(lambda e: ClearTargets()))
        self.auto_checkbox.on_update(self._cb(lambda e: self._auto_command()))
        self.auto_count.on_update(self._typed("auto_count", lambda: self._typed_count_command()))
        self.auto_method.on_update(self._cb(lambda e: self._auto_command() if self.auto_checkbox.value else None))
        self.case_dropdown.on_update(self._cb(lambda e: SetCase(self.case_dropdown.value)))  # type: ignore[arg-type]
        self.model_point_dropdown.on_update(self._own_next_click)
        # The simulated operator: clicks every model point in view at its true projection, and again
        # whenever the pose has been invalid for a while (a source with ground truth only).
        self.select_model_button.on_click(self._cb(lambda e: SelectModelPoints(repeat=True)))
        self.acquire_button.on_click(self._cb(lambda e: AcquireModel()))
        self.load_model_button.on_click(self._cb(lambda e: LoadModel(self.model_path.value.strip())))
        self.cutoff.on_update(self._typed("cutoff", lambda: self._cutoff_command()))
        self.record_checkbox.on_update(self._cb(lambda e: self._record_command(e.client)))
        self.right_checkbox.on_update(lambda e: self._show_right_image(bool(self.right_checkbox.value)))
        self.view_buttons.on_click(lambda e: self._choose_view(e.client, str(self.view_buttons.value)) if e.client else None)

    def _typed(self, name: str, make: Any) -> Any:
        """A viser callback for a field the operator types into: remember that ``name`` was
        edited; :meth:`_send_settled_edits` sends ``make()`` (read then) once it stays."""

        def callback(event: Any) -> None:
            if getattr(event, "client", None) is None:
                return  # the publisher showing the tracker's value
            with self._pending_lock:
                self._edits[name] = (make, event.client, time.monotonic())

        self.edit_callbacks[name] = callback  # as viser calls it (tests type through it)
        return _on_event_loop(callback)

    def _send_settled_edits(self) -> None:
        now = time.monotonic()
        with self._pending_lock:
            settled = [(name, edit) for name, edit in self._edits.items() if now - edit[2] >= EDIT_SETTLE_S]
            for name, _ in settled:
                del self._edits[name]
        for name, (make, client, _) in settled:
            try:
                command = make()  # None: an emptied field, or a count with selection off
            except ValueError as exc:  # typed text that is no number: say so, show the tracker's
                self._show_tracker_value(name)
                command_name = next(c for c, widgets in _WIDGETS_OF_COMMAND.items() if name in widgets)
                self._notify(client, f"{_COMMAND_TITLES[command_name]}: refused", str(exc), False)
                continue
            if command is not None:
                self.submit(command, client, type(command).__name__)

    def _cutoff_command(self) -> Command | None:
        """The cutoff the operator typed (ValueError: no number); None for an emptied field,
        which then shows the tracker's cutoff again."""
        hz = decimal_of(self.cutoff.value)
        if hz is None:
            self._show_tracker_value("cutoff")
            return None
        return SetFilterCutoff(hz)

    def _auto_command(self) -> Command:
        """Automatic selection as the widgets show it; a Count that is no count (being typed,
        or refused) sends the tracker's."""
        try:
            count = whole_number_of(self.auto_count.value, 1, self.auto_count_max)
        except ValueError:
            count = None
        if count is None:
            count = max(int(self.pipeline.latest().auto_count), 1)
        return SetAuto(bool(self.auto_checkbox.value), count, str(self.auto_method.value))

    def _typed_count_command(self) -> Command | None:
        """The count the operator typed (ValueError: not a whole number in range); None for an
        emptied field, which then shows the tracker's count again, or with selection off (the
        count is sent when it is switched on)."""
        count = whole_number_of(self.auto_count.value, 1, self.auto_count_max)
        if count is None:
            self._show_tracker_value("auto_count")
            return None
        return self._auto_command() if self.auto_checkbox.value else None

    def _record_command(self, client: Any) -> Command | None:
        """Record as ticked: start in a fresh folder, or stop. A Folder that names no folder
        (:meth:`_fresh_record_dir`) is refused here with the reason, and the box unticked."""
        if not self.record_checkbox.value:
            return SetRecording(None)
        try:
            return SetRecording(self._fresh_record_dir())
        except ValueError as exc:
            self._show_tracker_value("record")
            self._notify(client, f"{_COMMAND_TITLES['SetRecording']}: refused", str(exc), False)
            return None

    def _fresh_record_dir(self) -> str:
        """The folder to record to, from the Folder field (ValueError: it names none)."""
        typed = typed_text(self.record_dir.value.strip())
        try:
            base = Path(typed or str(self.record_root / "recording")).expanduser()
        except RuntimeError:  # "~name/..." of no user here: it escaped the callback, unanswered
            home = typed.split("/", 1)[0]
            raise ValueError(f"{quoted_name(typed)}: the server finds no home folder for {quoted_name(home)}"
                             + (" (no such user there)" if home != "~" else "")) from None
        # Never mix two recordings in one folder: number it on when it already holds one (from
        # the number a numbered one has: the field shows the last recording, rec-2, and the
        # next is rec-3, not rec-2-2).
        numbered = re.fullmatch(r"(.+)-(\d+)", base.name)
        stem, n = (numbered.group(1), int(numbered.group(2))) if numbered else (base.name, 1)
        candidate = base
        try:
            while (candidate / "cam0" / "data.csv").exists():
                n += 1
                candidate = base.with_name(f"{stem}-{n}")
        except OSError:
            pass  # a name the file system refuses: the recorder refuses it, with the reason
        # Absolute: "runs/recording-2" in the answer said nothing of where the server runs.
        return str(candidate.absolute())

    def _cb(self, make: Any) -> Any:
        """A viser callback that submits ``make(event)`` (if not None) and remembers the reply.

        Programmatic value changes (``client is None``) are ignored: they come from the
        publisher syncing a widget to the snapshot, not from an operator.
        """

        def callback(event: Any) -> None:
            if getattr(event, "client", None) is None:
                return
            command = make(event)
            if command is not None:
                self.submit(command, event.client, type(command).__name__)

        return _on_event_loop(callback)

    def submit(self, command: Command, client: Any = None, label: str = "") -> Future[CommandReply]:
        """Send ``command`` to the pipeline; its reply becomes a notification for ``client``."""
        future = self.pipeline.submit(command)
        with self._pending_lock:
            self._pending.append((future, client, label or type(command).__name__))
        return future

    def _say_loop(self, source_pass: int) -> None:
        """Say once that the source loops, as every target goes with each new pass."""
        if source_pass <= 1:
            self._loop_said = False
        elif not self._loop_said:
            self._loop_said = True
            self._notify_all("Source", f"the source loops: it starts over (pass {source_pass}), and so does "
                             "tracking: targets, model points and pose", True)

    def _say_shortfall(self, snap: Snapshot) -> None:
        """Say whole, once, why automatic selection started no target: the targets line cuts
        it to two lines of the panel, and a phone has no hover for its title. Said again only
        after selection started a target or was switched off."""
        why = snap.auto_shortfall if snap.auto_enabled else None
        if why is None:
            self._shortfall_said = False
        elif not self._shortfall_said:
            self._shortfall_said = True
            self._notify_all("Automatic selection", f"started no target: {why}", False)

    def _say_views(self, frame: StereoFrame | None) -> None:
        """Say once, on the first frames that tell, that the left and right images look swapped
        (or are one image): every click would be refused, or matched at a made-up depth, with no
        word of why."""
        if frame is None or self._views_watch is None:
            return
        problem = self._views_watch.check(frame.left, frame.right)
        if problem:
            self._notify_all("Stereo pair", problem, False)

    def _on_click(self, event: Any) -> None:
        uv = self._event_pixel(event)
        if uv is not None:
            self._click_at(uv, event.client)

    def _click_at(self, uv: tuple[float, float], client: Any) -> Future[CommandReply]:
        """A target at left-image pixel ``uv``, named after the model point chosen in "Next
        click is"; the choice is used up when the target is made, and stays for the next click
        when the point is refused (refusals are common on a turning body)."""
        model_point = self.model_point_dropdown.value
        with self._pending_lock:
            owner = self._next_click_owner
        if model_point != self._new_target and None not in (owner, client) and client.client_id != owner:
            # The widget is every browser's, the choice one operator's: another's click, meant
            # as a new target, would bind an arbitrary pixel to that model point.
            return self.submit(SelectPoint(uv[0], uv[1]), client,
                               f"Target at {_pixel_text(uv)}, not {model_point}: another browser chose that "
                               "model point for its own next click")
        if model_point == self._new_target:
            return self.submit(SelectPoint(uv[0], uv[1]), client, f"Target at {_pixel_text(uv)}")
        future = self.submit(SelectPoint(uv[0], uv[1], model_point), client,
                             f"Model point {model_point} at {_pixel_text(uv)}")
        with self._pending_lock:  # used up by the publisher once the target is made (_flush_replies)
            self._model_point_clicks[future] = model_point
        return future

    def _on_right_click(self, event: Any) -> None:
        self._notify(getattr(event, "client", None), "Click on the right image",
                     "targets are set on the left image: click there (the right image shows each "
                     "target's match)", False)

    def _on_scene_click(self, event: Any) -> None:
        """A click anywhere in the scene (viser calls this after an image's own handler): in the
        image view, one that hit neither image fell on the blank margin and would go unanswered.
        In the 3D view a click on the background is part of looking around: no answer."""
        client = getattr(event, "client", None)
        if self._image_size is None or client is None:
            return
        with self._pending_lock:
            view = self._views.get(client.client_id)
        if view is None or view[1] != "image":
            return
        images = [self.left_image] + ([self.right_image] if self.right_image.visible else [])
        if any(ray_to_pixel(event.ray_origin, event.ray_direction, image.wxyz, image.position, self._image_size,
                            self.render_size) is not None for image in images):
            return  # the image's own handler answers
        self._notify(client, "Click beside the image", "targets are set on the left image: click on it", False)

    def _on_remove_click(self, event: Any) -> None:
        uv = self._event_pixel(event)
        if uv is None:
            return
        # Not judged against the last published frame: a click's target may not be made there
        # yet (the tracker a frame behind), and the remove that follows it would be refused.
        # The tracker has every command in order and answers "no target within 20 px" itself.
        self.submit(RemoveNearest(uv[0], uv[1], exclude=tuple(self._hidden_ids)), event.client,
                    f"Remove target near {_pixel_text(uv)}")

    def _event_pixel(self, event: Any) -> tuple[float, float] | None:
        if self._image_size is None:
            return None
        return ray_to_pixel(event.ray_origin, event.ray_direction, self.left_image.wxyz, self.left_image.position,
                            self._image_size, self.render_size)

    def _notify_all(self, title: str, body: str, ok: bool) -> None:
        """:meth:`_notify` every browser connected (kept in :attr:`notifications` with none)."""
        clients: list[viser.ClientHandle | None] = list(self.server.get_clients().values())
        for client in clients or [None]:
            self._notify(client, title, body, ok)

    def _notify(self, client: Any, title: str, body: str, ok: bool) -> None:
        """Answer ``client`` with a pop-up, which replaces the one it showed before: pop-ups
        stack from the view's top-left corner, and a stack of them (quick clicks, several
        refused) would cover the image there and catch the clicks meant for it."""
        self.notifications.append((title, body))
        if client is None:
            return
        seconds = POPUP_OK_S if ok else POPUP_REFUSED_S
        try:
            shown = client.add_notification(shown_text(title), shown_text(body), auto_close_seconds=seconds,
                                            color="green" if ok else "red")
        except Exception as exc:  # the browser went away
            log.debug("notification not sent: %s", exc)
            return
        with self._pending_lock:
            before = self._popups.get(client.client_id)
            # Not for a browser gone since (its answer came after it closed): _on_disconnect
            # dropped its entry already, and one kept now stayed for good, one per such browser.
            if client.client_id in self._views:
                self._popups[client.client_id] = shown
                self._popup_close_at[client.client_id] = time.monotonic() + seconds + POPUP_GRACE_S
        if before is not None:
            with contextlib.suppress(Exception):  # closed already, or the browser went away
                before.remove()

    def _close_stale_popups(self) -> None:
        """Close the pop-ups past their time from here: the browser's own timer stops while the
        pointer rests on one (Mantine's notifications), and a pointer at the image's top-left,
        where they stack, kept a refusal over the image, catching the clicks meant for it, for
        as long as it stayed (an outside console probe)."""
        now = time.monotonic()
        with self._pending_lock:
            stale = [cid for cid, at in self._popup_close_at.items() if at <= now]
            closing = [self._popups.pop(cid, None) for cid in stale]
            for cid in stale:
                del self._popup_close_at[cid]
        for popup in closing:
            if popup is not None:
                with contextlib.suppress(Exception):  # closed already, or the browser went away
                    popup.remove()

    # ------------------------------------------------------------------ clients and views
    def _on_connect(self, client: viser.ClientHandle) -> None:
        # Framing needs the browser's canvas aspect, which settles after the page's layout
        # (the docked panel); the publisher re-frames the image preset when it changes.
        with self._pending_lock:
            self._views[client.client_id] = [client, "image", None]

    def _on_disconnect(self, client: viser.ClientHandle) -> None:
        with self._pending_lock:
            self._views.pop(client.client_id, None)
            self._popups.pop(client.client_id, None)
            self._popup_close_at.pop(client.client_id, None)
            gone_owner = self._next_click_owner == client.client_id
        if gone_owner:  # its click will not come: the others' clicks are new targets again
            self.model_point_dropdown.value = self._new_target  # type: ignore[misc]  # viser 1.1's setter: see _flush_replies

    def _own_next_click(self, event: Any) -> None:
        """The model point chosen in "Next click is" belongs to the browser that chose it (None:
        set by the console itself, e.g. used up or reset; any click may use it then)."""
        client = getattr(event, "client", None)
        with self._pending_lock:
            self._next_click_owner = (client.client_id if client is not None
                                      and self.model_point_dropdown.value != self._new_target else None)

    def _frame_clients(self) -> None:
        with self._pending_lock:
            views = list(self._views.values())
        for view in views:
            client, preset, framed_aspect = view
            try:
                aspect = float(client.camera.aspect)
            except Exception:  # no camera message yet, or gone
                continue
            if preset == "image" and (framed_aspect is None or abs(aspect - framed_aspect) > 1e-3):
                view[2] = aspect
                try:
                    self._apply_view(client, "image")
                except Exception as exc:
                    log.debug("client view not set: %s", exc)

    def _show_right_image(self, shown: bool) -> None:
        """Show or hide the right image; the views on the image preset are framed again (by
        the publisher, :meth:`_frame_clients`) to hold it, or the left image alone."""
        self.right_image.visible = shown
        self._repush.set()  # it is drawn by _push only: paused, it stayed black or stale
        with self._pending_lock:
            for view in self._views.values():
                if view[1] == "image":
                    view[2] = None

    def _choose_view(self, client: Any, preset: str) -> None:
        with self._pending_lock:
            view = self._views.get(client.client_id)
            if view is not None:
                view[1], view[2] = preset, None
        self._apply_view(client, preset)

    def _apply_view(self, client: Any, preset: str) -> None:
        rw, rh = self.render_size
        fov = np.radians(50.0)
        up = (0.0, -1.0, 0.0)
        try:
            aspect = float(client.camera.aspect)
        except (AssertionError, ZeroDivisionError):
            aspect = 16 / 9
        band = view_band(aspect)  # on a phone held upright its control sheet covers the view's bottom
        # The 3D and both presets are placed for a wide view; one narrower than tall (a phone, or
        # a desktop window's view beside the panel) is fitted to them, within the band on a phone.
        fit = aspect < 1.0
        right_x = float(self.right_image.position[0]) if self.right_image.visible else None
        with client.atomic():
            client.camera.up_direction = up
            client.camera.fov = fov
            if preset == "3D":
                ox, oy, oz = SCENE3D_OFFSET
                position, look_at = (ox - 1.2, oy - 1.0, oz - 1.5), (ox, oy, oz + 3.5)
                if fit:
                    position, look_at = view_in_band(position, look_at, up, aspect, fov, band)
            elif preset == "both":
                # The rig's scene (satellite ~3.5 m ahead, so near z = 0.5 here) left of the image.
                left = SCENE3D_OFFSET[0] - 1.5
                mid = (left + rw / 2) / 2
                position, look_at = (mid, 0.0, -14.5), (mid, 0.0, 0.0)
                if fit:  # the scene and the image(s) fitted into the view (band), as the image preset does
                    right = (right_x if right_x is not None else 0.0) + rw / 2
                    position, look_at = image_view((right - left, rh), aspect, fov, ((left + right) / 2, 0.0), band)
            else:
                span, centre = self.render_size, (0.0, 0.0)
                if right_x is not None:  # both images, side by side
                    span, centre = (right_x + rw, rh), (right_x / 2, 0.0)
                position, look_at = image_view(span, aspect, fov, centre, band)
            client.camera.position, client.camera.look_at = position, look_at

    # ------------------------------------------------------------------ snapshots
    def _on_snapshot(self, snap: Snapshot) -> None:
        # Tracking thread: only cheap appends.
        self.plots.add(snap)

    def _publish_loop(self) -> None:
        """Push the newest snapshot at ``publish_hz``; a change of the target set (a click, a
        removal) is pushed at once, so the operator sees the answer without waiting a tick (the
        operator's boxes are scene nodes over the image, :meth:`_update_operator_overlay`: they
        show in the browser's next frame, not after a new image has loaded).

        ``publish_hz`` is read at every push, so it can be changed while running."""
        last_seq = -1
        last_text_seq = -1  # the snapshot whose numbers the page shows
        tick = 0
        last_push = 0.0
        next_trim = time.monotonic() + TRIM_EVERY_S
        while not self._stop.is_set():
            period = 1.0 / self.publish_hz
            try:
                snap = self.pipeline.wait_snapshot(last_seq, min(period, 0.1))
                self._flush_replies()
                self._close_stale_popups()
                self._send_settled_edits()
                self._frame_clients()
                if snap is None and self._repush.is_set() and last_seq >= 0:
                    # Paused or ended: the page shows again what changed on the console's side
                    # (_push redraws the same frame; trails and plots add nothing for it).
                    snap = self.pipeline.latest()
                if snap is not None:  # this push shows it
                    self._repush.clear()
                if snap is None:
                    if last_seq >= 0 and last_text_seq != last_seq:
                        # The stream went quiet (paused, ended, failed) right after a push that
                        # skipped the text: show its last state, or the page keeps an older one.
                        quiet = self.pipeline.latest()
                        self._push(quiet, plots=True, text=True)
                        last_seq = last_text_seq = quiet.sequence
                    continue
                # Only the operator's own targets make a push urgent (automatic ones churn).
                operator_ids = {t.id for t in snap.targets if t.origin == "operator"}
                urgent = operator_ids != self._pushed_operator_ids
                wait = last_push + period - time.monotonic()
                if wait > 0 and not urgent:
                    if self._stop.wait(wait):
                        break
                    snap = self.pipeline.latest()
                last_seq = snap.sequence
                last_push = time.monotonic()
                t0 = time.perf_counter()
                text = urgent or tick % self.text_every == 0
                self._push(snap, plots=(tick % self.plot_every == 0), text=text)
                if text:
                    last_text_seq = snap.sequence
                self.push_ms.append((time.perf_counter() - t0) * 1e3)
                tick += 1
                if last_push >= next_trim:
                    next_trim = last_push + TRIM_EVERY_S
                    release_free_heap()
            except Exception:
                log.exception("console publish failed")
                self._stop.wait(period)

    def _flush_replies(self) -> None:
        done: list[tuple[Future[CommandReply], Any, str]] = []
        with self._pending_lock:
            keep: deque[tuple[Future[CommandReply], Any, str]] = deque()
            for item in self._pending:
                (done if item[0].done() else keep).append(item)
            self._pending = keep
        for future, client, label in done:
            try:
                reply = future.result(0)
            except Exception as exc:
                reply = CommandReply(False, f"{type(exc).__name__}: {exc}")
            with self._pending_lock:
                model_point = self._model_point_clicks.pop(future, None)
            if reply.ok and model_point is not None and self.model_point_dropdown.value == model_point:
                # viser 1.1 defines the value setter apart from its getter, and mypy takes the property as read-only.
                self.model_point_dropdown.value = self._new_target  # type: ignore[misc]  # the choice is used up; a refusal keeps it
            if reply.ok and not reply.notable and label.startswith(("SetAuto", "SetFilterCutoff", "SetPaused",
                                                                    "StepOnce")):
                continue  # the UI shows the new state; no pop-up needed
            if not reply.ok:  # the widget the operator changed shows the tracker's state again
                for name in _WIDGETS_OF_COMMAND.get(label, ()):
                    self._show_tracker_value(name)
            title = _COMMAND_TITLES.get(label, label)
            title = title if reply.ok else f"{title}: {'partly done' if reply.partial else 'refused'}"
            self._notify(client, title, reply.message or ("ok" if reply.ok else "refused"), reply.ok)

    def _push(self, snap: Snapshot, plots: bool, text: bool = True) -> None:
        frame = snap.frame
        self._say_loop(snap.source_pass)
        self._say_shortfall(snap)
        if snap.sequence != self._views_seen_sequence:  # a snapshot pushed again is no new frame to look at
            self._views_seen_sequence = snap.sequence
            self._say_views(frame)
        left_rgb = right_rgb = None
        drawn = self._lost_targets.shown(snap.targets, frame.t_s) if frame is not None else list(snap.targets)
        self._hidden_ids = frozenset(t.id for t in snap.targets) - {t.id for t in drawn}
        if frame is not None:
            self._trails.update(snap.targets, frame.index, snap.source_pass, frame.cut)
            left_rgb = draw_overlays(to_rgb(frame.left), drawn, self._trails.points, self.patch_px,
                                     operator_boxes=False)
            if self.right_image.visible:
                right_rgb = draw_matches(to_rgb(frame.right), snap.targets, self.patch_px)
        status_text = self._status_html(snap) if text else None
        targets_text = self._targets_html(snap) if text else None
        rec = self.pipeline.recording_stats()
        with self.server.atomic():
            if left_rgb is not None:
                if frame is not None and (frame.left.shape[1], frame.left.shape[0]) != self._image_size:
                    self._image_size = (frame.left.shape[1], frame.left.shape[0])
                    self.left_image.render_width, self.left_image.render_height = self.render_size
                    self.right_image.render_width, self.right_image.render_height = self.render_size
                self.left_image.image = left_rgb
                if right_rgb is not None:
                    self.right_image.image = right_rgb
            self._update_operator_overlay(drawn)
            if status_text is not None and targets_text is not None:
                self.status_html.content = shown_text(status_text)
                self.targets_html.content = shown_text(targets_text)
            self.record_md.content = shown_text(self._recording_text(rec))
            if rec.active and rec.directory != self._record_dir_shown:
                # The folder of the recording going on (--record's, another browser's): the
                # field kept its default and read as where the frames went.
                self._record_dir_shown = rec.directory
                assert rec.directory is not None  # an active recording's folder (RecordingStats)
                self.record_dir.value = shown_text(rec.directory)  # type: ignore[misc]  # viser 1.1's setter
            self._sync_widgets(snap)
            self._update_scene3d(snap)
            if plots:
                for name, window in self.plots.windows.items():
                    if self._plot_version.get(name) != window.version and len(window) >= 2:
                        self._plot_version[name] = window.version
                        set_uplot_data(self.uplots[name], uplot_data(window.arrays()))
        self._pushed_operator_ids = {t.id for t in snap.targets if t.origin == "operator"}
        if left_rgb is None:
            return
        # The last_push* fields describe the last pushed IMAGE (what the browser can show).
        self.images_pushed += 1
        self.last_pushed_sequence = snap.sequence
        self.last_pushed_target_ids = tuple(t.id for t in snap.targets)
        self.image_pushes.append((time.monotonic(), self.last_pushed_target_ids))
        self.last_pushed_time = time.monotonic()
        # One assignment, so a reader never pairs these ids with an older push time.
        self.last_push = (self.last_pushed_time, snap.sequence, self.last_pushed_target_ids)

    def _update_operator_overlay(self, targets: Sequence[TargetState]) -> None:
        """The operator's ``targets`` as boxes (status colour) and ``id*`` labels over the left image."""
        if self._image_size is not None:
            self.operator_marks.update([t for t in targets if t.origin == "operator"], self._image_size,
                                       self.render_size)

    def _sync_widgets(self, snap: Snapshot) -> None:
        if snap.model_ids != self._model_ids:  # a model loaded (or dropped): its points to name clicks by
            self._model_ids = snap.model_ids
            self._new_target = new_target_option(snap.model_ids)
            self.model_point_dropdown.options = (self._new_target, *snap.model_ids)  # ids are text (load_model)
            self.model_point_dropdown.value = self._new_target  # type: ignore[misc]  # viser 1.1's setter
        if snap.pose.case != self._shown_case:
            # A choice made for another case's model (or none: case (c) makes its own) would
            # name the next plain click after it, long after it was meant.
            if self._shown_case is not None and self.model_point_dropdown.value != self._new_target:
                self.model_point_dropdown.value = self._new_target  # type: ignore[misc]  # viser 1.1's setter
            self._shown_case = snap.pose.case
        label = "Play" if snap.paused else "Pause"
        if self.pause_button.label != label:
            self.pause_button.label = label
        self._mirror("auto", self.auto_checkbox, snap.auto_enabled)
        if snap.auto_count >= 1 and "auto_count" not in self._edits:
            self._mirror("auto_count", self.auto_count, str(snap.auto_count))
        if snap.auto_method in self.auto_method.options:
            self._mirror("auto_method", self.auto_method, snap.auto_method)
        if np.isfinite(snap.filter_cutoff_hz) and "cutoff" not in self._edits:
            # As the filter takes it (clipped to its range); not while the operator's value waits
            # to settle (:meth:`_send_settled_edits`): the field keeps what they typed.
            low, top = self.cutoff_range_hz
            self._mirror("cutoff", self.cutoff, _hz_text(min(max(snap.filter_cutoff_hz, low), top)))
        self._mirror("record", self.record_checkbox, snap.recording)
        if snap.pose.case in ("a", "b", "c"):
            self._mirror("case", self.case_dropdown, snap.pose.case)

    def _show_tracker_value(self, name: str) -> None:
        """Have widget ``name`` show the tracker's state again at the next push (what the
        operator typed or ticked was refused, or emptied). Paused, or with the source ended, no
        new snapshot comes: the latest is pushed again (:attr:`_repush`), or the field kept the
        refused text."""
        self._mirrored.pop(name, None)
        self._repush.set()

    def _mirror(self, name: str, widget: Any, state: Any) -> None:
        """Show the tracker's ``state`` on ``widget`` when it changed since last shown here.

        Edge-triggered on purpose. viser stores a browser's new value on the widget before it
        runs the ``on_update`` callback in a worker thread; a push that reset every widget to
        the tracker's state put the old value back in between, and the callback then read it
        and sent it as the command (CI: a click on "Automatic selection" sent "off"). A
        change made elsewhere (another browser, ``--auto``, a recording that failed) still
        shows, and a refused command shows the state again (:meth:`_flush_replies`).
        """
        if name in self._mirrored and self._mirrored[name] == state:
            return
        self._mirrored[name] = state
        if widget.value != state:
            widget.value = state

    @staticmethod
    def _status_html(snap: Snapshot) -> str:
        """The live numbers as HTML in a box of fixed height (:data:`STATUS_HEIGHT_EM`).

        Its height must not follow the content: a panel that grows when the pose becomes valid
        or a line wraps moves the buttons below under the operator's cursor, and a browser's
        click never finds them still. Every state fills the same rows, a dash where there is
        nothing to say; a long reason scrolls inside the box.

        After a restart of the source the share dropped counts from it, the total beside it.
        """
        t = snap.timings
        n_track = sum(1 for x in snap.targets if x.measured)
        n_lost = sum(1 for x in snap.targets if not x.measured)
        counts_from = t.counts_at_restart
        read0, dropped0 = counts_from or (0, 0)
        read, dropped = t.frames_read - read0, t.frames_dropped - dropped0
        dropped_pct = 100.0 * dropped / read if read > 0 else 0.0
        dropped_line = f"dropped {dropped} ({dropped_pct:.1f} %)"
        if counts_from is not None:
            dropped_line += f" since Restart · {t.frames_dropped} in all"
        # Ended or failed, no frame comes and no snapshot lowers the last rates: they are not
        # shown as if still true, nor the state as "running" (an outside console probe).
        stopped = snap.source_status is not None and not snap.paused
        ended = snap.source_status == "ended"
        state = "paused" if snap.paused else ("ended" if ended else "source stopped") if stopped else "running"
        status = snap.source_status_text
        source = (f"<b>{escape(status)}</b>" if status
                  else "source held: no frame is read while paused" if snap.paused
                  else "source delivering" + (f" · pass {snap.source_pass} (it loops; tracking starts over "
                                              "each pass)" if snap.source_pass > 1 else ""))
        if snap.source_warning:
            source += f" · <b>{escape(snap.source_warning)}</b>"
        lines = [f"<b>{state}</b> · frame {snap.frame.index if snap.frame else '-'} · auto "
                 f"{'on' if snap.auto_enabled else 'off'}" + (" · <b>● REC</b>" if snap.recording else ""),
                 source,
                 # paused, no frame moves and no snapshot comes to lower the last rates
                 "read – · tracking – (paused)" if snap.paused else
                 f"read – · tracking – ({'ended' if ended else 'source stopped'})" if stopped else
                 f"read {t.acquisition_hz:.1f} Hz · tracking {t.tracking_hz:.1f} Hz",
                 f"latency {t.latency_ms:.0f} ms · step {t.step_ms:.0f} ms",
                 dropped_line,
                 f"targets: <b>{n_track} tracking</b>, {n_lost} lost" + (
                     f" · auto started none: {escape(snap.auto_shortfall)}"
                     if snap.auto_enabled and snap.auto_shortfall else "")]
        pose = snap.pose
        rows: dict[str, Any] = dict.fromkeys(("p [m]", "rotvec [°]", "v [mm/s]", "ω [°/s]", "error [mm]"))
        if pose.valid:
            T = np.asarray(pose.T_cam_body)
            if pose.coasting_s > 0.0:
                lines.append(f"pose valid, <b>COASTING</b> (case {pose.case}{_sigma_text(pose.cov_pose)}): "
                             f"{escape(str(pose.reason))}")
            else:
                lines.append(f"pose valid (case {pose.case}, {pose.n_points} points{_sigma_text(pose.cov_pose)})")
            rows["p [m]"] = (T[:3, 3], "{:+.3f}")
            rows["rotvec [°]"] = (np.degrees(Rotation.from_matrix(T[:3, :3]).as_rotvec()), "{:+.1f}")
            rows["v [mm/s]"] = (np.asarray(pose.velocity_cam_m_s) * 1e3, "{:+.1f}")
            rows["ω [°/s]"] = (np.degrees(pose.omega_body_rad_s), "{:+.2f}")
        else:
            reason = str(pose.reason)
            if reason.endswith(MODEL_NOT_TARGETED):
                # The controls that do it sit in a folder closed at start: named first, where the
                # box's three lines show them (the count of points located is 0 here anyway).
                reason = ("case (b), no model point targeted: under Model, pick one in 'Next click is' and "
                          "click it, or 'Click the model points (simulator)'")
            lines.append(f"pose invalid: {escape(reason)}")
        e = snap.errors
        attitude_error = "–"
        if e and "position_m" in e:
            rows["error [mm]"] = (np.asarray(e["position_m"]) * 1e3, "{:+.1f}")
            attitude_error = f"{np.degrees(float(e.get('attitude_total_rad', np.nan))):.2f}°"
        cell = 'style="text-align:right;padding:0 0.4em"'
        table = [f"<tr><td></td>{''.join(f'<td {cell}>{a}</td>' for a in 'xyz')}</tr>"]
        for name, value in rows.items():
            texts = (["–"] * 3 if value is None or not np.all(np.isfinite(value[0]))
                     else [value[1].format(x) for x in value[0]])
            table.append(f"<tr><td>{name}</td>{''.join(f'<td {cell}>{x}</td>' for x in texts)}</tr>")

        def clamped(html: str, kind: str) -> str:
            text = re.sub(r"<[^>]+>", "", html)  # the title attribute's plain text (escaped already)
            return (f'<div style="display:-webkit-box;-webkit-box-orient:vertical;overflow:hidden;'
                    f'-webkit-line-clamp:{STATUS_CLAMP_LINES[kind]}" title="{text}">{html}</div>')

        kinds = {1: "source", len(lines) - 2: "targets", len(lines) - 1: "pose"}
        blocks = [clamped(line, kinds[i]) if i in kinds else f"<div>{line}</div>" for i, line in enumerate(lines)]
        return (f'<div style="height:{STATUS_HEIGHT_EM}em;overflow-y:auto;font-size:0.875rem;'
                f'line-height:1.45;padding:0 0.75rem">' + "".join(blocks)
                + '<table style="border-collapse:collapse;font-variant-numeric:tabular-nums">'
                + "".join(table) + f"</table>attitude error: {attitude_error}</div>")

    @staticmethod
    def _recording_text(rec: RecordingStats) -> str:
        """The Recording folder's line: the recording going on, or that none is and the last one's counts."""
        if not rec.directory:
            return "not recording"
        if rec.discarded:
            return f"not recording (last: no frame came, nothing kept in {rec.directory})"
        n = rec.image_bytes_written
        size = "" if not n else f" ({n / 1e6:.0f} MB)" if n < 1e9 else f" ({n / 1e9:.1f} GB)"
        counts = (f"{rec.directory}: {counted(rec.frames_written, 'frame')} written{size}, "
                  f"{rec.frames_dropped + rec.frames_lost} not recorded" + (f", {rec.error}" if rec.error else ""))
        if not rec.active and rec.queue_depth > 0 and rec.error is None:  # stopped: what it queued is written on
            return f"stopped, writing the {counted(rec.queue_depth, 'frame')} still queued ({counts})"
        return counts if rec.active else f"not recording (last: {counts})"

    @staticmethod
    def _targets_html(snap: Snapshot) -> str:
        """The target list as an HTML table of fixed column widths, each cell one line cut with
        an ellipsis (its whole text on hover). Why not markdown: viser's markdown table has no
        cell padding, so columns ran together ("wing_south_c2operator"), its z column crossed
        the folder's border, and a lost target's reason wrapped to five lines a row, making 30
        targets several screens long (an outside console probe)."""
        if not snap.targets:
            return '<div style="padding:0 0.75rem"><i>no targets</i></div>'
        cell = "padding:1px 4px;overflow:hidden;text-overflow:ellipsis;white-space:nowrap"
        widths = {"id": 22, "by": 14, "status": 24, "u, v": 27, "z [m]": 13}
        head = "".join(f'<th style="{cell};width:{w}%;text-align:left">{name}</th>' for name, w in widths.items())
        rows = [f"<tr>{head}</tr>"]
        for t in snap.targets[:TARGET_LIST_ROWS]:
            z = f"{t.point_cam[2]:.3f}" if t.measured and np.isfinite(t.point_cam[2]) else "-"
            status = t.status if t.status != "lost" else f"lost ({t.lost_reason or '?'})"
            # Re-made through the pose: a point of the a-priori model, or one that joined the
            # model (grown, acquired, a provisional frame's): "model" for both read, beside "no
            # model point targeted", as if the a-priori model were bound.
            by = "grown" if t.origin == "model" and t.id not in snap.model_ids else t.origin
            texts = (t.id, by, status, f"{t.uv[0]:.1f}, {t.uv[1]:.1f}", z)
            rows.append("<tr>" + "".join(f'<td style="{cell}" title="{escape(x)}">{escape(x)}</td>' for x in texts)
                        + "</tr>")
        if len(snap.targets) > TARGET_LIST_ROWS:
            rows.append(f'<tr><td colspan="5" style="{cell}">… {len(snap.targets) - TARGET_LIST_ROWS} more</td></tr>')
        return ('<table style="table-layout:fixed;width:100%;border-collapse:collapse;font-size:0.8rem;'
                'font-variant-numeric:tabular-nums">' + "".join(rows) + "</table>")

