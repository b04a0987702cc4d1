"""Hand phantom: radius, a carpal block (capitate), 5 metacarpals, 14 phalanges.

Template world frame (mm, a right hand lying flat): ``+y`` distal (towards
the fingertips), ``+x`` ulnar (towards the little finger; the thumb is at
``-x``), ``+z`` dorsal; the palm faces ``-z`` and fingers flex towards
``-z``.  Paper grid (Rhee Table 1): 255×255×90 voxels at 0.78×0.78×1.0 mm.

Bones: the radius, metacarpals and phalanges are :func:`digit_bone` shapes
(waisted shaft, a base wider than deep with a dorsal lip, palmar condyles),
so none is a body of revolution; the capitate is an ellipsoid.

Link model (Kurihara §3, Fig. 3): the radius is the root; the wrist
(radius → capitate) and the thumb CMC are 6-DOF joints, all others 3 DOF:
four finger CMC joints, five MCP, four PIP, four DIP and the thumb IP —
20 joints for 21 bones.  Kurihara reports "19 joints, two with 6 DOFs"; a
tree of the 21 bones this phantom carries needs 20 links, so we keep the
paper's two 6-DOF joints and one more 3-DOF joint than the paper counts.
"""

from __future__ import annotations

import numpy as np

from deformation.kinematics.skeleton import Bone, Joint, Skeleton

from .anatomy import Anatomy
from .shapes import Ellipsoid, RoundCone, SmoothUnion

NAME = "hand"
GRIDS = {
    "paper": ((255, 255, 90), (0.78, 0.78, 1.0)),
    "test": ((64, 64, 30), (3.1078125, 3.1078125, 3.0)),
}
# The wrist near the lower edge, fingertips inside the upper one; 67 mm of room on the palmar
# side (-z) for the curled fingers, 22 mm dorsally (the template body reaches z = +19.5).
GRID_CENTER = (-8.0, 6.0, -22.5)
DEFAULT_POSES = 10

GAP = 1.6  # joint space between articular caps, mm
# finger: (MC base x, spread angle ψ in degrees towards +x, lengths MC/P1/P2/P3 between cap centres)
FINGERS = {
    "index": (-21.0, -7.0, (49.0, 30.0, 17.0, 10.0)),
    "middle": (-6.0, 0.0, (51.0, 33.0, 20.0, 10.5)),
    "ring": (8.0, 6.0, (47.5, 31.0, 18.5, 10.0)),
    "little": (21.0, 13.0, (42.0, 24.5, 13.0, 8.0)),
}
# bone radii (base, head) for MC, P1, P2, P3
RADII = ((4.0, 5.0), (4.4, 3.9), (3.6, 3.2), (3.0, 2.6))
THUMB_BASE = np.array([-28.0, -53.0, -6.0])
THUMB_DIR = np.array([-0.62, 0.72, -0.30]) / np.linalg.norm([-0.62, 0.72, -0.30])
THUMB_LENGTHS = (36.0, 26.0, 17.0)
THUMB_RADII = ((4.5, 5.0), (4.5, 4.0), (3.6, 3.0))
MC_BASE_Y = -46.0
SOFT = {"bone": 4.6, "palm": 9.0}


def _frame(direction) -> np.ndarray:
    """Joint frame for a digit along ``direction``: z along the digit, y as dorsal as possible."""
    z = np.asarray(direction, float) / np.linalg.norm(direction)
    y = np.array([0.0, 0.0, 1.0]) - z[2] * z
    y /= np.linalg.norm(y)
    return np.column_stack([np.cross(y, z), y, z])


def _chain(base, direction, lengths, radii):
    """Cap centres of a digit's bones: list of (start, end, r_start, r_end) and joint centres."""
    d = np.asarray(direction, float)
    segs = []
    start = np.asarray(base, float)
    for i, (length, (ra, rb)) in enumerate(zip(lengths, radii)):
        end = start + length * d
        segs.append((start, end, ra, rb))
        if i + 1 < len(lengths):
            start = end + (rb + GAP + radii[i + 1][0]) * d
    return segs


