"""A procedural family of industrial part shapes, for training a front end that finds parts it
has never seen.

Each shape is drawn from one of the kinds that factories hold (turned parts, fasteners, pipe
fittings, bent sheet brackets, gears, castings, plates with holes, flanges, rings), its
dimensions and features drawn from a seeded generator, and built as a solid with manifold3d
(extrusions, revolutions and booleans), so the mesh is watertight by construction. Sizes span
real parts: the longest side is 20 to 130 mm by default; with a larger ``max_mm`` (up to 400) a
share of the shapes (``LARGE_SHARE``) is scaled up to a longest side drawn log-uniformly between
130 mm and ``max_mm``, for part sets that hold large parts (an eye bolt of 193 mm). Meshes are
in millimetres and bbox-centred, as
:mod:`sim.parts` builds the five catalog parts, which stay in the family (``family_shapes``
lists them first).

A family is a function of ``(count, seed)`` alone: shape ``k`` of seed ``s`` is drawn from
``np.random.default_rng([s, k])``, so a family's first shapes are those of any larger family of
the same seed, and tuning families take seeds disjoint from training's.
"""

from __future__ import annotations

from collections.abc import Callable

import manifold3d as mf
import numpy as np
import trimesh

from posefuse.sim.parts import PARTS, _to_trimesh, build_part

SEG = 48  # facets of a full circle: smooth enough at bin distances, cheap to ray-cast


def _rot_x(solid: mf.Manifold) -> mf.Manifold:
    return solid.rotate([90.0, 0.0, 0.0])


def _rot_y(solid: mf.Manifold) -> mf.Manifold:
    return solid.rotate([0.0, 90.0, 0.0])


def _cyl(h: float, r: float, segments: int = SEG, center: bool = False) -> mf.Manifold:
    return mf.Manifold.cylinder(h, r, r, segments, center)


def _box(x: float, y: float, z: float) -> mf.Manifold:
    return mf.Manifold.cube([x, y, z], True)


def _threads(length: float, r_major: float, pitch: float) -> mf.Manifold:
    """A shank along +z from 0 to ``length`` with grooves of ``pitch`` (a revolved saw-tooth)."""
    r_minor = r_major * 0.85
    profile = [(0.0, 0.0), (r_minor, 0.0)]
    for k in range(int((length - 1.0) / pitch)):
        z = 0.5 + k * pitch
        profile += [(r_major, z + pitch * 0.4), (r_minor, z + pitch * 0.8)]
    profile += [(r_minor, length), (0.0, length)]
    return mf.CrossSection([np.array(profile)]).revolve(SEG)


def turned(rng: np.random.Generator) -> mf.Manifold:
    """A shaft, pin, bushing or spacer: a revolved stepped profile, chamfers, maybe a bore."""
    n_steps = int(rng.integers(1, 6))
    length = rng.uniform(20, 120)
    r_max = rng.uniform(5, 30) if length > 50 else rng.uniform(6, 35)
    cuts = np.sort(rng.uniform(0, length, n_steps - 1)) if n_steps > 1 else np.zeros(0)
    edges = np.concatenate([[0.0], cuts, [length]])
    radii = rng.uniform(0.45, 1.0, n_steps) * r_max
    bore = rng.uniform(0.2, 0.6) * radii.min() if rng.random() < 0.4 else 0.0
    profile = [(bore, 0.0)]
    for k in range(n_steps):
        z0, z1, r = edges[k], edges[k + 1], radii[k]
        c = min(r - bore, z1 - z0) * rng.uniform(0.0, 0.3)  # chamfer at the step
        profile += [(r - c, z0), (r, z0 + c), (r, z1)]
    profile += [(bore, length)]
    solid = mf.CrossSection([np.array(profile)]).revolve(SEG)
    if rng.random() < 0.3:  # a cross hole or a flat
        d = rng.uniform(0.15, 0.35) * r_max
        hole = _rot_y(_cyl(4 * r_max, d, 24, True)).translate(
            [0, 0, rng.uniform(0.2, 0.8) * length]
        )
        solid = solid - hole
    elif rng.random() < 0.3:
        solid = solid - _box(4 * r_max, 4 * r_max, length * 2).translate(
            [0, r_max * (2 + rng.uniform(0.6, 0.9) - 1) + r_max, 0]
        )
    return solid


