"""Knee phantom: femur, tibia, fibula and patella in a leg-shaped body.

Template world frame (mm): ``+y`` proximal (along the femur), ``+x``
anterior, ``+z`` lateral; the knee's flexion axis is ``z``.  In the template
the leg is straight.  Grids follow Rhee Table 1: the paper size is
255×255×123 voxels at 1.25×1.25×1.2 mm with the sagittal plane (x, y)
in-plane, so flexion happens within the slices.

Skeleton (Rhee §3.1: "the tibia and fibula are attached to the femur
bone"): femur is the root; ``knee`` (femur → tibia, 3 DOF: flexion, varus,
internal rotation), ``tibiofibular`` (femur → fibula) and ``patellofemoral``
(femur → patella) joints.  The fibula is rigidly tied to the tibia (its joint
copies the knee's angles) and the patella turns about the trochlea by 70 % of
the knee flexion; :func:`complete_angles` fills these couplings in, so a
poses file only needs the ``knee`` angles.
"""

from __future__ import annotations

import numpy as np

from deformation.kinematics.skeleton import Bone, Joint, Skeleton

from .anatomy import Anatomy
from .shapes import Ellipsoid, RoundCone, SmoothUnion

NAME = "knee"
# (size (nx, ny, nz), spacing mm) — paper: Rhee Table 1.
GRIDS = {
    "paper": ((255, 255, 123), (1.25, 1.25, 1.2)),
    "test": ((64, 64, 40), (4.98046875, 4.98046875, 3.69)),
}
GRID_CENTER = (10.0, 0.0, 0.0)
DEFAULT_POSES = 4
KNEE_CENTER = (19.0, 20.0, 0.0)  # centre of the femoral condyles' distal arc
TROCHLEA_CENTER = (19.0, 24.0, 0.0)
PATELLA_RATIO = 0.7

# Joint frame of the knee: x = flexion axis, y = the side the shank swings to
# (posterior ↔ -y_joint), z = along the tibia (distal).
_KNEE_AXES = np.column_stack([(0.0, 0.0, -1.0), (1.0, 0.0, 0.0), (0.0, -1.0, 0.0)])


# Range of motion per joint (flexion, varus/valgus, axial rotation; degrees): the knee's normal active range
# (AAOS, Joint Motion, 1965: flexion 0-135°, hyperextension to -10°) widened a little for passive motion;
# the fibula follows the tibia; the patella turns by ~70 % of the flexion
RANGE_OF_MOTION = {"knee": ((-10, 150), (-15, 15), (-30, 30)), "patellofemoral": ((-10, 110), (-15, 15), (-20, 20))}


def skeleton() -> Skeleton:
    bones = [Bone("femur", 1, None), Bone("tibia", 2, "femur"), Bone("fibula", 3, "femur"), Bone("patella", 4, "femur")]
    joints = [
        Joint("knee", "femur", "tibia", 3, KNEE_CENTER, _KNEE_AXES, RANGE_OF_MOTION["knee"]),
        Joint("tibiofibular", "femur", "fibula", 3, KNEE_CENTER, _KNEE_AXES, RANGE_OF_MOTION["knee"]),
        Joint("patellofemoral", "femur", "patella", 3, TROCHLEA_CENTER, _KNEE_AXES, RANGE_OF_MOTION["patellofemoral"]),
    ]
    return Skeleton(bones, joints, name=NAME)


def anatomy() -> Anatomy:
    x0 = 25.0
    femur = SmoothUnion(
        (
            RoundCone((x0, 175.0, 0.0), (x0 - 3.0, 40.0, 0.0), 13.0, 15.0),
            Ellipsoid((x0 - 6.0, 20.0, -20.0), (24.0, 20.0, 16.0)),
            Ellipsoid((x0 - 6.0, 20.0, 20.0), (24.0, 20.0, 16.0)),
        ),
        k=8.0,
    )
    tibia = SmoothUnion(
        (
            RoundCone((x0, -175.0, 0.0), (x0, -25.0, 0.0), 12.0, 16.0),
            Ellipsoid((x0 - 2.0, -14.0, 0.0), (28.0, 9.0, 38.0)),
        ),
        k=6.0,
    )
    # Neither the fibula nor the patella is a body of revolution (a round fibular head or
    # a disc-shaped patella would leave a rotation that no image shows): the fibular head
    # is longer antero-posteriorly than it is wide and sits off the shaft's axis, and the
    # patella is a rounded triangle, its broad base proximal and its apex distal.
    fibula = SmoothUnion(
        (
            RoundCone((x0 - 14.0, -175.0, 31.0), (x0 - 12.0, -40.0, 32.0), 6.0, 7.0),
            Ellipsoid((x0 - 11.0, -36.0, 31.0), (10.0, 7.0, 7.0)),
        ),
        k=4.0,
    )
    patella = SmoothUnion(
        (
            Ellipsoid((x0 + 33.0, 31.0, 0.0), (10.0, 15.0, 18.0)),
            Ellipsoid((x0 + 32.0, 17.0, 0.0), (7.5, 9.0, 10.0)),
        ),
        k=4.0,
    )
    body = SmoothUnion(
        (
            RoundCone((x0 - 5.0, 190.0, 0.0), (x0 - 2.0, 45.0, 0.0), 64.0, 56.0),
            Ellipsoid((x0 + 2.0, 10.0, 0.0), (58.0, 70.0, 60.0)),
            RoundCone((x0 - 6.0, -20.0, 0.0), (x0 - 2.0, -190.0, 0.0), 52.0, 38.0),
        ),
        k=20.0,
    )
    return Anatomy(
        skeleton(),
        {"femur": femur, "tibia": tibia, "fibula": fibula, "patella": patella},
        body,
        joint_radius_mm={"knee": 55.0},
        cortex_mm=2.5,
        skin_mm=2.0,
        fat_mm=8.0,
        weight_power=2.0,
        weight_falloff_mm=40.0,
    )


def complete_angles(angles: dict) -> dict:
    """Fill in the coupled joints: fibula follows the tibia, patella 70 % of the flexion."""
    out = {k: np.asarray(v, float) for k, v in angles.items()}
    knee = out.get("knee", np.zeros(3))
    out.setdefault("tibiofibular", knee.copy())
    out.setdefault("patellofemoral", np.array([PATELLA_RATIO * knee[0], 0.0, 0.0]))
    return out


def default_poses(n: int, rng: np.random.Generator) -> list[dict]:
    """``n`` poses from straight (0°) to 70° flexion with screw-home rotation and small varus jitter."""
    flex = np.linspace(0.0, 70.0, n)
    poses = []
    for f in flex:
        rot = 8.0 * f / 70.0 + (rng.normal(0, 1.0) if f > 0 else 0.0)
        var = rng.normal(0, 1.0) if f > 0 else 0.0
        poses.append(complete_angles({"knee": [f, var, rot]}))
    return poses