def _layout():
    """Bones (name → segment), joints (name, parent, child, dof, centre, axes), soft radii."""
    segs, joints, radius = {}, [], {}
    wrist_axes = _frame((0.0, 1.0, 0.0))
    segs["radius"] = ((-6.0, -104.0, 0.0), (-6.0, -80.0, 0.0), 9.0, 10.0)
    joints.append(("wrist", "radius", "capitate", 6, (-2.0, -68.0, 0.0), wrist_axes))
    radius["wrist"] = 22.0
    for finger, (bx, psi, lengths) in FINGERS.items():
        d = np.array([np.sin(np.deg2rad(psi)), np.cos(np.deg2rad(psi)), 0.0])
        chain = _chain((bx, MC_BASE_Y, 0.0), d, lengths, RADII)
        names = [f"{finger}_metacarpal", f"{finger}_proximal", f"{finger}_middle", f"{finger}_distal"]
        axes = _frame(d)
        parent = "capitate"
        for i, (name, seg) in enumerate(zip(names, chain)):
            segs[name] = seg
            if i == 0:
                jn, centre = f"{finger}_cmc", seg[0] - 2.0 * d
            else:
                jn, centre = f"{finger}_{('mcp', 'pip', 'dip')[i - 1]}", chain[i - 1][1]
                radius[jn] = (11.0, 9.0, 8.0)[i - 1]
            joints.append((jn, parent, name, 3, tuple(centre), axes))
            parent = name
    chain = _chain(THUMB_BASE, THUMB_DIR, THUMB_LENGTHS, THUMB_RADII)
    names = ["thumb_metacarpal", "thumb_proximal", "thumb_distal"]
    axes = _frame(THUMB_DIR)
    parent = "capitate"
    for i, (name, seg) in enumerate(zip(names, chain)):
        segs[name] = seg
        if i == 0:
            jn, dof, centre = "thumb_cmc", 6, seg[0] - 2.0 * THUMB_DIR
            radius[jn] = 14.0
        else:
            jn, dof, centre = ("thumb_mcp", "thumb_ip")[i - 1], 3, chain[i - 1][1]
            radius[jn] = (10.0, 8.0)[i - 1]
        joints.append((jn, parent, name, dof, tuple(centre), axes))
        parent = name
    return segs, joints, radius


# Ranges of motion, degrees in the joint frames (flexion, abduction towards the radial side, axial twist): the
# normal active ranges (American Academy of Orthopaedic Surgeons, Joint Motion: Method of Measuring and
# Recording, 1965) widened by a few degrees for passive motion and for the jitter of measured (or the
# phantom's seeded) angles around a straight joint (a PIP estimated at −1° must pass);
# the thumb's carpometacarpal joint within ±60° about each axis; the 6-DOF joints' translations within 10 mm
RANGE_OF_MOTION = {
    "cmc": ((-5, 25), (-7, 7), (-12, 12)),  # fingers' carpometacarpal cupping (ring and little move)
    "mcp": ((-45, 90), (-25, 25), (-10, 10)),
    "pip": ((-10, 110), (-7, 7), (-7, 7)),
    "dip": ((-15, 90), (-7, 7), (-7, 7)),
    "thumb_cmc": ((-60, 60), (-60, 60), (-60, 60)),
    "thumb_mcp": ((-10, 55), (-15, 15), (-15, 15)),
    "thumb_ip": ((-25, 85), (-7, 7), (-7, 7)),
    "wrist": ((-70, 80), (-20, 30), (-10, 10)),
}
TRANSLATION_LIMIT_MM = 10.0


def range_key(joint: str) -> str:
    """The ``RANGE_OF_MOTION`` entry of a hand joint ("index_mcp" → "mcp")."""
    if joint.startswith("thumb_") or joint == "wrist":
        return joint
    return joint.rsplit("_", 1)[1]


def _limits(name: str, dof: int) -> tuple:
    rot = RANGE_OF_MOTION[range_key(name)]
    return tuple(rot) + ((-TRANSLATION_LIMIT_MM, TRANSLATION_LIMIT_MM),) * (dof - 3)


def skeleton() -> Skeleton:
    segs, joints, _ = _layout()
    bone_order = ["radius", "capitate"] + [n for n in segs if n != "radius"]
    parent_of = {j[2]: j[1] for j in joints}
    bones = [Bone(n, i + 1, parent_of.get(n)) for i, n in enumerate(bone_order)]
    return Skeleton(bones, [Joint(*j, limits=_limits(j[0], j[3])) for j in joints], name=NAME)


def digit_bone(a, b, ra, rb, axes) -> SmoothUnion:
    """A tubular bone of the hand or forearm that is not a body of revolution.

    Real metacarpals and phalanges have a waisted shaft, a base wider
    radio-ulnarly than it is deep with a dorsal lip, and a head whose condyles
    project palmarly.  A round cone would be
    symmetric about its long axis, so its twist is invisible in any image and
    no registration can recover it; these widths and offsets (about 1.4:1 at
    the ends) make every rotation observable, as in real bones.  ``axes`` is
    the digit frame of ``_frame`` (x radio-ulnar, y dorsal, z along the
    digit).  The articular ends stay where the round cone's caps were, so the
    joint spaces keep their ``GAP``.
    """
    a, b, axes = np.asarray(a, float), np.asarray(b, float), np.asarray(axes, float)
    y = axes[:, 1]
    rot = tuple(axes.reshape(-1))
    return SmoothUnion(
        (
            RoundCone(tuple(a), tuple(b), 0.78 * ra, 0.78 * rb),
            Ellipsoid(tuple(a + 0.12 * ra * y), (1.22 * ra, 0.86 * ra, ra), rot),
            Ellipsoid(tuple(b - 0.12 * rb * y), (1.18 * rb, 0.86 * rb, rb), rot),
        ),
        k=1.5,
    )