def fastener(rng: np.random.Generator) -> mf.Manifold:
    """A bolt, socket screw, nut or washer, with thread grooves where it has a shank."""
    kind = rng.choice(["hex_bolt", "socket", "nut", "washer", "stud"])
    d = rng.uniform(4, 16)
    if kind == "nut":
        s = d * rng.uniform(1.5, 1.9)
        h = d * rng.uniform(0.5, 1.0)
        return _cyl(h, s / np.sqrt(3), 6, True) - _cyl(h + 2, d / 2, SEG, True)
    if kind == "washer":
        r_out = d * rng.uniform(0.9, 1.6)
        return _cyl(d * rng.uniform(0.1, 0.25), r_out, SEG, True) - _cyl(d, d / 2, SEG, True)
    length = d * rng.uniform(2.0, 8.0)
    shank = _threads(length, d / 2, rng.uniform(0.12, 0.2) * d)
    if kind == "stud":
        return shank
    if kind == "hex_bolt":
        h = d * rng.uniform(0.6, 0.8)
        head = _cyl(h, d * 0.9, 6).translate([0, 0, length])
        if rng.random() < 0.5:  # a washer face under the head
            head = head + _cyl(0.1 * d, d * 0.8).translate([0, 0, length - 0.1 * d])
        return shank + head
    h = d * rng.uniform(0.8, 1.0)
    head = mf.Manifold.cylinder(h, d * 0.75, d * 0.7, SEG).translate([0, 0, length])
    socket = _cyl(h, d * 0.3, 6).translate([0, 0, length + h * 0.4])
    return shank + head - socket


def fitting(rng: np.random.Generator) -> mf.Manifold:
    """A pipe fitting: straight, elbow, tee or cross of tubes, with collars at the ends."""
    kind = rng.choice(["straight", "elbow", "tee", "cross", "y"])
    r_out = rng.uniform(6, 20)
    r_in = r_out * rng.uniform(0.55, 0.8)
    arm = rng.uniform(1.5, 3.5) * r_out
    hex_collar = rng.random() < 0.5
    collar_r = r_out * rng.uniform(1.15, 1.5)
    collar_h = r_out * rng.uniform(0.4, 0.9)
    directions = {
        "straight": [0.0, 180.0],
        "elbow": [0.0, 90.0],
        "tee": [0.0, 90.0, 180.0],
        "cross": [0.0, 90.0, 180.0, 270.0],
        "y": [0.0, 135.0, 225.0],
    }[str(kind)]
    solid = mf.Manifold.sphere(r_out, SEG)
    bores = mf.Manifold.sphere(r_in, SEG)
    for a in directions:
        tube = _rot_y(_cyl(arm, r_out))
        bore = _rot_y(_cyl(arm + 2, r_in))
        collar = _rot_y(_cyl(collar_h, collar_r, 6 if hex_collar else SEG)).translate(
            [arm - collar_h, 0, 0]
        )
        part = tube + collar if rng.random() < 0.8 else tube
        solid = solid + part.rotate([0, 0, a])
        bores = bores + bore.rotate([0, 0, a])
    return solid - bores


def bracket(rng: np.random.Generator) -> mf.Manifold:
    """A bent sheet bracket (L, Z, U or hat profile) with holes or slots in its flanges."""
    kind = rng.choice(["L", "Z", "U", "hat"])
    t = rng.uniform(1.5, 4.0)
    width = rng.uniform(12, 50)
    a, b = rng.uniform(15, 60), rng.uniform(15, 60)
    paths = {
        "L": [(0, b), (0, 0), (a, 0)],
        "Z": [(-a, 0), (0, 0), (0, b), (a * 0.8, b)],
        "U": [(0, b), (0, 0), (a, 0), (a, b)],
        "hat": [(-a * 0.5, 0), (0, 0), (0, b), (a, b), (a, 0), (a * 1.5, 0)],
    }[str(kind)]
    solid = None
    for (x0, y0), (x1, y1) in zip(paths[:-1], paths[1:], strict=True):
        length = float(np.hypot(x1 - x0, y1 - y0))
        angle = float(np.degrees(np.arctan2(y1 - y0, x1 - x0)))
        leg = _box(length + t, t, width).rotate([0, 0, angle])
        leg = leg.translate([(x0 + x1) / 2, (y0 + y1) / 2, 0])
        solid = leg if solid is None else solid + leg
        if rng.random() < 0.7 and length > 4 * t + 6:  # a hole or a slot through this leg
            r = rng.uniform(1.5, min(6.0, width / 4, length / 5))
            hole = _rot_x(_cyl(4 * t, r, 24, True))
            if rng.random() < 0.3:
                hole = mf.Manifold.hull(hole + hole.translate([length * 0.2, 0, 0]))
            hole = hole.rotate([0, 0, angle]).translate(
                [(x0 + x1) / 2, (y0 + y1) / 2, rng.uniform(-0.2, 0.2) * width]
            )
            solid = solid - hole
    return solid


