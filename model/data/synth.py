"""A procedural chair category for tests and quick demos.

Each chair is assembled from boxes and cylinders in the Z-up world, its front facing -Y:

- legs: four square legs (thin or thick), four round legs, or a central pedestal on a disc;
- a seat, which may carry a striped or checkered texture (a small image mapped with UVs);
- a back, low or tall, slightly reclined: solid (sharing the seat's texture), slatted
  (vertical slats between two posts) or ladder (horizontal rails between two posts);
- optional arms (rests on front supports).

Colours come from the named palette of :mod:`model.data.colours` so captions can name them; the caption is built from the same
attributes (e.g. "a red chair with white stripes on the seat, four thin black legs, a tall
slatted back and arms"), which are also kept in ``index.json`` under ``"attributes"``.

Chair ``i`` of seed ``s`` depends only on ``(s, i)`` (numpy's seeded ``Generator``), so a run is
reproducible and asking for more objects keeps the first ones unchanged.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import asdict, dataclass

import numpy as np
import trimesh

from model.data.build import SourceObject
from model.data.colours import PALETTE
from model.data.meshes import Material, RenderMesh, concatenate, solid_mesh

CATEGORY = "chair"

SEAT_COLOURS = ("red", "orange", "yellow", "green", "teal", "blue", "purple", "pink", "brown", "black", "white", "grey")
FRAME_COLOURS = ("black", "brown", "grey", "white")
LEG_STYLES = ("thin", "thick", "round", "pedestal")
BACK_STYLES = ("solid", "slatted", "ladder")
PATTERNS = ("plain", "stripes", "checker")

# Size of one texture tile in world units, so patterns have the same density on every part.
_TILE = 0.12
_TEXTURE_SIZE = 32
_CYLINDER_SECTIONS = 20


@dataclass
class ChairSpec:
    """The attributes of one chair; lengths in world units before normalisation (roughly metres)."""

    seat_colour: str
    frame_colour: str
    pattern: str
    pattern_colour: str
    leg_style: str
    back_style: str
    tall_back: bool
    arms: bool
    seat_width: float
    seat_depth: float
    seat_height: float
    seat_thickness: float
    leg_size: float
    back_height: float
    back_tilt_deg: float
    slats: int


def sample_spec(rng: np.random.Generator) -> ChairSpec:
    """Draw one chair's attributes."""
    seat_colour = str(rng.choice(SEAT_COLOURS))
    frame_colour = seat_colour if rng.random() < 0.3 else str(rng.choice(FRAME_COLOURS))
    pattern = str(rng.choice(PATTERNS, p=[0.5, 0.25, 0.25]))
    pattern_colour = str(rng.choice([c for c in ("white", "black", "yellow", "blue") if c != seat_colour]))
    leg_style = str(rng.choice(LEG_STYLES))
    back_style = str(rng.choice(BACK_STYLES))
    tall_back = bool(rng.random() < 0.5)
    leg_size = rng.uniform(0.05, 0.07) if leg_style == "thick" else rng.uniform(0.025, 0.038)
    return ChairSpec(
        seat_colour=seat_colour,
        frame_colour=frame_colour,
        pattern=pattern,
        pattern_colour=pattern_colour,
        leg_style=leg_style,
        back_style=back_style,
        tall_back=tall_back,
        arms=bool(rng.random() < 0.35),
        seat_width=float(rng.uniform(0.40, 0.58)),
        seat_depth=float(rng.uniform(0.38, 0.52)),
        seat_height=float(rng.uniform(0.36, 0.50)),
        seat_thickness=float(rng.uniform(0.03, 0.08)),
        leg_size=float(leg_size),
        back_height=float(rng.uniform(0.42, 0.58) if tall_back else rng.uniform(0.20, 0.30)),
        back_tilt_deg=float(rng.uniform(0.0, 14.0)),
        slats=int(rng.integers(3, 6)),
    )