def anatomy() -> Anatomy:
    segs, joints, radius = _layout()
    axes_of = {child: np.asarray(ax, float) for (_, _, child, _, _, ax) in joints}
    axes_of["radius"] = _frame((0.0, 1.0, 0.0))
    shapes = {n: digit_bone(a, b, ra, rb, axes_of[n]) for n, (a, b, ra, rb) in segs.items()}
    shapes["capitate"] = Ellipsoid((0.0, -59.5, 0.0), (20.0, 6.5, 8.0))
    palm_parts = [
        RoundCone((-4.0, -120.0, 0.0), (-2.0, -62.0, 0.0), 19.0, 21.0),
        Ellipsoid((0.0, -58.0, -1.0), (32.0, 16.0, 16.0)),
    ]
    digits = []
    for name, (a, b, ra, rb) in segs.items():
        if name == "radius":
            continue
        if name.endswith("metacarpal"):
            palm_parts.append(RoundCone(tuple(a), tuple(b), ra + SOFT["palm"], rb + SOFT["palm"] - 1.0))
        else:
            digits.append(RoundCone(tuple(a), tuple(b), ra + SOFT["bone"], rb + SOFT["bone"]))
    body = SmoothUnion((SmoothUnion(tuple(palm_parts), k=12.0), *digits), k=5.0)
    return Anatomy(
        skeleton(),
        shapes,
        body,
        joint_radius_mm=radius,
        cortex_mm=1.2,
        skin_mm=1.5,
        fat_mm=3.0,
        bulge_gain=0.5,
        slide_gain=0.3,
        bone_fade_mm=1.5,
        residual_gain=0.1,
        residual_wavelength_mm=30.0,
        structure=dict(
            muscle_cell_mm=6.0,
            fat_cell_mm=3.0,
            muscle_septum_mm=0.35,
            fat_septum_mm=0.2,
            cell_amplitude=0.10,
            lobule_amplitude=0.06,
            tendon_offset=0.6,
            tendon_radius_mm=1.0,
            vessel_offset=0.65,
            vessel_radius_mm=0.6,
        ),
    )


def complete_angles(angles: dict) -> dict:
    return {k: np.asarray(v, float) for k, v in angles.items()}


def default_poses(n: int, rng: np.random.Generator) -> list[dict]:
    """``n`` poses from a wide spread (t = 0) to a fist-like curl (t = 1), with seeded jitter."""
    poses = []
    for t in np.linspace(0.0, 1.0, n):

        def jit(k, s=2.0):
            return rng.normal(0.0, s, size=k)

        a = {"wrist": np.concatenate([[-4.0 + 8.0 * t], jit(2, 2.0), [0.0, -0.5 * t, 0.3 * t]])}
        for i, (finger, (_, psi, _)) in enumerate(FINGERS.items()):
            cup = (0.0, 2.0, 4.0, 8.0)[i]
            a[f"{finger}_cmc"] = np.array([cup * t, 0.0, 0.0]) + jit(3, 1.0)
            abd = (1.0 - t) * (-4.0 * np.sign(psi)) + t * 0.8 * psi
            a[f"{finger}_mcp"] = np.array([70.0 * t, abd, 0.0]) + jit(3)
            a[f"{finger}_pip"] = np.array([85.0 * t, 0.0, 0.0]) + jit(3, 1.5)
            a[f"{finger}_dip"] = np.array([50.0 * t, 0.0, 0.0]) + jit(3, 1.5)
        # Thumb opposition: adduction towards the palm (+x) and palmar flexion, kept moderate so
        # that the thumb's soft tissue does not sink into the index finger's.
        a["thumb_cmc"] = np.concatenate(
            [np.array([15.0 * t, -20.0 * t, 20.0 * t]) + jit(3), [0.8 * t, -0.5 * t, 0.4 * t]]
        )
        a["thumb_mcp"] = np.array([20.0 * t, 0.0, 0.0]) + jit(3, 1.5)
        a["thumb_ip"] = np.array([30.0 * t, 0.0, 0.0]) + jit(3, 1.5)
        poses.append(a)
    return poses
