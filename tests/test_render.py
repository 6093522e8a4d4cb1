"""The satellite mock-up and the stereo renderer: geometric exactness against the rig's own
projection (OpenCV), agreement of ``surface_points`` with the images, visibility, shadows,
sensor noise statistics, determinism, and bad mock-up files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from trackmeter.errors import TrackmeterError
from trackmeter.paths import MODELS_DIR
from trackmeter.sources.sim.mockup import MaterialSpec, Mockup, load_mockup, rect_face, surface_from_arrays
from trackmeter.sources.sim.render import Occluder, RenderParams, StereoRenderer, look_at

TEXEL_M = 0.002
N_TEX = 200  # the test board is 0.4 m square
DOTS = ((37.3, 51.8), (150.6, 140.25), (100.0, 100.5), (160.2, 40.7))  # texel coordinates (i, j)
PLAIN = MaterialSpec(name="plain", kind="plain", albedo=0.5, albedo_variation=0.0)
# noise-free, fixed exposure, no black level: grey = gain * radiance
EXACT = RenderParams(ambient=0.0, auto_exposure=False, exposure_gain_grey=230.0, black_level_grey=0.0)


def _board(albedo: np.ndarray, center=(0.0, 0.0, 0.0), name: str = "board"):  # type: ignore[no-untyped-def]
    """A square face facing -z of the body frame (towards a camera at look_at's identity)."""
    return rect_face(name, np.asarray(center, float), np.array([1.0, 0, 0]), np.array([0, -1.0, 0]), surface_from_arrays(PLAIN, albedo), texel_m=TEXEL_M)


def _dot_texture() -> np.ndarray:
    jj, ii = np.mgrid[0:N_TEX, 0:N_TEX].astype(float)
    tex = np.zeros((N_TEX, N_TEX))
    for di, dj in DOTS:
        tex += np.exp(-((ii - di) ** 2 + (jj - dj) ** 2) / (2 * 2.5**2))
    return tex


def _texel_body(face, i: float, j: float) -> np.ndarray:  # type: ignore[no-untyped-def]
    """Body point of continuous texel coordinate (i, j) (texel centres at integers)."""
    return face.origin + (i + 0.5) * TEXEL_M * face.e_u + (j + 0.5) * TEXEL_M * face.e_v


def _centroid(img: np.ndarray, uv: np.ndarray, k: int = 8) -> np.ndarray | None:
    u0, v0 = np.round(uv).astype(int)
    h, w = img.shape
    if not (k <= u0 < w - k and k <= v0 < h - k):
        return None
    win = img[v0 - k : v0 + k + 1, u0 - k : u0 + k + 1].astype(float)
    yy, xx = np.mgrid[v0 - k : v0 + k + 1, u0 - k : u0 + k + 1]
    return np.array([(win * xx).sum(), (win * yy).sum()]) / win.sum()


# Poses that put the board off-centre (where distortion is largest) and tilted.
POSES = [((0.9, -0.6, 3.5), (20, -30, 10)), ((-0.7, 0.45, 3.2), (-25, 15, 40)), ((0.0, 0.0, 3.5), (0, 0, 0))]


@pytest.fixture(scope="module")
def dot_scene(estec_rig):  # type: ignore[no-untyped-def]
    face = _board(_dot_texture())
    return face, StereoRenderer(estec_rig, Mockup(name="dots", texel_m=TEXEL_M, faces=(face,)), EXACT)


def test_rendered_dots_land_on_rig_projection(estec_rig, dot_scene) -> None:  # type: ignore[no-untyped-def]
    """A Gaussian dot at a known texture point renders where StereoRig.project (OpenCV
    projectPoints with the rig's distortion) puts its 3D point, in both images: < 0.05 px."""
    face, renderer = dot_scene
    errors = []
    for pos, rv in POSES:
        T = look_at(np.array(pos), np.array(rv, float))
        sun = T[:3, :3] @ np.array([0, 0, -1.0])  # straight onto the board
        left, right = renderer.render(T, sun, np.random.default_rng(0), noise=False)
        for di, dj in DOTS:
            p_cam = T[:3, :3] @ _texel_body(face, di, dj) + T[:3, 3]
            uv_l, uv_r = estec_rig.project(p_cam[None])
            for img, uv in ((left, uv_l[0]), (right, uv_r[0])):
                c = _centroid(img, uv)
                if c is not None:
                    errors.append(c - uv)
    errors = np.array(errors)
    assert len(errors) >= 16  # both images, several poses, distortion exercised near the edges
    assert np.abs(errors).max() < 0.05, np.abs(errors).max()


def test_rendered_dots_exact_on_coarse_texture_levels(estec_rig) -> None:  # type: ignore[no-untyped-def]
    """At 9-10 m the renderer draws from coarser mip levels (texel ~ 4x smaller than a pixel at
    level 0); their texel centres must map as exactly as level 0's."""
    n, sigma = 400, 8.0
    dots = ((77.3, 101.8), (300.6, 280.25), (200.0, 200.5), (320.2, 80.7))
    jj, ii = np.mgrid[0:n, 0:n].astype(float)
    tex = sum(np.exp(-((ii - di) ** 2 + (jj - dj) ** 2) / (2 * sigma**2)) for di, dj in dots)
    face = _board(tex)
    renderer = StereoRenderer(estec_rig, Mockup(name="far", texel_m=TEXEL_M, faces=(face,)), EXACT)
    errors = []
    for pos, rv in (((1.5, -1.0, 9.0), (20, -30, 10)), ((-1.2, 0.8, 10.0), (-25, 15, 40))):
        T = look_at(np.array(pos), np.array(rv, float))
        left, right = renderer.render(T, T[:3, :3] @ np.array([0, 0, -1.0]), np.random.default_rng(0), noise=False)
        for di, dj in dots:
            uv_l, uv_r = estec_rig.project((T[:3, :3] @ _texel_body(face, di, dj) + T[:3, 3])[None])
            for img, uv in ((left, uv_l[0]), (right, uv_r[0])):
                c = _centroid(img, uv, k=6)
                assert c is not None
                errors.append(c - uv)
    assert np.abs(np.array(errors)).max() < 0.05


@pytest.mark.parametrize("trilinear", [True, False])
def test_a_receding_face_changes_its_texture_smoothly(estec_rig, trilinear: bool) -> None:  # type: ignore[no-untyped-def]
    """A fine random texture receding from 2.8 m to 8 m crosses two mip levels. Its image contrast
    falls as texels shrink below a pixel; with the levels blended (trilinear) it falls
    smoothly, with the nearest level it drops at each switch (the switch that made a tracker
    lose most of its targets in one frame of the estec scenario)."""
    from dataclasses import replace

    rng = np.random.default_rng(5)
    face = _board(0.2 + 0.6 * rng.random((N_TEX, N_TEX)))
    renderer = StereoRenderer(estec_rig, Mockup(name="board", texel_m=TEXEL_M, faces=(face,)), replace(EXACT, trilinear=trilinear))
    sun = np.array([0.0, 0.0, -1.0])
    contrast = []
    for z in np.geomspace(2.8, 8.0, 50):
        T = look_at(np.array([0.0, 0.0, z]), np.array([0.0, 0.0, 0.0]))
        left, _ = renderer.render(T, sun, np.random.default_rng(0), noise=False)
        h = int(0.1 * estec_rig.left.K[0, 0] / z)  # inside the board's central 0.2 m
        u0, v0 = int(estec_rig.left.K[0, 2]), int(estec_rig.left.K[1, 2])
        contrast.append(left[v0 - h:v0 + h, u0 - h:u0 + h].astype(float).std())
    steps = np.abs(np.diff(np.log(contrast)))  # 2.1 % farther per step
    if trilinear:
        assert steps.max() < 0.25  # (the largest, ~0.16, is the moire both modes show near 5 m)
    else:
        assert steps.max() > 0.5  # contrast halves from one step to the next at a switch


def test_motion_blur_is_centred_on_the_current_pose(estec_rig) -> None:  # type: ignore[no-untyped-def]
    """Sub-frames spread symmetrically about T_cam_body: a dot moving 7 px per frame is smeared
    along its motion, but its centroid stays on the current pose's projection."""
    face = _board(_dot_texture())
    params = RenderParams(ambient=0.0, auto_exposure=False, exposure_gain_grey=230.0, black_level_grey=0.0, motion_blur_subframes=9, shutter_fraction=1.0)
    renderer = StereoRenderer(estec_rig, Mockup(name="dots", texel_m=TEXEL_M, faces=(face,)), params)
    T = look_at(np.array([0.1, 0.05, 3.5]), np.array([10.0, -5.0, 0.0]))
    T_prev = T.copy()
    T_prev[:3, 3] -= (0.02, 0.0, 0.0)  # 2 cm per frame: ~6.6 px
    sun = T[:3, :3] @ np.array([0, 0, -1.0])
    blurred, _ = renderer.render(T, sun, np.random.default_rng(0), T_cam_body_prev=T_prev, noise=False)
    sharp, _ = renderer.render(T, sun, np.random.default_rng(0), noise=False)
    for di, dj in DOTS:
        uv = estec_rig.project((T[:3, :3] @ _texel_body(face, di, dj) + T[:3, 3])[None])[0][0]
        c = _centroid(blurred, uv, k=12)
        assert c is not None and np.abs(c - uv).max() < 0.05
        u0, v0 = np.round(uv).astype(int)
        # smeared along u: the blurred dot is wider in u than in v, the sharp one is round
        win = blurred[v0 - 12 : v0 + 13, u0 - 12 : u0 + 13].astype(float)
        spread_u = (win.sum(axis=0) > 0.2 * win.sum(axis=0).max()).sum()
        spread_v = (win.sum(axis=1) > 0.2 * win.sum(axis=1).max()).sum()
        assert spread_u >= spread_v + 4
        assert blurred[v0, u0] < sharp[v0, u0]


def test_surface_points_agree_with_render(estec_rig, dot_scene) -> None:  # type: ignore[no-untyped-def]
    face, renderer = dot_scene
    T = look_at(np.array([0.3, -0.2, 3.4]), np.array([15.0, -20.0, 5.0]))
    sun = T[:3, :3] @ np.array([0, 0, -1.0])
    left, right = renderer.render(T, sun, np.random.default_rng(0), noise=False)
    # the pixel where the dot is seen (measured in the image) sees the dot's texture point
    for di, dj in DOTS:
        p_body = _texel_body(face, di, dj)
        uv_l, uv_r = estec_rig.project((T[:3, :3] @ p_body + T[:3, 3])[None])
        c_l = _centroid(left, uv_l[0])
        c_r = _centroid(right, uv_r[0])
        assert c_l is not None and c_r is not None
        assert np.linalg.norm(renderer.surface_points(T, c_l[None])[0] - p_body) < 0.3e-3
        assert np.linalg.norm(renderer.surface_points_right(T, c_r[None])[0] - p_body) < 0.3e-3
    # every pixel: a surface point projects back onto the pixel; NaN exactly where the image is black
    vv, uu = np.mgrid[0:512:7, 0:726:7]
    uv = np.column_stack([uu.ravel(), vv.ravel()]).astype(float)
    pts = renderer.surface_points(T, uv)
    hit = np.isfinite(pts[:, 0])
    assert 0.02 < hit.mean() < 0.6
    back, _ = estec_rig.project(pts[hit] @ T[:3, :3].T + T[:3, 3])
    assert np.abs(back - uv[hit]).max() < 1e-6
    board = np.zeros((N_TEX, N_TEX)) + 0.5
    flat = StereoRenderer(estec_rig, Mockup(name="flat", texel_m=TEXEL_M, faces=(_board(board),)), EXACT)
    img, _ = flat.render(T, sun, np.random.default_rng(0), noise=False)
    grey = img[uv[:, 1].astype(int), uv[:, 0].astype(int)]
    # away from the board's edge (1 px soft edge), lit <=> surface point
    inner = np.isfinite(flat.surface_points(T, uv + 1.5)[:, 0]) & np.isfinite(flat.surface_points(T, uv - 1.5)[:, 0])
    outer = ~np.isfinite(flat.surface_points(T, uv + 1.5)[:, 0]) & ~np.isfinite(flat.surface_points(T, uv - 1.5)[:, 0])
    assert np.all(grey[inner & hit] > 50) and np.all(grey[outer & ~hit] == 0)


def _two_boards(estec_rig, params=EXACT):  # type: ignore[no-untyped-def]
    far = _board(np.full((N_TEX, N_TEX), 0.8), center=(0.0, 0.0, 0.0), name="far")
    near = _board(np.full((N_TEX, N_TEX), 0.3), center=(0.25, 0.1, -0.3), name="near")
    return far, near, StereoRenderer(estec_rig, Mockup(name="two", texel_m=TEXEL_M, faces=(far, near)), params)


def test_near_face_hides_far_face_and_occluder_hides_both(estec_rig) -> None:  # type: ignore[no-untyped-def]
    far, near, renderer = _two_boards(estec_rig)
    T = look_at(np.array([0.0, 0.0, 3.5]), np.zeros(3))
    sun = np.array([0, 0, -1.0])
    occ = Occluder(look_at(np.array([-0.2, 0.0, 2.5]), np.zeros(3)), (0.1, 1.0))
    for occluders in ((), (occ,)):
        img, _ = renderer.render(T, sun, np.random.default_rng(0), occluders=occluders, noise=False)
        vv, uu = np.mgrid[5:512:9, 5:726:9]
        uv = np.column_stack([uu.ravel(), vv.ravel()]).astype(float)
        pts = renderer.surface_points(T, uv, occluders=occluders)
        z = pts[:, 2]
        grey = img[uv[:, 1].astype(int), uv[:, 0].astype(int)].astype(float)
        on_near = np.isclose(z, -0.3, atol=1e-9)
        on_far = np.isclose(z, 0.0, atol=1e-9)
        assert on_near.sum() > 50 and on_far.sum() > 50
        # both seen with the sun straight on: grey = 230 * albedo (edge pixels aside)
        assert np.median(grey[on_near]) == pytest.approx(230 * 0.3, abs=1.5)
        assert np.median(grey[on_far]) == pytest.approx(230 * 0.8, abs=1.5)
        if occluders:
            blocked = ~np.isfinite(z) & (np.abs(uv[:, 0] - (362.5 - 0.2 * 1152 / 2.5)) < 15)
            assert blocked.sum() > 20
            assert np.median(grey[blocked]) < 230 * 0.05


def test_shadow_of_near_face_on_far_face(estec_rig) -> None:  # type: ignore[no-untyped-def]
    """With an oblique sun the near board's shadow on the far board is where a ray from the far
    board toward the sun meets the near board; there only the ambient light remains."""
    params = RenderParams(ambient=0.1, auto_exposure=False, exposure_gain_grey=230.0, black_level_grey=0.0)
    far, near, renderer = _two_boards(estec_rig, params)
    T = look_at(np.array([0.0, 0.0, 3.5]), np.zeros(3))
    sun = np.array([0.6, 0.0, -0.8])  # from the right, toward the camera side
    img, _ = renderer.render(T, sun, np.random.default_rng(0), noise=False)
    vv, uu = np.mgrid[5:512:6, 5:726:6]
    uv = np.column_stack([uu.ravel(), vv.ravel()]).astype(float)
    pts = renderer.surface_points(T, uv)
    on_far = np.isclose(pts[:, 2], 0.0, atol=1e-9)
    # ray from far-board point toward the sun: where does it cross the near board's plane z = -0.3?
    s_body = T[:3, :3].T @ (sun / np.linalg.norm(sun))
    lam = (-0.3 - pts[:, 2]) / s_body[2]
    hit = pts + lam[:, None] * s_body
    hx, hy = hit[:, 0] - 0.25, hit[:, 1] - 0.1
    half = 0.5 * N_TEX * TEXEL_M
    shadowed = on_far & (np.abs(hx) < half - 0.01) & (np.abs(hy) < half - 0.01)
    lit = on_far & ((np.abs(hx) > half + 0.01) | (np.abs(hy) > half + 0.01))
    assert shadowed.sum() > 20 and lit.sum() > 20
    grey = img[uv[:, 1].astype(int), uv[:, 0].astype(int)].astype(float)
    cos = -s_body[2]
    assert np.median(grey[lit]) == pytest.approx(230 * 0.8 * (0.1 + cos), abs=1.5)
    assert np.median(grey[shadowed]) == pytest.approx(230 * 0.8 * 0.1, abs=1.5)


@pytest.mark.parametrize("read, shot", [(2.0, 0.0), (1.0, 0.5)])
def test_noise_statistics_match_params(estec_rig, read: float, shot: float) -> None:  # type: ignore[no-untyped-def]
    """Over a uniformly lit board: mean = black + gain * radiance, variance = read² + shot_gain *
    signal + 1/12 (8-bit quantisation)."""
    params = RenderParams(ambient=0.0, auto_exposure=False, exposure_gain_grey=200.0, black_level_grey=10.0, read_noise_grey=read, shot_noise_gain=shot)
    board = _board(np.full((400, 400), 0.6))  # 0.8 m: 460 px wide at 2 m, in both images
    renderer = StereoRenderer(estec_rig, Mockup(name="flat", texel_m=TEXEL_M, faces=(board,)), params)
    T = look_at(np.array([0.0, 0.0, 2.0]), np.zeros(3))
    left, right = renderer.render(T, np.array([0, 0, -1.0]), np.random.default_rng(5))
    signal = 200.0 * 0.6
    for img in (left, right):
        patch = img[150:360, 150:420].astype(float)
        assert patch.mean() == pytest.approx(10.0 + signal, abs=0.1)
        assert patch.var() == pytest.approx(read**2 + shot * signal + 1 / 12, rel=0.06)
    # black space: black level plus read noise
    corner = left[:60, :60].astype(float)
    assert corner.mean() == pytest.approx(10.0, abs=0.1)
    assert corner.var() == pytest.approx(read**2 + 1 / 12, rel=0.1)


@pytest.fixture(scope="module")
def estec(estec_rig):  # type: ignore[no-untyped-def]
    return StereoRenderer(estec_rig, load_mockup(MODELS_DIR / "estec_mockup.yaml"), RenderParams(motion_blur_subframes=3))


def test_estec_render_deterministic_and_exposed(estec) -> None:  # type: ignore[no-untyped-def]
    T = look_at(np.array([0.1, 0.0, 3.5]), np.array([-110.0, 35.0, 20.0]))
    T_prev = look_at(np.array([0.1, 0.0, 3.5]), np.array([-108.0, 34.0, 21.0]))
    sun = np.array([-0.5, -0.6, -0.6])
    a = estec.render(T, sun, np.random.default_rng(42), T_cam_body_prev=T_prev)
    b = estec.render(T, sun, np.random.default_rng(42), T_cam_body_prev=T_prev)
    c = estec.render(T, sun, np.random.default_rng(43), T_cam_body_prev=T_prev)
    assert a[0].shape == (512, 726) and a[0].dtype == np.uint8
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert not np.array_equal(a[0], c[0])
    # auto-iris: the 99th percentile of the satellite sits near the target
    pts = estec.surface_points(T, np.column_stack([np.mgrid[0:512:4, 0:726:4][1].ravel(), np.mgrid[0:512:4, 0:726:4][0].ravel()]).astype(float))
    seen = np.isfinite(pts[:, 0])
    assert 0.1 < seen.mean() < 0.8
    vals = a[0][::4, ::4].ravel()[seen]
    assert 150 < np.percentile(vals, 99) < 255
    # a different attitude changes the glints: the two images differ a lot
    T2 = look_at(np.array([0.1, 0.0, 3.5]), np.array([-104.0, 38.0, 20.0]))
    d = estec.render(T2, sun, np.random.default_rng(42))
    assert np.abs(d[0].astype(int) - a[0].astype(int)).mean() > 3


def test_estec_mockup_model(estec) -> None:  # type: ignore[no-untyped-def]
    m = estec.mockup
    names = [n for n, _ in m.salient_points]
    assert len(names) == len(set(names)) >= 8
    corners = np.array([p for n, p in m.salient_points if n.startswith("bus_")])
    assert np.allclose(np.abs(corners), [0.4, 0.4, 0.45])
    v, f, c = m.to_trimesh_arrays()
    assert v.shape[1] == 3 and f.shape[1] == 3 and c.shape == (len(f), 3)
    assert f.min() == 0 and f.max() == len(v) - 1
    assert 0.9 < np.abs(v).max() < 1.2  # wings' tips ~ 0.93 m from the bus centre


@pytest.mark.parametrize(
    "edit, key",
    [
        ("parts[0].size: [1, 2]", "parts[0].size"),
        ("parts[0].material: unobtainium", "parts[0].material"),
        ("materials[0].albedo: 3", "materials[0].albedo"),
        ("parts[0].colour: red", "parts[0].colour"),
        ("texel_m: fine", "texel_m"),
    ],
)
def test_bad_mockup_file_names_the_key(tmp_path: Path, edit: str, key: str) -> None:
    import yaml

    data = yaml.safe_load((MODELS_DIR / "estec_mockup.yaml").read_text())
    path_s, value = edit.split(": ", 1)
    target = data
    parts = path_s.replace("]", "").replace("[", ".").split(".")
    for p in parts[:-1]:
        target = target[int(p)] if p.isdigit() else target[p]
    target[parts[-1]] = yaml.safe_load(value)
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(data))
    with pytest.raises(TrackmeterError, match=key.replace("[", r"\[").replace("]", r"\]")):
        load_mockup(bad)


def test_a_microscopic_part_blurs_its_texture_no_wider_than_the_texture(tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    # A tiny part has 2x2 texels and a feature size of hundreds of them (a tenth of a
    # millimetre: 300 times the texture; a micrometre: a million): the Gaussian kernel was
    # built that wide, and load_mockup ran for minutes (an outside probe).
    import trackmeter.sources.sim.mockup as mockup

    widest = []
    blur = mockup.cv2.GaussianBlur

    def recorded(src, ksize, sigma, **kwargs):  # type: ignore[no-untyped-def]
        widest.append(sigma / max(src.shape))
        return blur(src, ksize, sigma, **kwargs)

    monkeypatch.setattr(mockup.cv2, "GaussianBlur", recorded)
    path = tmp_path / "tiny.yaml"
    path.write_text("materials: [{name: m}]\nparts: [{name: p, material: m, size: [1.0e-4, 1.0e-4, 1.0e-4]}]\n")
    assert len(load_mockup(path).faces) == 6  # a box
    assert widest and max(widest) <= 2.0