def gear(rng: np.random.Generator) -> mf.Manifold:
    """A spur gear or sprocket: 8 to 40 teeth, a hub, a bore, maybe a keyway or lightening holes."""
    n = int(rng.integers(8, 41))
    r_tip = rng.uniform(12, 55)
    depth = rng.uniform(0.08, 0.18) * r_tip * (1.0 if n < 25 else 0.7)
    r_root = r_tip - depth
    thickness = rng.uniform(4, 20)
    top, flank = rng.uniform(0.2, 0.45), rng.uniform(0.5, 0.7)
    pts = []
    for k in range(n):
        a0, half = 2 * np.pi * k / n, np.pi / n
        for da, r in ((-flank * half, r_root), (-top * half, r_tip), (top * half, r_tip)):
            pts.append((r * np.cos(a0 + da), r * np.sin(a0 + da)))
        for da in np.linspace(flank * half, 2 * half - flank * half, 3)[:-1]:
            pts.append((r_root * np.cos(a0 + da), r_root * np.sin(a0 + da)))
    solid = mf.CrossSection([np.array(pts)]).extrude(thickness).translate([0, 0, -thickness / 2])
    bore = rng.uniform(0.1, 0.3) * r_tip
    if rng.random() < 0.7:
        hub_r = bore + rng.uniform(0.15, 0.3) * r_tip
        solid = solid + _cyl(thickness + rng.uniform(2, 12), hub_r, SEG, True)
    if rng.random() < 0.4 and r_root > 2.5 * bore + 8:
        m = int(rng.integers(3, 7))
        r_hole = rng.uniform(0.1, 0.18) * r_root
        ring = (r_root + bore) / 2 + 2
        for k in range(m):
            a = 2 * np.pi * k / m
            solid = solid - _cyl(thickness * 4, r_hole, 24, True).translate(
                [ring * np.cos(a), ring * np.sin(a), 0]
            )
    solid = solid - _cyl(thickness * 4, bore, SEG, True)
    if rng.random() < 0.4:  # a keyway
        solid = solid - _box(bore * 0.5, bore * 0.8, thickness * 4).translate([0, bore, 0])
    return solid


def casting(rng: np.random.Generator) -> mf.Manifold:
    """A block-like casting: a body with bosses, ribs, a pocket and bolt holes."""
    x, y, z = rng.uniform(20, 100), rng.uniform(15, 70), rng.uniform(8, 50)
    solid = _box(x, y, z)
    for _ in range(int(rng.integers(1, 4))):  # cylindrical bosses on a face
        r = rng.uniform(0.1, 0.3) * min(x, y)
        h = rng.uniform(0.2, 0.8) * z
        px, py = rng.uniform(-0.35, 0.35) * x, rng.uniform(-0.35, 0.35) * y
        boss = _cyl(h, r).translate([px, py, z / 2])
        solid = solid + boss - _cyl(3 * (h + z), r * 0.5, 24, True).translate([px, py, 0])
    if rng.random() < 0.5:  # a rib along x on one side
        rib_h = rng.uniform(0.3, 0.8) * z
        solid = solid + _box(x * 0.9, rng.uniform(2, 5), rib_h).translate([0, y / 2, z / 2])
    if rng.random() < 0.5:  # a pocket
        solid = solid - _box(x * rng.uniform(0.2, 0.5), y * rng.uniform(0.2, 0.5), z).translate(
            [rng.uniform(-0.2, 0.2) * x, rng.uniform(-0.2, 0.2) * y, z * 0.6]
        )
    for sx in (-1, 1):  # bolt holes at the ends
        if rng.random() < 0.6:
            solid = solid - _cyl(
                3 * z, rng.uniform(1.5, 0.12 * min(x, y) + 1.6), 24, True
            ).translate([sx * 0.4 * x, rng.uniform(-0.3, 0.3) * y, 0])
    return solid