def caption(spec: ChairSpec) -> str:
    """A sentence describing the chair from its attributes."""
    frame = "" if spec.frame_colour == spec.seat_colour else f"{spec.frame_colour} "
    legs = {
        "thin": f"four thin {frame}legs",
        "thick": f"four thick square {frame}legs",
        "round": f"four round {frame}legs",
        "pedestal": f"a {frame}central pedestal",
    }[spec.leg_style]
    back = f"a {'tall' if spec.tall_back else 'low'} {spec.back_style} back"
    parts = [legs, back] + (["arms"] if spec.arms else [])
    if spec.pattern != "plain":
        pattern = f"{spec.pattern_colour} stripes" if spec.pattern == "stripes" else f"a {spec.pattern_colour} checker pattern"
        parts.insert(0, f"{pattern} on the seat and back")
    listed = ", ".join(parts[:-1]) + " and " + parts[-1]
    return f"a {spec.seat_colour} chair with {listed}"


def pattern_texture(pattern: str, base: str, second: str, size: int = _TEXTURE_SIZE) -> np.ndarray | None:
    """A tileable RGBA float texture for a seat pattern, or ``None`` for plain colour."""
    if pattern == "plain":
        return None
    j, i = np.meshgrid(np.arange(size), np.arange(size), indexing="ij")
    half = size // 2
    mask = (i < half) if pattern == "stripes" else ((i < half) ^ (j < half))
    colours = np.where(mask[..., None], PALETTE[base], PALETTE[second])
    return np.concatenate([colours, np.ones((size, size, 1))], axis=-1).astype(np.float32)


def _colour(name: str) -> np.ndarray:
    return np.array([*PALETTE[name], 1.0])


def box(size, centre, material: Material) -> RenderMesh:
    """An axis-aligned box with four corners per face and UVs in world units divided by the tile size."""
    size, centre = np.asarray(size, dtype=np.float64), np.asarray(centre, dtype=np.float64)
    vertices, faces, uvs = [], [], []
    for axis in range(3):
        u_axis, v_axis = [a for a in range(3) if a != axis]
        for sign in (-1.0, 1.0):
            corners = []
            for du, dv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                offset = np.zeros(3)
                offset[axis], offset[u_axis], offset[v_axis] = sign, du, dv
                corners.append(centre + 0.5 * size * offset)
            base = len(vertices)
            vertices.extend(corners)
            uvs.extend([(c[u_axis] / _TILE, c[v_axis] / _TILE) for c in corners])
            faces.extend([(base, base + 1, base + 2), (base, base + 2, base + 3)])
    faces = np.array(faces)
    return solid_mesh(np.array(vertices), faces, material, np.array(uvs)[faces])


def cylinder(radius: float, z0: float, z1: float, xy, material: Material) -> RenderMesh:
    """A vertical cylinder from ``z0`` to ``z1`` centred on ``xy``."""
    shape = trimesh.creation.cylinder(radius=radius, height=z1 - z0, sections=_CYLINDER_SECTIONS)
    vertices = shape.vertices + np.array([xy[0], xy[1], 0.5 * (z0 + z1)])
    return solid_mesh(vertices, shape.faces, material)


def _legs(spec: ChairSpec, frame: Material) -> list[RenderMesh]:
    h = spec.seat_height
    if spec.leg_style == "pedestal":
        column = max(spec.leg_size, 0.035)
        base_radius = 0.45 * min(spec.seat_width, spec.seat_depth)
        return [cylinder(base_radius, 0.0, 0.03, (0, 0), frame), cylinder(column, 0.03, h, (0, 0), frame)]
    s = spec.leg_size
    x, y = 0.5 * spec.seat_width - s, 0.5 * spec.seat_depth - s
    corners = [(sx * x, sy * y) for sx in (-1, 1) for sy in (-1, 1)]
    if spec.leg_style == "round":
        return [cylinder(0.5 * s, 0.0, h, c, frame) for c in corners]
    return [box((s, s, h), (cx, cy, 0.5 * h), frame) for cx, cy in corners]


