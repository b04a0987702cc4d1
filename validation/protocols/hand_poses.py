"""A library of plausible hand poses from documented grasps and gestures, within normal joint ranges.

Rhee et al. 2011, §6.2, found that 10 eigenposes of "60 different meaningful
poses from the Poser character system" covered more than 90 % of the
variation (after Santello, Flanders & Soechting 1998, their ref. [48]).
Poser's pose set is not available, so this library is built from three
published, illustrated sets:

* **GRASP** — the 33 grasp types of Feix, Romero, Schmiedmayer, Dollar &
  Kragic, *The GRASP Taxonomy of Human Grasp Types*, IEEE Trans.
  Human-Machine Systems 46(1):66–77, 2016 (their Fig. 4 and Table I);
* **ASL** — the 26 hand shapes of the American Sign Language manual
  alphabet (J and Z move: their starting shapes);
* **gesture** — common communicative gestures (open palm, fist, pointing,
  thumbs-up, "OK", V, horns, call-me, counting three, pinch).

The joint angles are our reading of those illustrations, composed from
finger shapes (``FINGER_SHAPES``), thumb shapes (``THUMB_SHAPES``)
and spreads (``SPREADS``), each pose checked against the hand's ranges
of motion (``RANGE_OF_MOTION`` in :mod:`validation.phantoms.hand`: the
AAOS normal active ranges, *Joint Motion: Method of Measuring and
Recording*, 1965, widened a few degrees).  Angles are in degrees in the hand
phantom's joint frames (intrinsic XYZ = flexion, abduction towards the
radial side, twist); the wrist stays neutral.
"""

from __future__ import annotations

import numpy as np

from validation.phantoms.hand import RANGE_OF_MOTION, range_key

__all__ = [
    "FINGER_SHAPES",
    "THUMB_SHAPES",
    "SPREADS",
    "LIBRARY",
    "RANGE_OF_MOTION",
    "library_angles",
    "hand_angles",
    "check_range",
    "FINGERS",
]

FINGERS = ("index", "middle", "ring", "little")

# (MCP, PIP, DIP) flexion, degrees
FINGER_SHAPES = {
    "straight": (0, 0, 0),
    "relaxed": (15, 20, 10),  # the resting cascade
    "pad": (35, 25, 10),  # pad-to-pad contact, nearly straight distal joints
    "round": (35, 50, 30),  # around a large sphere or cylinder
    "half": (50, 60, 35),
    "tip": (55, 75, 45),  # tip-to-tip with the thumb
    "wrap": (70, 90, 55),  # a small-diameter power grasp
    "fist": (85, 100, 70),
    "hook": (5, 90, 65),  # MCP straight, PIP and DIP bent (carrying a bag)
    "table": (85, 5, 0),  # MCP bent, fingers straight (the intrinsic-plus position)
    "claw": (20, 90, 70),
    "side": (45, 15, 5),  # its radial side against the thumb pad (lateral pinch)
}
# thumb: (CMC flexion, CMC abduction, CMC twist), MCP flexion, IP flexion
THUMB_SHAPES = {
    "open": ((0, 0, 0), 0, 0),  # extended in the palm's plane, abducted from the index
    "up": ((-5, 5, 0), 0, -10),  # thumbs-up: extended, slightly hyperextended IP
    "alongside": ((5, -12, 5), 10, 5),  # adducted against the index's side (ASL A)
    "lateral": ((8, -15, 10), 15, 10),  # pad against the index's radial side (key pinch)
    "pad": ((12, -15, 15), 15, 20),  # pad opposed to a fingertip
    "tip": ((15, -18, 18), 20, 40),  # tip to tip
    "wrap": ((15, -20, 20), 25, 30),  # over the fingers of a power grasp
    "across": ((22, -25, 20), 40, 45),  # folded across the palm (ASL B, 4)
    "over": ((18, -22, 22), 30, 30),  # over the middle phalanges of a fist (ASL S)
    "tucked": ((20, -20, 18), 35, 20),  # under the curled index and middle (ASL T, N, M)
}
# MCP abduction per finger (index, middle, ring, little), degrees towards the radial side
SPREADS = {
    "neutral": (0, 0, 0, 0),
    "together": (-4, 0, 4, 8),
    "spread": (12, 0, -10, -18),
    "v": (12, -8, 0, 0),  # index and middle apart
}

