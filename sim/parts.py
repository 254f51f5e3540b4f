"""Procedural industrial parts that resemble the ROBI objects, in millimetres.

Each part is built as a solid with manifold3d (extrusions, revolutions and booleans), so the
mesh is watertight by construction, then moved so that its bounding-box centre is the origin.
Sizes are those of real parts (30-120 mm). The shapes are our own; only the kinds of part follow
ROBI (tube fitting, chrome screw, eye bolt, gear, zigzag bracket).
"""

from __future__ import annotations

from collections.abc import Callable

import manifold3d as mf
import numpy as np
import trimesh

SEGMENTS = 72  # facets of a full circle; fine enough that shading shows no faceting at 0.7 m


def _to_trimesh(solid: mf.Manifold) -> trimesh.Trimesh:
    m = solid.to_mesh()
    mesh = trimesh.Trimesh(
        vertices=np.asarray(m.vert_properties)[:, :3], faces=np.asarray(m.tri_verts), process=True
    )
    lo, hi = mesh.bounds
    mesh.apply_translation(-(lo + hi) / 2)
    return mesh


def _tube(length: float, r_out: float, r_in: float) -> mf.Manifold:
    """A tube along +z from 0 to ``length``."""
    outer = mf.Manifold.cylinder(length, r_out, r_out, SEGMENTS)
    inner = mf.Manifold.cylinder(length + 2, r_in, r_in, SEGMENTS).translate([0, 0, -1])
    return outer - inner


def tube_fitting() -> trimesh.Trimesh:
    """A tee: a run tube (x) with a branch (y), collars at the three ends; 80 x 52 x 32 mm."""
    r_out, r_in, r_collar = 12.0, 8.5, 16.0
    run = mf.Manifold.cylinder(80, r_out, r_out, SEGMENTS, True).rotate([0, 90, 0])
    branch = mf.Manifold.cylinder(40, r_out, r_out, SEGMENTS).rotate([-90, 0, 0])
    solid = run + branch
    for x in (-37.0, 37.0):  # collars (nut-like bands) on the run ends
        collar = mf.Manifold.cylinder(6, r_collar, r_collar, 6, True).rotate([0, 90, 0])
        solid = solid + collar.translate([x, 0, 0])
    collar = mf.Manifold.cylinder(6, r_collar, r_collar, 6).rotate([-90, 0, 0])
    solid = solid + collar.translate([0, 34, 0])
    bore_run = mf.Manifold.cylinder(90, r_in, r_in, SEGMENTS, True).rotate([0, 90, 0])
    bore_branch = mf.Manifold.cylinder(45, r_in, r_in, SEGMENTS).rotate([-90, 0, 0])
    return _to_trimesh(solid - bore_run - bore_branch)


def chrome_screw() -> trimesh.Trimesh:
    """A socket-head cap screw: round head with a hex socket, a threaded-looking shank; 16 x 56."""
    head = mf.Manifold.cylinder(8, 8.0, 7.2, SEGMENTS)  # slightly domed (chamfered) top
    socket = mf.Manifold.cylinder(5, 3.0, 3.0, 6).translate([0, 0, 4])
    head = (head - socket).translate([0, 0, 48])
    # threads as a stack of grooves: a revolved saw-tooth profile
    pitch, r_major, r_minor, length = 1.75, 5.0, 4.1, 48.0
    profile = [(0.0, 0.0), (r_minor, 0.0)]
    n_teeth = int(length / pitch)
    for k in range(n_teeth):
        z = 1.0 + k * pitch
        profile += [(r_major, z + pitch * 0.4), (r_minor, z + pitch * 0.8)]
    profile += [(r_minor, length + 0.5), (0.0, length + 0.5)]
    shank = mf.CrossSection([np.array(profile)]).revolve(SEGMENTS)
    return _to_trimesh(shank + head)