def _back(spec: ChairSpec, seat: Material, frame: Material) -> list[RenderMesh]:
    """Back parts in a frame whose origin is the back edge of the seat top (before reclining)."""
    w, bh, t = spec.seat_width, spec.back_height, 0.04
    y = -0.5 * t
    if spec.back_style == "solid":
        return [box((w, t, bh), (0, y, 0.5 * bh), seat)]
    post, rail = 0.04, 0.06
    inner = w - 2 * post
    parts = [box((post, t, bh), (sx * 0.5 * (w - post), y, 0.5 * bh), frame) for sx in (-1, 1)]
    parts.append(box((inner, t, rail), (0, y, bh - 0.5 * rail), seat))
    if spec.back_style == "slatted":
        slat = 0.6 * inner / (2 * spec.slats)
        xs = np.linspace(-0.5 * inner, 0.5 * inner, spec.slats + 2)[1:-1]
        parts += [box((slat, 0.6 * t, bh - rail), (x, y, 0.5 * (bh - rail)), seat) for x in xs]
    else:
        zs = np.linspace(0.0, bh - rail, spec.slats + 1)[1:-1]
        parts += [box((inner, 0.6 * t, 0.035), (0, y, z), seat) for z in zs]
    return parts


def _arms(spec: ChairSpec, frame: Material) -> list[RenderMesh]:
    top = spec.seat_height + spec.seat_thickness
    rest_z, size = top + 0.2, 0.045
    x = 0.5 * spec.seat_width - 0.5 * size
    front, back = -0.5 * spec.seat_depth + 0.02, 0.5 * spec.seat_depth
    parts = []
    for sx in (-1, 1):
        parts.append(box((size, back - front, 0.03), (sx * x, 0.5 * (front + back), rest_z), frame))
        parts.append(box((size * 0.8, size * 0.8, rest_z - top), (sx * x, front + size, 0.5 * (top + rest_z)), frame))
    return parts


def chair_mesh(spec: ChairSpec) -> RenderMesh:
    """The chair described by ``spec``, Z-up, front towards -Y, standing on z = 0."""
    seat_mat = Material(
        "seat", _colour(spec.seat_colour) if spec.pattern == "plain" else np.ones(4),
        pattern_texture(spec.pattern, spec.seat_colour, spec.pattern_colour),
    )
    frame_mat = Material("frame", _colour(spec.frame_colour))
    top = spec.seat_height + spec.seat_thickness
    seat = box((spec.seat_width, spec.seat_depth, spec.seat_thickness), (0, 0, spec.seat_height + 0.5 * spec.seat_thickness), seat_mat)
    tilt = math.radians(spec.back_tilt_deg)
    # Recline: rotate about the seat's back edge so the top of the back moves towards +Y.
    recline = np.array([[1, 0, 0], [0, math.cos(tilt), math.sin(tilt)], [0, -math.sin(tilt), math.cos(tilt)]])
    hinge = np.array([0.0, 0.5 * spec.seat_depth, top])
    back = [part.transformed(recline, hinge) for part in _back(spec, seat_mat, frame_mat)]
    parts = [seat, *_legs(spec, frame_mat), *back, *(_arms(spec, frame_mat) if spec.arms else [])]
    return concatenate(parts)


def synth_objects(count: int, seed: int) -> Iterator[SourceObject]:
    """``count`` procedural chairs for :func:`model.data.build.build_dataset`."""
    if count < 1:
        raise ValueError(f"--objects must be at least 1, got {count}")
    for index in range(count):
        spec = sample_spec(np.random.default_rng([seed, index]))
        yield SourceObject(
            id=f"synth-{seed}-{index:04d}",
            category=CATEGORY,
            caption=caption(spec),
            load=lambda spec=spec: (chair_mesh(spec), {}),
            extra={"source": "synth", "seed": seed, "texture": spec.pattern, "attributes": asdict(spec)},
        )