def plate(rng: np.random.Generator) -> mf.Manifold:
    """A flat plate, rectangular or round or slotted, with a pattern of holes."""
    t = rng.uniform(2, 10)
    if rng.random() < 0.6:
        x, y = rng.uniform(25, 120), rng.uniform(15, 80)
        solid = _box(x, y, t)
        if rng.random() < 0.5:  # rounded corners
            r = rng.uniform(2, min(x, y) / 4)
            corners = [
                _cyl(t, r, 24, True).translate([sx * (x / 2 - r), sy * (y / 2 - r), 0])
                for sx in (-1, 1)
                for sy in (-1, 1)
            ]
            solid = mf.Manifold.hull(mf.Manifold.batch_boolean(corners, mf.OpType.Add))
        nx, ny = int(rng.integers(1, 4)), int(rng.integers(1, 3))
        r_hole = rng.uniform(1.5, min(x / nx, y / ny) / 5)
        for i in range(nx):
            for j in range(ny):
                if rng.random() < 0.85:
                    px = (i + 0.5) / nx * x * 0.8 - 0.4 * x
                    py = (j + 0.5) / ny * y * 0.8 - 0.4 * y
                    solid = solid - _cyl(3 * t, r_hole, 24, True).translate([px, py, 0])
        if rng.random() < 0.3:  # a slot
            slot = mf.Manifold.hull(
                _cyl(3 * t, r_hole, 24, True)
                + _cyl(3 * t, r_hole, 24, True).translate([x * 0.3, 0, 0])
            )
            solid = solid - slot.translate([-x * 0.15, 0, 0])
        return solid
    r = rng.uniform(15, 60)
    solid = _cyl(t, r, SEG, True) - _cyl(3 * t, r * rng.uniform(0.1, 0.5), SEG, True)
    m = int(rng.integers(3, 9))
    r_hole = rng.uniform(0.05, 0.12) * r
    for k in range(m):
        a = 2 * np.pi * k / m
        solid = solid - _cyl(3 * t, r_hole, 24, True).translate(
            [0.75 * r * np.cos(a), 0.75 * r * np.sin(a), 0]
        )
    return solid


def flange(rng: np.random.Generator) -> mf.Manifold:
    """A pipe flange or bearing housing: a disk with a raised neck, a bore and a bolt circle."""
    r = rng.uniform(18, 60)
    t = rng.uniform(4, 14)
    neck_r = r * rng.uniform(0.35, 0.6)
    neck_h = rng.uniform(0.5, 2.0) * t
    bore = neck_r * rng.uniform(0.5, 0.8)
    sides = SEG if rng.random() < 0.7 else int(rng.choice([4, 6]))
    solid = _cyl(t, r, sides) + _cyl(neck_h + t, neck_r)
    solid = solid - _cyl(3 * (t + neck_h), bore, SEG, True)
    m = int(rng.integers(3, 9))
    for k in range(m):
        a = 2 * np.pi * k / m + np.pi / max(sides, 4)
        rad = (neck_r + r) / 2
        solid = solid - _cyl(3 * t, (r - neck_r) * 0.18, 24, True).translate(
            [rad * np.cos(a), rad * np.sin(a), 0]
        )
    return solid


def ring(rng: np.random.Generator) -> mf.Manifold:
    """A torus-like ring, a spring washer or a round link."""
    major = rng.uniform(8, 40)
    minor = rng.uniform(0.1, 0.3) * major
    section = (
        mf.CrossSection.circle(minor, 24)
        if rng.random() < 0.6
        else mf.CrossSection.square([minor * 2, minor * rng.uniform(0.8, 3)], True)
    )
    solid = section.translate([major, 0]).revolve(SEG)
    if rng.random() < 0.4:  # stretched into a link
        solid = solid.split_by_plane([1, 0, 0], 0.0)[0].translate([major * 0.6, 0, 0]) + (
            solid.split_by_plane([-1, 0, 0], 0.0)[0].translate([-major * 0.6, 0, 0])
        )
        bar = _rot_y(_cyl(major * 1.2, minor * 0.98, 24, True))
        solid = solid + bar.translate([0, major, 0]) + bar.translate([0, -major, 0])
    return solid