G, A, X = "GRASP (Feix et al. 2016)", "ASL manual alphabet", "gesture"
# name, source, thumb shape, (index, middle, ring, little) shapes, spread
LIBRARY = (
    ("large diameter", G, "wrap", ("round",) * 4, "neutral"),
    ("small diameter", G, "wrap", ("wrap",) * 4, "together"),
    ("medium wrap", G, "wrap", ("half",) * 4, "together"),
    ("adducted thumb", G, "alongside", ("half",) * 4, "together"),
    ("light tool", G, "alongside", ("wrap", "wrap", "fist", "fist"), "together"),
    ("prismatic 4 finger", G, "pad", ("pad",) * 4, "together"),
    ("prismatic 3 finger", G, "pad", ("pad", "pad", "pad", "relaxed"), "together"),
    ("prismatic 2 finger", G, "pad", ("pad", "pad", "relaxed", "relaxed"), "together"),
    ("palmar pinch", G, "pad", ("pad", "relaxed", "relaxed", "relaxed"), "neutral"),
    ("power disk", G, "wrap", ("round",) * 4, "spread"),
    ("power sphere", G, "wrap", ("half",) * 4, "spread"),
    ("precision disk", G, "pad", ("pad",) * 4, "spread"),
    ("precision sphere", G, "pad", ("round",) * 4, "spread"),
    ("tripod", G, "pad", ("pad", "pad", "relaxed", "relaxed"), "neutral"),
    ("fixed hook", G, "open", ("hook",) * 4, "together"),
    ("lateral", G, "lateral", ("side", "half", "wrap", "wrap"), "together"),
    ("index finger extension", G, "wrap", ("straight", "wrap", "wrap", "wrap"), "together"),
    ("extension type", G, "pad", ("table",) * 4, "together"),
    ("distal type", G, "tip", ("tip", "half", "half", "wrap"), "neutral"),
    ("writing tripod", G, "tip", ("tip", "half", "wrap", "wrap"), "together"),
    ("tripod variation", G, "pad", ("half", "tip", "wrap", "wrap"), "together"),
    ("parallel extension", G, "open", ("table",) * 4, "together"),
    ("adduction grip", G, "open", ("relaxed", "relaxed", "relaxed", "relaxed"), "together"),
    ("tip pinch", G, "tip", ("tip", "half", "half", "half"), "neutral"),
    ("lateral tripod", G, "lateral", ("side", "half", "wrap", "wrap"), "neutral"),
    ("sphere 4 finger", G, "pad", ("round",) * 4, "neutral"),
    ("quadpod", G, "tip", ("tip", "tip", "tip", "half"), "neutral"),
    ("sphere 3 finger", G, "pad", ("round", "round", "round", "half"), "neutral"),
    ("stick", G, "alongside", ("half", "wrap", "wrap", "wrap"), "together"),
    ("palmar", G, "open", ("relaxed", "relaxed", "relaxed", "relaxed"), "spread"),
    ("ring", G, "tip", ("tip", "relaxed", "relaxed", "relaxed"), "spread"),
    ("ventral", G, "pad", ("straight", "wrap", "wrap", "wrap"), "together"),
    ("inferior pincer", G, "tip", ("tip", "wrap", "wrap", "wrap"), "neutral"),
    ("A", A, "alongside", ("fist",) * 4, "together"),
    ("B", A, "across", ("straight",) * 4, "together"),
    ("C", A, "pad", ("round",) * 4, "together"),
    ("D", A, "tip", ("straight", "tip", "tip", "tip"), "together"),
    ("E", A, "across", ("claw",) * 4, "together"),
    ("F", A, "tip", ("tip", "straight", "straight", "straight"), "spread"),
    ("G", A, "lateral", ("table", "fist", "fist", "fist"), "together"),
    ("H", A, "over", ("table", "table", "fist", "fist"), "together"),
    ("I", A, "over", ("fist", "fist", "fist", "straight"), "together"),
    ("J", A, "over", ("fist", "fist", "fist", "straight"), "neutral"),
    ("K", A, "pad", ("straight", "half", "fist", "fist"), "v"),
    ("L", A, "open", ("straight", "fist", "fist", "fist"), "together"),
    ("M", A, "tucked", ("fist", "fist", "fist", "fist"), "together"),
    ("N", A, "tucked", ("fist", "fist", "wrap", "fist"), "together"),
    ("O", A, "tip", ("tip",) * 4, "together"),
    ("P", A, "pad", ("table", "half", "fist", "fist"), "v"),
    ("Q", A, "lateral", ("half", "fist", "fist", "fist"), "together"),
    ("R", A, "over", ("straight", "straight", "fist", "fist"), "together"),
    ("S", A, "over", ("fist",) * 4, "together"),
    ("T", A, "tucked", ("wrap", "fist", "fist", "fist"), "together"),
    ("U", A, "over", ("straight", "straight", "fist", "fist"), "together"),
    ("V", A, "over", ("straight", "straight", "fist", "fist"), "v"),
    ("W", A, "tip", ("straight", "straight", "straight", "fist"), "spread"),
    ("X", A, "over", ("claw", "fist", "fist", "fist"), "together"),
    ("Y", A, "up", ("fist", "fist", "fist", "straight"), "spread"),
    ("Z", A, "over", ("straight", "fist", "fist", "fist"), "together"),
    ("open palm", X, "open", ("straight",) * 4, "spread"),
    ("flat hand", X, "alongside", ("straight",) * 4, "together"),
    ("relaxed hand", X, "pad", ("relaxed",) * 4, "neutral"),
    ("fist", X, "over", ("fist",) * 4, "together"),
    ("pointing", X, "over", ("straight", "fist", "fist", "fist"), "neutral"),
    ("thumbs up", X, "up", ("fist",) * 4, "together"),
    ("OK", X, "tip", ("tip", "relaxed", "straight", "straight"), "spread"),
    ("horns", X, "over", ("straight", "fist", "fist", "straight"), "spread"),
    ("call me", X, "up", ("fist", "fist", "fist", "straight"), "spread"),
    ("three", X, "open", ("straight", "straight", "fist", "fist"), "v"),
    ("pinch", X, "tip", ("tip", "relaxed", "relaxed", "relaxed"), "neutral"),
    ("claw hand", X, "pad", ("claw",) * 4, "spread"),
)