def eye_bolt() -> trimesh.Trimesh:
    """A ring (in the xz plane) on a collar and a threaded shank along -z; 40 x 8 x 92 mm."""
    ring_major, ring_minor = 14.0, 4.0
    ring = mf.CrossSection.circle(ring_minor, 32).translate([ring_major, 0]).revolve(SEGMENTS)
    ring = ring.rotate([90, 0, 0]).translate([0, 0, ring_major + 6])  # ring plane xz
    collar = mf.Manifold.cylinder(6, 9.0, 9.0, SEGMENTS)
    neck = mf.Manifold.cylinder(8, 5.0, 5.0, SEGMENTS).translate([0, 0, 2])
    pitch, r_major, r_minor, length = 1.5, 5.0, 4.2, 50.0
    profile = [(0.0, 0.0), (r_minor, 0.0)]
    for k in range(int(length / pitch)):
        z = 1.0 + k * pitch
        profile += [(r_major, z + pitch * 0.4), (r_minor, z + pitch * 0.8)]
    profile += [(r_minor, length + 0.5), (0.0, length + 0.5)]
    shank = mf.CrossSection([np.array(profile)]).revolve(SEGMENTS).translate([0, 0, -length])
    return _to_trimesh(ring + collar + neck + shank)


def gear() -> trimesh.Trimesh:
    """A spur gear: 18 trapezoidal teeth, a hub on both faces and a bore; 64 mm across."""
    n_teeth, r_tip, r_root, thickness = 18, 32.0, 27.0, 10.0
    pts = []
    for k in range(n_teeth):
        a = 2 * np.pi * k / n_teeth
        half = np.pi / n_teeth
        for da, r in (
            (-0.55 * half, r_root),
            (-0.3 * half, r_tip),
            (0.3 * half, r_tip),
            (0.55 * half, r_root),
        ):
            pts.append((r * np.cos(a + da), r * np.sin(a + da)))
        for da in np.linspace(0.55 * half, 2 * half - 0.55 * half, 4)[1:-1]:
            pts.append((r_root * np.cos(a + da), r_root * np.sin(a + da)))
    body = mf.CrossSection([np.array(pts)]).extrude(thickness).translate([0, 0, -thickness / 2])
    hub = mf.Manifold.cylinder(thickness + 4, 13.0, 13.0, SEGMENTS, True)  # hub on both faces
    bore = mf.Manifold.cylinder(thickness + 6, 8.0, 8.0, SEGMENTS, True)
    solid = body + hub - bore
    return _to_trimesh(solid)


def zigzag() -> trimesh.Trimesh:
    """A Z-bent sheet-metal bracket (2.5 mm sheet, 30 mm wide) with a hole in each flange."""
    t, flange, web, width = 2.5, 32.0, 40.0, 30.0
    # Z profile in the (x, z) plane, point-symmetric about the origin
    half = web / 2
    profile = [
        (-flange, -half),
        (t / 2, -half),
        (t / 2, half - t),
        (flange, half - t),
        (flange, half),
        (-t / 2, half),
        (-t / 2, -half + t),
        (-flange, -half + t),
    ]
    sheet = mf.CrossSection([np.array(profile)]).extrude(width).translate([0, 0, -width / 2])
    sheet = sheet.rotate([90, 0, 0])  # profile plane -> xz, extrusion along y
    hole = mf.Manifold.cylinder(20, 3.5, 3.5, 36, True)
    sheet = (
        sheet
        - hole.translate([-flange * 0.55, 0, -half])
        - hole.translate([flange * 0.55, 0, half])
    )
    return _to_trimesh(sheet)


# name -> builder, in catalog order (obj_id = position + 1)
PARTS: tuple[tuple[str, Callable[[], trimesh.Trimesh]], ...] = (
    ("tube_fitting", tube_fitting),
    ("chrome_screw", chrome_screw),
    ("eye_bolt", eye_bolt),
    ("gear", gear),
    ("zigzag", zigzag),
)


def build_part(name: str) -> trimesh.Trimesh:
    """The mesh of one procedural part, in millimetres, bbox-centred and watertight."""
    builders = dict(PARTS)
    if name not in builders:
        raise ValueError(f"unknown part {name!r}; the parts are {[n for n, _ in PARTS]}")
    return builders[name]()
