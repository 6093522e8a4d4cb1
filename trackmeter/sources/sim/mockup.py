"""The satellite mock-up: planar textured faces with materials, built from a YAML file.

A mock-up file (``config/models/<name>.yaml``) lists *materials* (procedural textures with
their reflectance) and *parts* (boxes, flat panels, discs) placed in the body frame. Loading
it turns every part into planar :class:`Face` objects, each carrying per-texel textures for
its front (and, for thin panels, back) side:

- ``albedo``: diffuse reflectance (0..1),
- ``alpha``: coverage (1 on the part, 0 outside a disc's circle),
- ``normal``: the perturbed unit normal in the face's local frame ``(e_u, e_v, n)``, which makes
  crinkled foil, tilted solar cells and mirror tiles glint facet by facet as the attitude
  changes (the paper's "dazzling and very quickly variable images"),
- ``spec``: specular strength (how much of the sun a texel mirrors toward the camera).

Texture coordinates (pixel-centre convention, as OpenCV's warps use): texel ``(i, j)``
(column, row) of a level with ``nu x nv`` texels has its centre at the face-local point
``x = (i + 0.5) w / nu``, ``y = (j + 0.5) h / nv`` (metres), i.e. at the body point
``origin + x e_u + y e_v``. Coarser mip levels cover the same face, so the same formula holds
at every level with its own ``nu, nv``. The renderer (:mod:`trackmeter.sources.sim.render`)
relies on this to be geometrically exact.

Body frame: origin at the bus centre; the mock-up file's axes (in the ESTEC mock-up: +z the
antenna deck, ±y the wings).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Literal, cast

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from trackmeter.core.params import param
from trackmeter.data.config import build_dataclass, read_yaml_mapping
from trackmeter.errors import TrackmeterError

F32 = NDArray[np.float32]
FloatArray = NDArray[np.float64]
#: A material's texture: albedo, the bump map's two gradients and the specular weight, each (H,W).
_Texture = tuple[NDArray[np.floating], NDArray[np.floating], NDArray[np.floating], NDArray[np.floating]]

#: Box face order for ``face_materials``: outward normals +x, -x, +y, -y, +z, -z.
BOX_FACES: tuple[str, ...] = ("+x", "-x", "+y", "-y", "+z", "-z")


# --------------------------------------------------------------------------- file schema


@dataclass(frozen=True)
class MaterialSpec:
    """One material of a mock-up file (``materials[i]``)."""

    name: str = param("", "Name the parts refer to.")
    kind: Literal["mli", "solar", "radiator", "paint", "metal", "plain"] = param(
        "plain", "Procedural texture: crinkled MLI foil, solar cells, OSR radiator tiles, paint, metal, plain."
    )
    albedo: float = param(0.4, "Mean diffuse reflectance.", min=0.0, max=1.0)
    albedo_variation: float = param(0.2, "Relative texel-to-texel (facet, cell, tile) albedo variation.", min=0.0, max=2.0)
    specular: float = param(0.0, "Specular (glint) strength, in units of the sun's diffuse radiance.", min=0.0, max=100.0)
    sharpness: float = param(40.0, "Specular lobe exponent (Phong-like); larger = smaller, brighter glints.", min=1.0, max=1e5)
    feature_m: float = param(0.03, "Scale of the texture's features (foil facet, cell, tile, noise), m.", min=0.002, max=1.0)
    slope: float = param(0.1, "Normal perturbation (std of surface slope) of facets/cells/tiles.", min=0.0, max=2.0)
    tint_rgb: tuple[float, float, float] = param((1.0, 1.0, 1.0), "Colour tint for the console's 3D view.", min=0.0, max=1.0)
    seed: int = param(0, "Texture seed (added to the mock-up seed and the face index).")


@dataclass(frozen=True)
class PartSpec:
    """One part of a mock-up file (``parts[i]``), in the body frame."""

    name: str = param("", "Part name (face and salient-point names start with it).")
    kind: Literal["box", "panel", "disc"] = param("box", "box (6 faces), panel (thin two-sided rectangle), disc.")
    center: tuple[float, float, float] = param((0.0, 0.0, 0.0), "Part centre in the body frame, m.")
    size: tuple[float, ...] = param(
        (0.1, 0.1, 0.1), "box: (x, y, z) sizes; panel: (width along part x, height along part y); disc: (diameter,), m."
    )
    rotvec_deg: tuple[float, float, float] = param((0.0, 0.0, 0.0), "Part axes' rotation in the body frame (rotation vector), deg.")
    material: str = param("", "Material of every face (front side of panels/discs, whose front normal is part +z).")
    back_material: str = param("", "Material of the back side of a panel or disc (empty: same as material).")
    face_materials: tuple[str, ...] = param((), "box only: 6 materials for faces +x, -x, +y, -y, +z, -z (empty: material).")
    label: str = param("", "Text printed on the front face (box: the +z face... see label_face).")
    label_face: str = param("+z", "box only: the face the label goes on.", choices=BOX_FACES)
    salient: bool = param(False, "Export this part's corners (disc: centre) as salient model points.")


@dataclass(frozen=True)
class MockupSpec:
    """Top level of a mock-up file."""

    name: str = param("mockup", "Mock-up name.")
    texel_m: float = param(0.003, "Texel size of the finest texture level, m.", min=0.0005, max=0.05)
    seed: int = param(0, "Seed of the procedural textures.")
    materials: tuple[MaterialSpec, ...] = param((), "Materials.")
    parts: tuple[PartSpec, ...] = param((), "Parts.")


# --------------------------------------------------------------------------- faces


@dataclass(frozen=True, eq=False)
class TextureLevel:
    """One mip level of one side of a face; all arrays (nv, nu) float32.

    ``albedo_pm`` is albedo premultiplied by ``alpha``; ``normal`` (nv,nu,3) the perturbed unit
    normal's components along ``e_u``, ``e_v`` and the side's outward normal; ``spec_pm`` the
    specular strength premultiplied by ``alpha``.
    """

    albedo_pm: F32
    alpha: F32
    normal: F32
    spec_pm: F32

    @property
    def shape(self) -> tuple[int, int]:
        return self.alpha.shape


@dataclass(frozen=True, eq=False)
class Surface:
    """One side of a face: its material and mip pyramid (level 0 the finest)."""

    material: MaterialSpec
    levels: tuple[TextureLevel, ...]

    @property
    def sharpness(self) -> float:
        return self.material.sharpness


@dataclass(frozen=True, eq=False)
class Face:
    """A planar rectangle ``origin + x e_u + y e_v``, ``0 <= x <= w``, ``0 <= y <= h`` (body frame, m).

    ``normal = e_u x e_v`` is the front side's outward normal; ``back`` is the other side's
    surface for thin two-sided parts (None for closed boxes: their inner side is never seen).
    ``outline`` (K,2) is the face's shape in local metres (a rectangle, or a polygon for discs)
    used for shadows and picking.
    """

    name: str
    origin: FloatArray
    e_u: FloatArray
    e_v: FloatArray
    size_m: tuple[float, float]
    front: Surface
    back: Surface | None
    outline: FloatArray
    part: str = ""

    @property
    def normal(self) -> FloatArray:
        return np.cross(self.e_u, self.e_v)

    @cached_property
    def outline_body(self) -> FloatArray:
        """(K,3) outline vertices in the body frame, m."""
        return self.origin + self.outline[:, :1] * self.e_u + self.outline[:, 1:] * self.e_v

    def body_point(self, xy_local: FloatArray) -> FloatArray:
        """Body-frame points (N,3) of face-local points (N,2), m."""
        xy = np.asarray(xy_local, dtype=float).reshape(-1, 2)
        return self.origin + xy[:, :1] * self.e_u + xy[:, 1:] * self.e_v


@dataclass(frozen=True, eq=False)
class Mockup:
    """A satellite mock-up: planar textured faces in the body frame and named salient points.

    Build it with :func:`load_mockup`. ``salient_points`` are ``(name, xyz_body_m)`` pairs for a
    case-(b) ``model.yaml``.
    """

    name: str
    texel_m: float
    faces: tuple[Face, ...]
    salient_points: tuple[tuple[str, FloatArray], ...] = ()
    spec: MockupSpec = field(default_factory=MockupSpec, repr=False)

    @cached_property
    def radius_m(self) -> float:
        """Radius of the smallest origin-centred sphere holding every face, m."""
        return float(max(np.linalg.norm(f.outline_body, axis=1).max() for f in self.faces))

    def to_trimesh_arrays(self) -> tuple[NDArray[np.float32], NDArray[np.int32], NDArray[np.uint8]]:
        """A triangle mesh for a 3D view (e.g. viser ``scene.add_mesh_simple``).

        Returns:
            vertices (V,3) float32 body frame m, faces (F,3) int32 (counter-clockwise seen from
            the front), colours (F,3) uint8 RGB per triangle (material tint x albedo, so one
            colour per material).
            Two-sided faces get a second, reversed copy for their back.
        """
        verts: list[FloatArray] = []
        tris: list[NDArray[np.int32]] = []
        cols: list[NDArray[np.uint8]] = []
        n = 0
        for face in self.faces:
            poly = face.outline_body
            k = len(poly)
            fan = np.array([[0, i, i + 1] for i in range(1, k - 1)], dtype=np.int32)
            sides = [(face.front, fan)] + ([(face.back, fan[:, ::-1])] if face.back is not None else [])
            for surface, idx in sides:
                verts.append(poly)
                tris.append(idx + n)
                # one colour per material (the console draws one mesh per colour)
                grey = np.clip(0.25 + 1.2 * surface.material.albedo, 0.0, 1.0)
                rgb = np.clip(255.0 * grey * np.asarray(surface.material.tint_rgb), 0, 255).astype(np.uint8)
                cols.append(np.repeat(rgb[None, :], len(idx), axis=0))
                n += k
        return (
            np.concatenate(verts).astype(np.float32),
            np.concatenate(tris).astype(np.int32),
            np.concatenate(cols).astype(np.uint8),
        )


def rect_face(
    name: str,
    center: FloatArray,
    e_u: FloatArray,
    e_v: FloatArray,
    front: Surface,
    back: Surface | None = None,
    texel_m: float | None = None,
) -> Face:
    """A rectangular face centred at ``center`` (body frame, m) with unit in-plane axes ``e_u``,
    ``e_v`` (front normal ``e_u x e_v``) covered by ``front``'s texture, ``texel_m`` per texel
    (the face is ``nu * texel_m`` by ``nv * texel_m``). For tests and custom scenes."""
    nv, nu = front.levels[0].shape
    t = texel_m if texel_m is not None else 0.003
    w, h = nu * t, nv * t
    e_u, e_v = np.asarray(e_u, float), np.asarray(e_v, float)
    return Face(
        name=name,
        origin=np.asarray(center, float) - 0.5 * w * e_u - 0.5 * h * e_v,
        e_u=e_u,
        e_v=e_v,
        size_m=(w, h),
        front=front,
        back=back,
        outline=np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]]),
        part=name,
    )


# --------------------------------------------------------------------------- loading


def load_mockup(path: str | Path) -> Mockup:
    """Read and validate a mock-up file and build its faces and textures.

    Raises:
        TrackmeterError: unreadable file, unknown key, wrong type or range, unknown material,
            wrong ``size`` length for the part kind, degenerate sizes — the message names the key.
    """
    path = Path(path)
    spec: MockupSpec = build_dataclass(MockupSpec, read_yaml_mapping(path, kind="a mock-up file"), source=str(path))
    return build_mockup(spec, source=str(path))


def build_mockup(spec: MockupSpec, source: str = "mockup") -> Mockup:
    """Build a :class:`Mockup` from a validated :class:`MockupSpec`."""
    materials: dict[str, MaterialSpec] = {}
    for i, m in enumerate(spec.materials):
        if not m.name:
            raise TrackmeterError(f"{source}: 'materials[{i}].name' must not be empty")
        if m.name in materials:
            raise TrackmeterError(f"{source}: 'materials[{i}].name': duplicate material {m.name!r}")
        materials[m.name] = m
    if not spec.parts:
        raise TrackmeterError(f"{source}: 'parts' must list at least one part")

    def material(name: str, key: str) -> MaterialSpec:
        if name not in materials:
            known = ", ".join(sorted(materials)) or "none"
            raise TrackmeterError(f"{source}: '{key}': unknown material {name!r} (known: {known})")
        return materials[name]

    faces: list[Face] = []
    salient: list[tuple[str, FloatArray]] = []
    names: set[str] = set()
    for i, part in enumerate(spec.parts):
        key = f"parts[{i}]"
        if not part.name or part.name in names:
            raise TrackmeterError(f"{source}: '{key}.name': must be a unique non-empty name, got {part.name!r}")
        names.add(part.name)
        want = {"box": 3, "panel": 2, "disc": 1}[part.kind]
        if len(part.size) != want or min(part.size) <= 0:
            raise TrackmeterError(f"{source}: '{key}.size': a {part.kind} needs {want} positive sizes, got {list(part.size)}")
        front = material(part.material, f"{key}.material")
        R = Rotation.from_rotvec(np.radians(part.rotvec_deg)).as_matrix()
        c = np.asarray(part.center, dtype=float)
        seed0 = spec.seed * 1000 + i * 17
        if part.kind == "box":
            if part.face_materials and len(part.face_materials) != 6:
                raise TrackmeterError(f"{source}: '{key}.face_materials': needs 6 names (+x, -x, +y, -y, +z, -z) or none")
            mats = [material(m, f"{key}.face_materials[{j}]") for j, m in enumerate(part.face_materials)] or [front] * 6
            half = 0.5 * np.asarray(part.size)
            for j, tag in enumerate(BOX_FACES):
                axis = "xyz".index(tag[1])
                sign = 1.0 if tag[0] == "+" else -1.0
                n = sign * R[:, axis]
                # in-face axes chosen so that e_u x e_v = n (right-handed, outward normal)
                a1, a2 = (axis + 1) % 3, (axis + 2) % 3
                e_u, e_v = R[:, a1], R[:, a2] * sign
                w, h = 2 * half[a1], 2 * half[a2]
                origin = c + n * half[axis] - 0.5 * w * e_u - 0.5 * h * e_v
                label = part.label if part.label and tag == part.label_face else ""
                faces.append(
                    _make_face(f"{part.name}{tag}", origin, e_u, e_v, (w, h), mats[j], None, "rect", spec.texel_m, seed0 + j, label, part.name)
                )
            if part.salient:
                for sx in (1, -1):
                    for sy in (1, -1):
                        for sz in (1, -1):
                            tag = "".join(("p" if s > 0 else "m") + ax for s, ax in zip((sx, sy, sz), "xyz"))
                            salient.append((f"{part.name}_{tag}", c + R @ (half * (sx, sy, sz))))
        else:
            back = material(part.back_material, f"{key}.back_material") if part.back_material else front
            if part.kind == "panel":
                w, h = part.size
                shape = "rect"
            else:
                w = h = part.size[0]
                shape = "disc"
            e_u, e_v = R[:, 0], R[:, 1]
            origin = c - 0.5 * w * e_u - 0.5 * h * e_v
            face = _make_face(part.name, origin, e_u, e_v, (w, h), front, back, shape, spec.texel_m, seed0, part.label, part.name)
            faces.append(face)
            if part.salient:
                if shape == "disc":
                    salient.append((f"{part.name}_centre", c.copy()))
                else:
                    for k, p in enumerate(face.outline_body):
                        salient.append((f"{part.name}_c{k}", p.copy()))
    return Mockup(name=spec.name, texel_m=spec.texel_m, faces=tuple(_drop_hidden(faces)), salient_points=tuple(salient), spec=spec)


def _drop_hidden(faces: list[Face]) -> list[Face]:
    """Drop one-sided faces lying flat against another part's face, facing into it (a thruster's
    top against the bus): they can never be seen, and drawing them would only cost time."""
    keep = []
    for f in faces:
        hidden = False
        if f.back is None:
            for g in faces:
                if g.part == f.part or g.normal @ f.normal > -0.999:
                    continue
                corners = f.outline_body
                if np.abs((corners - g.origin) @ g.normal).max() > 1e-4:
                    continue
                x, y = (corners - g.origin) @ g.e_u, (corners - g.origin) @ g.e_v
                if x.min() >= -1e-6 and y.min() >= -1e-6 and x.max() <= g.size_m[0] + 1e-6 and y.max() <= g.size_m[1] + 1e-6:
                    hidden = True
                    break
        if not hidden:
            keep.append(f)
    return keep


def _make_face(
    name: str,
    origin: FloatArray,
    e_u: FloatArray,
    e_v: FloatArray,
    size: tuple[float, float],
    front: MaterialSpec,
    back: MaterialSpec | None,
    shape: str,
    texel_m: float,
    seed: int,
    label: str,
    part: str = "",
) -> Face:
    w, h = float(size[0]), float(size[1])
    nu, nv = max(2, int(round(w / texel_m))), max(2, int(round(h / texel_m)))
    alpha = np.ones((nv, nu), np.float32)
    if shape == "disc":
        # analytic coverage of the circle, 1-texel soft edge centred on the true rim
        x = (np.arange(nu) + 0.5) * (w / nu) - 0.5 * w
        y = (np.arange(nv) + 0.5) * (h / nv) - 0.5 * h
        r = np.hypot(x[None, :], y[:, None])
        alpha = np.clip(0.5 + (0.5 * w - r) / (w / nu), 0.0, 1.0).astype(np.float32)
        ang = np.linspace(0, 2 * np.pi, 32, endpoint=False)
        outline = np.column_stack([0.5 * w + 0.5 * w * np.cos(ang), 0.5 * h + 0.5 * h * np.sin(ang)])
    else:
        outline = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])
    px_m = w / nu
    fr = _surface(front, (nv, nu), px_m, alpha, seed + 1000 * front.seed, label)
    bk = _surface(back, (nv, nu), px_m, alpha, seed + 500 + 1000 * back.seed, "") if back is not None else None
    return Face(
        name=name,
        origin=np.asarray(origin, float),
        e_u=np.asarray(e_u, float),
        e_v=np.asarray(e_v, float),
        size_m=(w, h),
        front=fr,
        back=bk,
        outline=outline,
        part=part,
    )


# --------------------------------------------------------------------------- procedural textures


def _surface(mat: MaterialSpec, shape: tuple[int, int], texel_m: float, alpha: F32, seed: int, label: str) -> Surface:
    rng = np.random.default_rng(abs(seed) + 12345)
    albedo, gx, gy, spec = _TEXTURES[mat.kind](mat, shape, texel_m, rng)
    if label:
        _print_label(albedo, label, mat.albedo)
    return surface_from_arrays(mat, albedo, alpha, (gx, gy), spec)


def surface_from_arrays(
    material: MaterialSpec,
    albedo: NDArray[np.floating],
    alpha: NDArray[np.floating] | None = None,
    slopes: tuple[NDArray[np.floating], NDArray[np.floating]] | None = None,
    spec: NDArray[np.floating] | None = None,
) -> Surface:
    """A surface (with its mip pyramid) from level-0 texel arrays (nv,nu).

    Args:
        material: gives the specular sharpness (and the defaults below).
        albedo: diffuse reflectance per texel.
        alpha: coverage per texel (default 1).
        slopes: ``(gx, gy)`` surface slopes along ``e_u``, ``e_v``; the perturbed normal is
            ``normalize(-gx, -gy, 1)`` (default flat).
        spec: specular strength per texel (default ``material.specular``).
    """
    albedo = np.clip(np.asarray(albedo, np.float32), 0.0, 1.0)
    shape = albedo.shape
    alpha = np.ones(shape, np.float32) if alpha is None else np.asarray(alpha, np.float32)
    gx, gy = (np.zeros(shape, np.float32), np.zeros(shape, np.float32)) if slopes is None else slopes
    gx, gy = np.asarray(gx, np.float32), np.asarray(gy, np.float32)
    spec = np.full(shape, material.specular, np.float32) if spec is None else np.clip(np.asarray(spec, np.float32), 0.0, None)
    inv = 1.0 / np.sqrt(1.0 + gx * gx + gy * gy)
    normal = np.ascontiguousarray(np.dstack([-gx * inv, -gy * inv, inv]).astype(np.float32))
    levels = [TextureLevel(albedo * alpha, alpha, normal, spec * alpha)]
    nv, nu = shape
    while min(nv, nu) >= 8:
        nv, nu = max(2, int(round(nv / 2))), max(2, int(round(nu / 2)))
        prev = levels[0]

        def down(a: F32) -> F32:
            return cast(F32, cv2.resize(a, (nu, nv), interpolation=cv2.INTER_AREA))

        # normals are averaged then renormalised: a coarse level's glints are broader and dimmer
        n_ = down(normal)
        n_ /= np.linalg.norm(n_, axis=2, keepdims=True) + 1e-12
        levels.append(TextureLevel(down(prev.albedo_pm), down(alpha), n_, down(prev.spec_pm)))
    return Surface(material=material, levels=tuple(levels))


def _noise(rng: np.random.Generator, shape: tuple[int, int], sigma_texels: float) -> F32:
    """Gaussian-filtered white noise with unit standard deviation, feature size ~ sigma."""
    n = rng.standard_normal(shape).astype(np.float32)
    # A feature wider than the texture (a part of a few texels) leaves it as flat at twice its
    # size as at any size beyond: the kernel, which grows with sigma, is not built larger.
    sigma_texels = min(sigma_texels, 2.0 * max(shape))
    if sigma_texels > 0.3:
        n = cast(F32, cv2.GaussianBlur(n, (0, 0), sigma_texels, borderType=cv2.BORDER_REFLECT))
    s = float(n.std())
    return n / s if s > 0 else n


def _voronoi(rng: np.random.Generator, shape: tuple[int, int], cell_texels: float) -> tuple[NDArray[np.int32], int]:
    """Voronoi cells of random seeds (labels 0..K-1 per texel), via OpenCV's labelled distance transform."""
    nv, nu = shape
    k = max(2, int(nv * nu / max(cell_texels, 1.0) ** 2))
    img = np.ones(shape, np.uint8)
    img[rng.integers(0, nv, k), rng.integers(0, nu, k)] = 0
    _, labels = cv2.distanceTransformWithLabels(img, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
    labels = labels.astype(np.int32) - 1
    return labels, int(labels.max()) + 1


def _cell_edges(labels: NDArray[np.int32]) -> F32:
    e = np.zeros(labels.shape, np.float32)
    e[:, 1:] += labels[:, 1:] != labels[:, :-1]
    e[1:, :] += labels[1:, :] != labels[:-1, :]
    return np.minimum(e, 1.0)


def _tex_mli(m: MaterialSpec, shape: tuple[int, int], t: float, rng: np.random.Generator) -> _Texture:
    """Crinkled multi-layer insulation: faceted foil (Voronoi facets with random tilts), wrinkles
    along random creases, seams of tape along the edges."""
    nv, nu = shape
    cell = m.feature_m / t
    labels, k = _voronoi(rng, shape, cell)
    gx = rng.normal(0.0, m.slope, k).astype(np.float32)[labels]
    gy = rng.normal(0.0, m.slope, k).astype(np.float32)[labels]
    # large soft wrinkles: gradient of a smooth height field
    hgt = _noise(rng, shape, 2.5 * cell) * (m.slope * 2.5 * cell)
    gx += cast(F32, cv2.Sobel(hgt, cv2.CV_32F, 1, 0, ksize=3)) / 8.0
    gy += cast(F32, cv2.Sobel(hgt, cv2.CV_32F, 0, 1, ksize=3)) / 8.0
    facet = rng.normal(0.0, 1.0, k).astype(np.float32)[labels]
    albedo = m.albedo * (1.0 + m.albedo_variation * facet + 0.25 * m.albedo_variation * _noise(rng, shape, 0.3 * cell))
    albedo *= 1.0 - 0.35 * _cell_edges(labels)  # creases
    # long straight creases across the blanket
    for _ in range(max(2, int(nu * nv / (12 * cell) ** 2))):
        p0 = (int(rng.integers(0, nu)), int(rng.integers(0, nv)))
        ang = rng.uniform(0, np.pi)
        ln = rng.uniform(4, 12) * cell
        p1 = (int(p0[0] + ln * np.cos(ang)), int(p0[1] + ln * np.sin(ang)))
        cv2.line(albedo, p0, p1, float(0.55 * m.albedo), 1, cv2.LINE_AA)
    spec = np.full(shape, m.specular, np.float32)
    # tape seams along the blanket's edges: smoother, a different shade
    band = max(2, int(round(0.02 / t)))
    edge = np.zeros(shape, bool)
    edge[:band, :] = edge[-band:, :] = True
    edge[:, :band] = edge[:, -band:] = True
    albedo[edge] = (0.7 * m.albedo + 0.1 * _noise(rng, shape, 1.0) * m.albedo)[edge]
    gx[edge] *= 0.3
    gy[edge] *= 0.3
    spec[edge] *= 0.5
    return albedo, gx, gy, spec


def _tex_solar(m: MaterialSpec, shape: tuple[int, int], t: float, rng: np.random.Generator) -> _Texture:
    """Solar array: a grid of multicrystalline cells (grain texture, busbars) under cover glass
    (per-cell tilt → cell-wise glints), white gaps, an aluminium frame."""
    nv, nu = shape
    cu = max(6, int(round(m.feature_m / t)))
    cv_ = max(6, int(round(1.5 * m.feature_m / t)))
    jj, ii = np.mgrid[0:nv, 0:nu]
    frame = max(2, int(round(0.015 / t)))
    ci, cj = (ii - frame) // cu, (jj - frame) // cv_
    lu, lv = (ii - frame) % cu, (jj - frame) % cv_
    ncu, ncv = max(1, (nu - 2 * frame) // cu), max(1, (nv - 2 * frame) // cv_)
    cell_id = np.clip(cj, 0, ncv) * (ncu + 1) + np.clip(ci, 0, ncu)
    ncell = (ncu + 1) * (ncv + 1)
    grains, kg = _voronoi(rng, shape, 0.012 / t)
    albedo = m.albedo * (
        1.0
        + m.albedo_variation * rng.normal(0, 1, ncell).astype(np.float32)[cell_id]
        + 0.8 * m.albedo_variation * rng.normal(0, 1, kg).astype(np.float32)[grains]
    )
    busbar = (np.abs(lu - cu // 3) < 1) | (np.abs(lu - 2 * cu // 3) < 1)
    albedo = np.where(busbar, 0.45, albedo)
    gap = (lu == cu - 1) | (lv == cv_ - 1)
    albedo = np.where(gap, 0.6, albedo)
    gx = rng.normal(0, m.slope, ncell).astype(np.float32)[cell_id]
    gy = rng.normal(0, m.slope, ncell).astype(np.float32)[cell_id]
    spec = np.where(gap | busbar, 0.2 * m.specular, m.specular).astype(np.float32)
    border = (ii < frame) | (jj < frame) | (ii >= frame + ncu * cu) | (jj >= frame + ncv * cv_)
    albedo = np.where(border, 0.5 + 0.05 * _noise(rng, shape, 1.0), albedo)
    gx = np.where(border, 0.0, gx).astype(np.float32)
    gy = np.where(border, 0.0, gy).astype(np.float32)
    spec = np.where(border, 0.3 * m.specular, spec).astype(np.float32)
    return albedo.astype(np.float32), gx, gy, spec


def _tex_radiator(m: MaterialSpec, shape: tuple[int, int], t: float, rng: np.random.Generator) -> _Texture:
    """Radiator of optical solar reflector tiles: near-black mirrors (each slightly tilted, so
    they flash one by one), white grout, bolt heads; blotches where the paint is stained."""
    nv, nu = shape
    tile = max(5, int(round(m.feature_m / t)))
    jj, ii = np.mgrid[0:nv, 0:nu]
    tid = (jj // tile) * (nu // tile + 1) + ii // tile
    nt = int(tid.max()) + 1
    lu, lv = ii % tile, jj % tile
    albedo = m.albedo * (1.0 + m.albedo_variation * rng.normal(0, 1, nt).astype(np.float32)[tid])
    albedo = albedo * (1.0 + 0.3 * m.albedo_variation * _noise(rng, shape, 0.01 / t))
    grout = (lu == 0) | (lv == 0)
    albedo = np.where(grout, 0.7, albedo)
    gx = rng.normal(0, m.slope, nt).astype(np.float32)[tid]
    gy = rng.normal(0, m.slope, nt).astype(np.float32)[tid]
    spec = np.where(grout, 0.05 * m.specular, m.specular).astype(np.float32)
    bolts = rng.random(nt) < 0.3
    bolt = bolts[tid] & (np.hypot(lu - tile / 2, lv - tile / 2) < max(1.2, 0.004 / t))
    albedo = np.where(bolt, 0.25, albedo)
    return albedo.astype(np.float32), gx.astype(np.float32), gy.astype(np.float32), spec


def _tex_paint(m: MaterialSpec, shape: tuple[int, int], t: float, rng: np.random.Generator) -> _Texture:
    """Painted surface: mottled, with concentric rings and radial ribs (a dish's reflector)."""
    nv, nu = shape
    y, x = np.mgrid[0:nv, 0:nu].astype(np.float32)
    r = np.hypot(x - nu / 2, y - nv / 2) * t
    ang = np.arctan2(y - nv / 2, x - nu / 2)
    albedo = m.albedo * (1.0 + m.albedo_variation * _noise(rng, shape, m.feature_m / t / 3))
    albedo *= 1.0 + 0.5 * m.albedo_variation * _noise(rng, shape, 1.0)
    rings = np.abs(((r / m.feature_m) % 1.0) - 0.5) < (1.2 * t / m.feature_m)
    ribs = np.abs(((ang * 8 / np.pi) % 1.0) - 0.5) * r < 0.7 * t * 8 / np.pi
    albedo = np.where(rings | ribs, 0.6 * m.albedo, albedo)
    hgt = _noise(rng, shape, m.feature_m / t) * m.slope * m.feature_m / t
    gx = cast(F32, cv2.Sobel(hgt, cv2.CV_32F, 1, 0, ksize=3)) / 8.0
    gy = cast(F32, cv2.Sobel(hgt, cv2.CV_32F, 0, 1, ksize=3)) / 8.0
    spec = np.full(shape, m.specular, np.float32)
    return albedo.astype(np.float32), gx, gy, spec


def _tex_metal(m: MaterialSpec, shape: tuple[int, int], t: float, rng: np.random.Generator) -> _Texture:
    """Brushed metal: streaks along u, rivets, slight waviness."""
    nv, nu = shape
    streak = rng.standard_normal(shape).astype(np.float32)
    streak = cast(F32, cv2.GaussianBlur(streak, (0, 0), sigmaX=max(1.0, m.feature_m / t), sigmaY=0.5))
    streak /= float(streak.std()) + 1e-9
    albedo = m.albedo * (1.0 + m.albedo_variation * streak + 0.5 * m.albedo_variation * _noise(rng, shape, m.feature_m / t / 2))
    step = max(4, int(round(0.05 / t)))
    for j in range(step // 2, nv, step):
        for i in (step // 2, nu - 1 - step // 2):
            if 0 <= i < nu:
                cv2.circle(albedo, (i, j), max(1, int(0.004 / t)), float(0.4 * m.albedo), -1, cv2.LINE_AA)
    hgt = _noise(rng, shape, m.feature_m / t) * m.slope * m.feature_m / t
    gx = cast(F32, cv2.Sobel(hgt, cv2.CV_32F, 1, 0, ksize=3)) / 8.0
    gy = cast(F32, cv2.Sobel(hgt, cv2.CV_32F, 0, 1, ksize=3)) / 8.0
    return albedo.astype(np.float32), gx, gy, np.full(shape, m.specular, np.float32)


def _tex_plain(m: MaterialSpec, shape: tuple[int, int], t: float, rng: np.random.Generator) -> _Texture:
    """Uniform albedo with optional fine noise (variation 0: exactly uniform)."""
    albedo = np.full(shape, m.albedo, np.float32)
    if m.albedo_variation > 0:
        albedo *= 1.0 + m.albedo_variation * _noise(rng, shape, m.feature_m / t)
    zero = np.zeros(shape, np.float32)
    return albedo, zero, zero.copy(), np.full(shape, m.specular, np.float32)


_TEXTURES = {
    "mli": _tex_mli,
    "solar": _tex_solar,
    "radiator": _tex_radiator,
    "paint": _tex_paint,
    "metal": _tex_metal,
    "plain": _tex_plain,
}


def _print_label(albedo: F32, text: str, base: float) -> None:
    """Print ``text`` in dark letters across the middle of a texture (in place)."""
    nv, nu = albedo.shape
    font = cv2.FONT_HERSHEY_DUPLEX
    (tw, th), _ = cv2.getTextSize(text, font, 1.0, 2)
    scale = 0.6 * nu / max(tw, 1)
    thick = max(1, int(round(2 * scale)))
    (tw, th), _ = cv2.getTextSize(text, font, scale, thick)
    org = (int((nu - tw) / 2), int((nv + th) / 2))
    ink = np.zeros(albedo.shape, np.uint8)  # putText draws only into 8-bit images
    cv2.putText(ink, text, org, font, scale, 255, thick, cv2.LINE_AA)
    a = ink.astype(np.float32) / 255.0
    albedo *= 1.0 - a
    albedo += a * float(0.15 * base)