def hand_angles(skeleton, thumb: str, shapes, spread) -> dict:
    """Joint angles for the hand ``skeleton`` from a ``THUMB_SHAPES`` name, four ``FINGER_SHAPES``
    names (index, middle, ring, little) and a ``SPREADS`` name or four MCP abductions (degrees)."""
    a = {j.name: np.zeros(j.dof) for j in skeleton.joints}
    abds = SPREADS[spread] if isinstance(spread, str) else tuple(float(v) for v in spread)
    for finger, shape, abd in zip(FINGERS, shapes, abds):
        mcp, pip, dip = FINGER_SHAPES[shape]
        a[f"{finger}_mcp"][:3] = (mcp, abd, 0.0)
        a[f"{finger}_pip"][0] = pip
        a[f"{finger}_dip"][0] = dip
        # the ring and little metacarpals cup the palm in a grasp (their CMC joints), ~ their MCP flexion / 6
        if finger in ("ring", "little"):
            a[f"{finger}_cmc"][0] = (0.1 if finger == "ring" else 0.2) * mcp
    cmc, mcp, ip = THUMB_SHAPES[thumb]
    a["thumb_cmc"][:3] = cmc
    a["thumb_mcp"][0] = mcp
    a["thumb_ip"][0] = ip
    return a


def library_angles(skeleton) -> list[tuple[str, str, dict]]:
    """Every library pose as ``(name, source, {joint: angles})`` for the hand ``skeleton`` (its joint DOFs)."""
    return [
        (name, source, hand_angles(skeleton, thumb, shapes, spread)) for name, source, thumb, shapes, spread in LIBRARY
    ]


def check_range(angles: dict) -> list[str]:
    """The joint rotations of ``angles`` outside ``RANGE_OF_MOTION`` (empty when all are within)."""
    bad = []
    for joint, v in angles.items():
        lims = RANGE_OF_MOTION[range_key(joint)]
        for axis, (value, (lo, hi)) in enumerate(zip(np.asarray(v, float)[:3], lims)):
            if not lo <= value <= hi:
                bad.append(f"{joint}[{axis}] = {value:g}° outside [{lo}, {hi}]")
    return bad