KINDS: tuple[tuple[str, Callable[[np.random.Generator], mf.Manifold]], ...] = (
    ("turned", turned),
    ("fastener", fastener),
    ("fitting", fitting),
    ("bracket", bracket),
    ("gear", gear),
    ("casting", casting),
    ("plate", plate),
    ("flange", flange),
    ("ring", ring),
)


MIN_MM, DEFAULT_MAX_MM = 20.0, 130.0
LARGE_SHARE = 0.3  # of the shapes scaled up when max_mm is above DEFAULT_MAX_MM


def family_shape(
    seed: int, index: int, max_mm: float = DEFAULT_MAX_MM
) -> tuple[str, trimesh.Trimesh]:
    """Shape ``index`` of the family of ``seed``: (name, mesh in mm, bbox-centred, watertight).
    Its kind cycles through ``KINDS``; a draw that does not give a sound solid is drawn again.
    With ``max_mm`` above DEFAULT_MAX_MM, a share of the shapes is scaled up (module docstring)
    by a draw of its own stream, so the default family is unchanged."""
    if not DEFAULT_MAX_MM <= max_mm <= 400.0:
        raise ValueError(f"max_mm must be in [{DEFAULT_MAX_MM:g}, 400], got {max_mm}")
    kind, build = KINDS[index % len(KINDS)]
    rng = np.random.default_rng([seed, index])
    for _attempt in range(20):
        solid = build(rng)
        if solid.is_empty() or solid.num_tri() < 12:
            continue
        mesh = _to_trimesh(solid)
        extent = float(mesh.extents.max())
        if not mesh.is_watertight or extent < 1.0:
            continue
        if extent > DEFAULT_MAX_MM or extent < MIN_MM:  # into the size range of real parts
            mesh.apply_scale(float(np.clip(extent, MIN_MM, DEFAULT_MAX_MM)) / extent)
        if max_mm > DEFAULT_MAX_MM:
            size_rng = np.random.default_rng([seed, index, 1])
            large, target = size_rng.random(), size_rng.uniform(0.0, 1.0)
            if large < LARGE_SHARE:
                target_mm = DEFAULT_MAX_MM * (max_mm / DEFAULT_MAX_MM) ** target
                mesh.apply_scale(target_mm / float(mesh.extents.max()))
        return f"{kind}_{seed}_{index:04d}", mesh
    raise RuntimeError(f"family seed {seed}: shape {index} ({kind}) gave no sound solid")


def family_shapes(
    count: int, seed: int, with_catalog_parts: bool = True, max_mm: float = DEFAULT_MAX_MM
) -> list[tuple[str, trimesh.Trimesh]]:
    """``count`` shapes: the five catalog parts first (``with_catalog_parts``), then drawn
    shapes of ``seed`` (``family_shape``). Meshes in millimetres."""
    if count < 1:
        raise ValueError(f"count must be at least 1, got {count}")
    if not DEFAULT_MAX_MM <= max_mm <= 400.0:
        raise ValueError(f"max_mm must be in [{DEFAULT_MAX_MM:g}, 400], got {max_mm}")
    shapes = [(name, build_part(name)) for name, _ in PARTS][:count] if with_catalog_parts else []
    k = 0
    while len(shapes) < count:
        shapes.append(family_shape(seed, k, max_mm))
        k += 1
    return shapes


def family_models(
    count: int, seed: int, with_catalog_parts: bool = True, max_mm: float = DEFAULT_MAX_MM
) -> list:
    """The family as object models (obj_ids 1..count, metres), symmetries not detected: a
    detector learns where parts are, not their poses."""
    from posefuse.estimator.core.objects import make_model

    models = []
    shapes = family_shapes(count, seed, with_catalog_parts, max_mm)
    for obj_id, (name, mesh) in enumerate(shapes, 1):
        mesh.apply_scale(1e-3)
        models.append(make_model(obj_id, name, mesh, detect=False))
    return models
