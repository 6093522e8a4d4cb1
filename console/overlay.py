"""Pure helpers of the console: click ray → image pixel, overlays drawn into the image.

No viser here, so the geometry is tested without a browser.

The left image is a viser scene image: a plane of ``render_w`` x ``render_h`` scene units
centred on its node, the image's top-left corner at local (-render_w/2, -render_h/2), local +x
along image columns (u), local +y along image rows (v), seen from local -z (DESIGN.md
section 8). With the pixel-centre convention ((0, 0) is the CENTRE of the top-left pixel, DESIGN.md
section 3), a pixel (u, v) of a W x H image sits at local::

    x = (u + 0.5) * render_w / W - render_w / 2,    y = (v + 0.5) * render_h / H - render_h / 2
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Mapping, Sequence
from functools import lru_cache
from typing import cast

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from trackmeter.core.targets import TargetState

#: RGB colour of each target status (drawn into an RGB image).
STATUS_RGB: dict[str, tuple[int, int, int]] = {
    "tracking": (60, 230, 60),
    "lost": (255, 60, 60),
    "recovered": (255, 200, 0),
}
SEARCH_RGB = (90, 140, 255)
PREDICTED_RGB = (255, 80, 255)
TRAIL_RGB = (0, 220, 255)


#: How long a lost target stays drawn at its last good pixel, s of frame time: long enough to
#: see where it was lost (and a re-lock a few frames later), short enough that a mark does not
#: sit on a part of the image the tumbling body has long turned away from.
LOST_SHOWN_S = 1.5


class LostTargets:
    """Which targets to draw: the measured ones, and a lost one for :data:`LOST_SHOWN_S` of frame
    time after it was lost (its ``uv`` is the last good pixel; the targets table still lists it).

    Frame time, not the wall clock: a paused console keeps its marks. A frame time earlier than a
    loss (the source restarted) counts the loss from that frame.
    """

    def __init__(self, shown_s: float = LOST_SHOWN_S) -> None:
        self.shown_s = shown_s
        self.since: dict[str, float] = {}  # target id -> frame time it was first seen lost

    def shown(self, targets: Sequence[TargetState], t_s: float) -> list[TargetState]:
        """The ``targets`` of the frame at ``t_s`` (s) to draw, in their order."""
        since = {}
        for t in targets:
            if t.status == "lost":
                first = self.since.get(t.id, t_s)
                since[t.id] = first if first <= t_s else t_s
        self.since = since
        return [t for t in targets if t.status != "lost" or t_s - since[t.id] <= self.shown_s]


#: Pixels a target's trail keeps (the console's frames, newest last).
TRAIL_FRAMES = 12


class Trails:
    """Each target's last pixels (:data:`TRAIL_FRAMES` published frames), for its trail.

    A trail joins the pixels of one stretch of tracking only. It starts over after the target was
    seen lost (the trail stays drawn with the lost mark until then) or re-locked ("recovered":
    the re-lock may land far from the loss), when a target of the same id is younger than its
    trail (made again: after a Restart the simulator's operator picks the model points again
    under their ids), and for every target when the stream jumps: a cut, a looping source's next
    pass, frame numbers going back. One frame published twice adds its pixel once.
    """

    def __init__(self, length: int = TRAIL_FRAMES) -> None:
        self.length = length
        self.points: dict[str, deque[tuple[float, float]]] = {}
        self._age: dict[str, int] = {}  # target id -> its age_frames when last added to
        self._broken: set[str] = set()  # seen lost since their last pixel
        self._frame_index: int | None = None
        self._source_pass: int | None = None

    def update(self, targets: Sequence[TargetState], frame_index: int, source_pass: int = 1,
               cut: bool = False) -> None:
        """Add the pixels of ``targets`` after the step of frame ``frame_index``."""
        last_index, last_pass = self._frame_index, self._source_pass
        if cut or (last_pass is not None and source_pass != last_pass) or (
                last_index is not None and frame_index < last_index):
            self.points.clear()
            self._age.clear()
            self._broken.clear()
        new_frame = cut or frame_index != last_index or source_pass != last_pass
        self._frame_index, self._source_pass = frame_index, source_pass
        alive = {t.id for t in targets}
        for tid in [tid for tid in self.points if tid not in alive]:
            del self.points[tid]
            self._age.pop(tid, None)
        self._broken &= alive
        for t in targets:
            if t.status == "lost" or not np.all(np.isfinite(t.uv)):
                if t.id in self.points:
                    self._broken.add(t.id)
                continue
            if not new_frame and t.id in self.points:
                continue
            if (t.id in self._broken or t.status == "recovered"
                    or t.age_frames < self._age.get(t.id, t.age_frames)):
                self.points.pop(t.id, None)
                self._broken.discard(t.id)
            trail = self.points.setdefault(t.id, deque(maxlen=self.length))
            trail.append((float(t.uv[0]), float(t.uv[1])))
            self._age[t.id] = t.age_frames


# three.js's ACES filmic tone mapping (the fit in its shader chunk tonemapping_pars_fragment,
# after Stephen Hill's RRT + ODT fit), which viser's client applies to every scene node but images.
_ACES_IN = np.array([[0.59719, 0.35458, 0.04823], [0.07600, 0.90834, 0.01566], [0.02840, 0.13383, 0.83777]])
_ACES_OUT = np.array([[1.60475, -0.53108, -0.07367], [-0.10208, 1.10813, -0.00605], [-0.00327, -0.07276, 1.07602]])


def displayed_rgb(node_rgb: ArrayLike) -> NDArray[np.float64]:
    """(3,) the sRGB colour (0-255) on screen of a scene node given the colour ``node_rgb``
    (0-255): viser's client takes it as linear, tone-maps it (ACES filmic, exposure 1) and
    encodes sRGB. E.g. (60, 230, 60) shows as (179, 223, 165), as read off headless Chromium."""
    c = np.asarray(node_rgb, dtype=float) / 255.0 / 0.6
    v = _ACES_IN @ c
    v = (v * (v + 0.0245786) - 0.000090537) / (v * (0.983729 * v + 0.4329510) + 0.238081)
    lin = np.clip(_ACES_OUT @ v, 0.0, 1.0)
    return 255.0 * np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * lin ** (1 / 2.4) - 0.055)


@lru_cache(maxsize=64)
def node_rgb_for(rgb: tuple[int, int, int]) -> tuple[int, int, int]:
    """The colour to give a scene node so that it shows as ``rgb`` (0-255, sRGB), or as close as
    the tone mapping reaches (least squares over the node colour): the operator's boxes drawn
    as nodes then match the status colours drawn into the image (:data:`STATUS_RGB`)."""
    from scipy.optimize import least_squares

    target = np.asarray(rgb, dtype=float)
    fit = least_squares(lambda x: (displayed_rgb(x) - target) / 255.0, np.full(3, 128.0), bounds=(0.0, 255.0))
    return tuple(int(round(float(x))) for x in fit.x)  # type: ignore[return-value]


def pixel_to_plane(uv: ArrayLike, image_size: tuple[int, int], render_size: tuple[float, float]) -> NDArray[np.float64]:
    """(N,2) pixels (u, v) → (N,2) plane-local (x, y), scene units (see the module docstring)."""
    w, h = image_size
    rw, rh = render_size
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    return np.stack([(uv[:, 0] + 0.5) * rw / w - rw / 2, (uv[:, 1] + 0.5) * rh / h - rh / 2], axis=1)


def box_segments(
    uv: ArrayLike, half_px: float, image_size: tuple[int, int], render_size: tuple[float, float], z: float
) -> NDArray[np.float32]:
    """(N*4,2,3) line segments of square boxes around pixels ``uv`` (N,2), in the image plane's
    local frame (see the module docstring) at height ``z`` (negative: in front of the image).

    Each box has corners ``uv ± half_px`` (pixels) and its four edges in the order top, right,
    bottom, left.
    """
    c = np.asarray(uv, dtype=float).reshape(-1, 2)
    h = float(half_px)
    corners = np.stack([c + (-h, -h), c + (h, -h), c + (h, h), c + (-h, h)], axis=1)  # (N,4,2)
    xy = pixel_to_plane(corners.reshape(-1, 2), image_size, render_size).reshape(-1, 4, 2)
    ends = np.stack([xy, np.roll(xy, -1, axis=1)], axis=2).reshape(-1, 2, 2)  # (N*4, 2, 2)
    return np.concatenate([ends, np.full((len(ends), 2, 1), z)], axis=2).astype(np.float32)


#: Of the view the image preset leaves around the image, at least this fraction of the image's
#: half-extent on the axis that limits it.
VIEW_MARGIN = 0.04

#: A view narrower than it is tall frames the image in this top fraction of its height: on a
#: phone (viser's mobile layout, under 576 CSS px wide) the control panel is a sheet over the
#: bottom of the view, up to 60 % of its height, and an image framed at the bottom lay under it.
PORTRAIT_BAND = 0.4

#: Views narrower than this (width / height) are taken for a phone held upright, framed in
#: :data:`PORTRAIT_BAND`. The page does not tell the console its CSS width, only the canvas's
#: pixels (times a device pixel ratio that viser also varies with the frame rate), so the shape
#: decides: a phone's view is under 0.56 (a 9:16 screen; 0.46 at 9:19.5, less the browser's
#: bars), while a desktop window's view beside the docked panel is rarely so narrow (1024x768:
#: 0.91) and was squeezed into the band, 60 % of it left empty. A small desktop window under
#: 576 CSS px wide gets viser's sheet with a wider view; the sheet folds away there.
PHONE_ASPECT = 0.62


def view_band(aspect: float) -> float:
    """The top fraction of a view of ``aspect`` (width / height) to frame in: :data:`PORTRAIT_BAND`
    on a phone held upright (:data:`PHONE_ASPECT`), else all of it."""
    return PORTRAIT_BAND if aspect < PHONE_ASPECT else 1.0


def image_view(render_size: tuple[float, float], aspect: float, fov_y_rad: float,
               centre: tuple[float, float] = (0.0, 0.0), band: float = 1.0) -> tuple[
        tuple[float, float, float], tuple[float, float, float]]:
    """The browser camera's ``(position, look_at)`` that shows the whole left image (centred
    on the scene origin, facing -z; see the module docstring), or any rectangle of
    ``render_size`` centred on ``centre`` in the plane z = 0 (both images side by side), in a
    view of ``aspect`` (width / height) and vertical field of view ``fov_y_rad``, with up
    along -y.

    The image fills the view along the axis that limits it, leaving :data:`VIEW_MARGIN`; the
    room left over on the other axis is put above and to the left of the image, not split
    around it: the browser's pop-ups (a click's answer) stack from the view's top-left corner
    and would otherwise lie over the image and catch the clicks meant for it.

    ``band`` (0, 1]: frame the image within the top ``band`` of the view's height instead of
    all of it (:data:`PORTRAIT_BAND`: the room a phone's control sheet leaves); the band is then
    the view above, spare room and margin included.

    With the camera at ``(cx, cy, -d)`` looking along +z, the view spans ``d tan(fov/2)`` up
    and down and ``aspect`` times that sideways; the image's right and bottom edges are put at
    the limiting axis's margin from the band's.
    """
    if not 0.0 < band <= 1.0:
        raise ValueError(f"band must be in (0, 1], got {band}")
    rw, rh = render_size
    tan_half = float(np.tan(fov_y_rad / 2.0))
    d = (1.0 + VIEW_MARGIN) * max((rh / 2) / (tan_half * band), (rw / 2) / (tan_half * aspect))
    half_h = d * tan_half
    half_w = half_h * aspect
    gap = min(half_w - rw / 2, band * half_h - rh / 2)  # the limiting axis's margin, >= 0
    cx = centre[0] + rw / 2 - half_w + gap
    # The band's bottom edge lies 2 band half_h below the view's top edge (cy - half_h; up is -y).
    cy = centre[1] + rh / 2 + half_h - 2 * band * half_h + gap
    return (cx, cy, -d), (cx, cy, 0.0)


def view_in_band(position: ArrayLike, look_at: ArrayLike, up: ArrayLike, aspect: float, fov_y_rad: float,
                 band: float, reference_aspect: float = 16 / 9) -> tuple[
        tuple[float, float, float], tuple[float, float, float]]:
    """A 3D view ``(position, look_at)``, made for a view of ``reference_aspect`` (width /
    height), moved so that what it showed around ``look_at`` shows within the top ``band`` of
    the view's height in a view of ``aspect`` (a phone held upright, whose control sheet covers
    the rest: :data:`PORTRAIT_BAND`).

    The camera turns down about its horizontal axis by ``alpha = atan((1 - band) tan(fov/2))``,
    so that ``look_at`` appears at the band's centre, not the view's, and backs away along its
    line of sight until the rectangle the reference view showed at ``look_at``'s distance ``D``
    (half-extents ``h = D tan(fov/2)`` up and ``reference_aspect h`` across, square to the
    line of sight) fits the band: with ``t = tan(fov/2)``, a point ``y`` up that rectangle lies
    ``D' cos(alpha) - y sin(alpha)`` deep along the new axis and ``D' sin(alpha) + y cos(alpha)``
    above it, which bounds ``D'`` by its top corners against the view's sides and top and its
    bottom edge against the band's. It never comes nearer than ``D``: a view at least as wide
    as ``reference_aspect`` with ``band`` 1 is returned unchanged.
    """
    if not 0.0 < band <= 1.0:
        raise ValueError(f"band must be in (0, 1], got {band}")
    P, C = np.asarray(position, dtype=float), np.asarray(look_at, dtype=float)
    sight = C - P
    distance = float(np.linalg.norm(sight))
    forward = sight / distance
    up_v = np.asarray(up, dtype=float)
    up_on_screen = up_v - forward * float(forward @ up_v)
    up_on_screen /= np.linalg.norm(up_on_screen)
    t = float(np.tan(fov_y_rad / 2.0))
    tilt = np.arctan((1.0 - band) * t)
    c, s = float(np.cos(tilt)), float(np.sin(tilt))
    h = distance * t
    w = h * reference_aspect
    b = 1.0 - 2.0 * band  # the band's bottom edge, in the view's normalised height (-1 bottom, 1 top)
    distance_new = max(distance,
                       (w / (t * aspect) + h * s) / c,  # the top corners inside the sides
                       h * (c + t * s) / (t * c - s),  # the top edge below the view's top
                       h * (c + b * t * s) / (s - b * t * c))  # the bottom edge above the band's
    P_new = C - forward * distance_new
    axis = c * forward - s * up_on_screen  # below the target: it shows above the centre
    L_new = P_new + axis * distance
    return (float(P_new[0]), float(P_new[1]), float(P_new[2])), (float(L_new[0]), float(L_new[1]), float(L_new[2]))


#: How far outside the image (px) a click ray may land and still be the edge pixel.
EDGE_SLACK_PX = 0.5


def ray_to_pixel(
    ray_origin: ArrayLike,
    ray_direction: ArrayLike,
    plane_wxyz: ArrayLike,
    plane_position: ArrayLike,
    image_size: tuple[int, int],
    render_size: tuple[float, float],
) -> tuple[float, float] | None:
    """The image pixel (u, v) a click ray hits, or None when it misses the image (by more than
    :data:`EDGE_SLACK_PX`: a hit just outside is put on the image's border, ``-0.5`` or
    ``W - 0.5``, where the tracker says why it refuses it).

    Args:
        ray_origin, ray_direction: (3,) the click ray in the world frame (viser's click event).
        plane_wxyz, plane_position: pose of the image node in the world frame, ``T_world_plane``.
        image_size: (W, H) of the image, px.
        render_size: (render_w, render_h) of the plane, scene units.

    The ray is brought into the plane's frame (``p_plane = R^T (p_world - t)``), intersected
    with z = 0, and the hit scaled to pixels by inverting :func:`pixel_to_plane`.
    """
    R = Rotation.from_quat(np.asarray(plane_wxyz, dtype=float), scalar_first=True).as_matrix()
    t = np.asarray(plane_position, dtype=float)
    o = R.T @ (np.asarray(ray_origin, dtype=float) - t)
    d = R.T @ np.asarray(ray_direction, dtype=float)
    if abs(d[2]) < 1e-12:
        return None
    s = -o[2] / d[2]
    if s < 0:
        return None
    x, y = o[0] + s * d[0], o[1] + s * d[1]
    w, h = image_size
    rw, rh = render_size
    u = (x + rw / 2) * w / rw - 0.5
    v = (y + rh / 2) * h / rh - 0.5
    # The browser found the click on the image; its float32 ray, intersected again here, may
    # land a hair outside the edge: up to EDGE_SLACK_PX out it is put on the border.
    if not (-0.5 - EDGE_SLACK_PX <= u <= w - 0.5 + EDGE_SLACK_PX and -0.5 - EDGE_SLACK_PX <= v <= h - 0.5 + EDGE_SLACK_PX):
        return None
    return float(min(max(u, -0.5), w - 0.5)), float(min(max(v, -0.5), h - 0.5))


def to_rgb(grey: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """(H,W) grey → (H,W,3) RGB (viser refuses 2-D images)."""
    return cast("NDArray[np.uint8]", cv2.cvtColor(np.ascontiguousarray(grey), cv2.COLOR_GRAY2RGB))


def _pt(uv: ArrayLike, scale: float) -> tuple[int, int]:
    # cv2 draws at integer pixel centres; pixel centre (0,0) is cv2's (0,0) too.
    u, v = np.asarray(uv, dtype=float)
    return int(round(u * scale)), int(round(v * scale))


def box_half_px(patch_px: int, operator: bool = False) -> float:
    """Half the side of the box drawn around a target, image px: its patch's, at least 3 px; an
    operator's target's box one pixel more (drawn thicker, it stays clear of the patch)."""
    return max(patch_px / 2.0, 3.0) + (1.0 if operator else 0.0)


def label_origins(
    anchors: Sequence[tuple[int, int]],
    sizes: Sequence[tuple[int, int, int]],
    half_px: int,
    image_size: tuple[int, int],
) -> list[tuple[int, int]]:
    """Where to write each target's id beside its box so that no two ids overlap where it can
    be helped: the first of four corners (right above, left above, right below, left below the
    box) that stays inside the image and meets no label placed before it, else the corner that
    overlaps least. Greedy, in the order given.

    Args:
        anchors: (u, v) box centres in the drawn image, px.
        sizes: ``(width, height, baseline)`` of each label (``cv2.getTextSize``), px.
        half_px: half the box's side, px.
        image_size: (W, H) of the drawn image, px.

    Returns:
        Each label's text origin (``cv2.putText``'s bottom-left), px.
    """
    W, H = image_size
    placed: list[tuple[int, int, int, int]] = []
    origins: list[tuple[int, int]] = []
    for (cu, cv), (w, h, base) in zip(anchors, sizes):
        right, left = cu + half_px + 3, cu - half_px - 3 - w
        above, below = cv - half_px, cv + half_px + h
        best: tuple[float, tuple[int, int], tuple[int, int, int, int]] | None = None
        for x, y in ((right, above), (left, above), (right, below), (left, below)):
            x0, y0, x1, y1 = box = (x, y - h, x + w, y + base)
            cost = 0.0 if 0 <= x0 and x1 <= W and 0 <= y0 and y1 <= H else 1e9  # off the image: only when every corner is
            for a0, b0, a1, b1 in placed:
                if a0 < x1 and x0 < a1 and b0 < y1 and y0 < b1:  # (the publisher's time: most pairs are apart)
                    cost += (min(x1, a1) - max(x0, a0)) * (min(y1, b1) - max(y0, b0))
            if best is None or cost < best[0]:
                best = (cost, (x, y), box)
            if cost == 0.0:
                break
        assert best is not None
        origins.append(best[1])
        placed.append(best[2])
    return origins


def draw_overlays(
    rgb: NDArray[np.uint8],
    targets: Sequence[TargetState],
    trails: Mapping[str, Iterable[tuple[float, float]]] | None = None,
    patch_px: int = 8,
    scale: float = 1.0,
    show_search: bool = True,
    operator_boxes: bool = True,
) -> NDArray[np.uint8]:
    """Draw each target into ``rgb`` (modified in place and returned).

    Operator targets get a thick box with a corner tick, automatic ones a thin box, model
    re-locks a diamond; the colour says the status (:data:`STATUS_RGB`). Also the search
    window (thin blue), the Kalman-predicted position (magenta cross) and a short trail.
    ``operator_boxes=False`` leaves the operator targets' boxes and ids out (the console draws
    them as scene nodes over the image, see :func:`box_segments`).

    Args:
        rgb: (H*scale, W*scale, 3) uint8 image.
        targets: the snapshot's targets; ``uv`` etc. in original-image pixels.
        trails: id → recent (u, v) positions, oldest first.
        patch_px: patch side drawn as the box, px.
        scale: display scale of ``rgb`` relative to the original image.
    """
    half = box_half_px(patch_px)
    font = cv2.FONT_HERSHEY_SIMPLEX
    if show_search:
        # Search windows can be large and overlap: drawn at 40 % so the image stays readable.
        layer = rgb.copy()
        drawn = False
        for t in targets:
            if t.status != "lost" and np.all(np.isfinite(t.search_box)):
                u0, v0, u1, v1 = t.search_box
                cv2.rectangle(layer, _pt((u0, v0), scale), _pt((u1, v1), scale), SEARCH_RGB, 1, cv2.LINE_8)
                drawn = True
        if drawn:
            cv2.addWeighted(layer, 0.4, rgb, 0.6, 0.0, dst=rgb)
    labelled: list[tuple[TargetState, tuple[int, int]]] = []
    for t in targets:
        if not np.all(np.isfinite(t.uv)):
            continue
        colour = STATUS_RGB.get(t.status, (255, 255, 255))
        if trails is not None and t.id in trails:
            trail = np.asarray(list(trails[t.id]), dtype=float).reshape(-1, 2)
            pts = np.rint(trail[np.isfinite(trail).all(axis=1)] * scale).astype(np.int32)
            if len(pts) >= 2:
                cv2.polylines(rgb, [pts.reshape(-1, 1, 2)], False, TRAIL_RGB, 1, cv2.LINE_AA)
        if np.all(np.isfinite(t.predicted_uv)):
            pu, pv = _pt(t.predicted_uv, scale)
            cv2.drawMarker(rgb, (pu, pv), PREDICTED_RGB, cv2.MARKER_CROSS, 7, 1, cv2.LINE_AA)
        if t.origin == "operator" and not operator_boxes:
            continue
        c = _pt(t.uv, scale)
        labelled.append((t, c))
        h = int(round(half * scale))
        if t.origin == "operator":
            cv2.rectangle(rgb, (c[0] - h - 1, c[1] - h - 1), (c[0] + h + 1, c[1] + h + 1), colour, 2, cv2.LINE_8)
        elif t.origin == "model":
            diamond = np.array([(c[0], c[1] - h - 2), (c[0] + h + 2, c[1]), (c[0], c[1] + h + 2), (c[0] - h - 2, c[1])], np.int32)
            cv2.polylines(rgb, [diamond.reshape(-1, 1, 2)], True, colour, 1, cv2.LINE_8)
        else:
            cv2.rectangle(rgb, (c[0] - h, c[1] - h), (c[0] + h, c[1] + h), colour, 1, cv2.LINE_8)
    # The ids after every box, placed so that targets side by side do not write over each other.
    font_scale = 0.38 * max(scale, 1.0)
    texts = [t.id if t.origin != "operator" else f"{t.id}*" for t, _ in labelled]
    sizes = [(w, h_text, base) for (w, h_text), base in (cv2.getTextSize(x, font, font_scale, 1) for x in texts)]
    origins = label_origins([c for _, c in labelled], sizes, int(round(half * scale)), (rgb.shape[1], rgb.shape[0]))
    for (t, _), text, origin in zip(labelled, texts, origins):
        cv2.putText(rgb, text, origin, font, font_scale, STATUS_RGB.get(t.status, (255, 255, 255)), 1, cv2.LINE_AA)
    return rgb


def draw_matches(rgb: NDArray[np.uint8], targets: Sequence[TargetState], patch_px: int = 8) -> NDArray[np.uint8]:
    """Box the right-image match (``uv_right``) of each measured target in ``rgb`` (modified in
    place and returned), ``patch_px`` wide, in the tracking green; the part of a box off the
    image is left out. Drawn with numpy slices, a match above or left of the image (``uv_right``
    is the unrectified pixel of a rectified match) gave negative indices, which wrapped round:
    a full-height line, and another at the far edge."""
    height, width = rgb.shape[:2]
    half = patch_px // 2
    for t in targets:
        if t.measured and np.all(np.isfinite(t.uv_right)):
            # Held just beyond the edges: a far-off box stays off the image, in cv2's int range.
            u = int(round(min(max(float(t.uv_right[0]), -half - 1.0), width + half)))
            v = int(round(min(max(float(t.uv_right[1]), -half - 1.0), height + half)))
            cv2.rectangle(rgb, (u - half, v - half), (u + half, v + half), STATUS_RGB["tracking"], 1, cv2.LINE_8)
    return rgb
