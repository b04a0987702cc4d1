"""Skeletons, joints, forward kinematics and poses.

A skeleton is a tree of bones (name, label id in the label map, parent).
Every non-root bone hangs from its parent by exactly one joint, which has a
centre (template world mm), an orthonormal joint frame with axes ``x``
(flexion/extension), ``y`` (ab/adduction) and ``z`` (axial twist, along the
child bone), and 1, 2, 3 or 6 degrees of freedom: ``[flex]``,
``[flex, abd]``, ``[flex, abd, twist]`` or ``[flex, abd, twist, tx, ty, tz]``.
Angles are in **degrees**, intrinsic rotations in the joint frame in the
order x, y, z (SciPy ``"XYZ"``); the 6-DOF translation is in mm along the
joint-frame axes.

The child's motion *relative to its parent* is (Kurihara §3, the matrix
``M_{i,k}`` of Kurihara Eq. 1)::

    M(θ) p = c + A (R(θ) Aᵀ (p − c) + t)

with ``c`` the joint centre, ``A`` the 3x3 matrix whose columns are the joint
axes, ``R(θ)`` the intrinsic XYZ rotation and ``t`` the 6-DOF translation.
Forward kinematics composes down the tree: ``T_child = T_parent @ M(θ)``; the
root bone's world transform is given (identity by default).  All transforms
map template world → scan world.  The JSON files ``skeleton.json`` and
``pose.json`` are described at :class:`Skeleton` and :class:`Pose`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from deformation.kinematics.transforms import apply, check_rigid, compose, invert

__all__ = ["Bone", "Joint", "Skeleton", "Pose", "SkeletonError", "VALID_DOF"]

VALID_DOF = (1, 2, 3, 6)
#: the rotations a joint without limits takes (degrees, either way)
HALF_TURN_DEG = 180.0
SKELETON_FORMAT = "avw-skeleton"
POSE_FORMAT = "avw-pose"


class SkeletonError(ValueError):
    """An inconsistent skeleton, joint or pose description."""


def _check_version(d: dict, what: str) -> None:
    # Exactly the integer 1: int() would let 1.5, "1", true and null through (or crash on null).
    version = d.get("version")
    if isinstance(version, bool) or not isinstance(version, int) or version != 1:
        raise SkeletonError(
            f"unsupported {what} version {version!r}: this workbench reads version 1 "
            f"(the integer 1 in the 'version' key)"
        )


@dataclass(frozen=True)
class Bone:
    name: str
    label: int
    parent: str | None = None


@dataclass(frozen=True)
class Joint:
    """A joint between ``parent`` and ``child`` bones.

    ``axes`` is the 3x3 matrix ``A`` whose *columns* are the joint frame's x,
    y, z axes in template world coordinates.
    """

    name: str
    parent: str
    child: str
    dof: int
    center: tuple[float, float, float]
    axes: np.ndarray = field(default_factory=lambda: np.eye(3))
    #: optional range of motion, one ``(low, high)`` per DOF (degrees, then mm for a 6-DOF joint's
    #: translations); what a user's pose is checked against (:meth:`Skeleton.limit_problems`)
    limits: tuple | None = None

    def __post_init__(self):
        if self.dof not in VALID_DOF:
            raise SkeletonError(f"joint {self.name!r}: dof must be one of {VALID_DOF}, got {self.dof}")
        c = np.asarray(self.center, dtype=float).reshape(-1)
        if c.shape != (3,) or not np.all(np.isfinite(c)):
            raise SkeletonError(f"joint {self.name!r}: center must be 3 finite numbers, got {self.center!r}")
        object.__setattr__(self, "center", tuple(float(v) for v in c))
        a = np.asarray(self.axes, dtype=float)
        if a.shape != (3, 3) or not np.allclose(a.T @ a, np.eye(3), atol=1e-6) or np.linalg.det(a) < 0:
            raise SkeletonError(
                f"joint {self.name!r}: axes must be a right-handed orthonormal frame (columns x, y, z), got\n{a}"
            )
        a = a.copy()
        a.setflags(write=False)
        object.__setattr__(self, "axes", a)
        if self.limits is not None:
            try:
                lim = np.asarray(self.limits, dtype=float)
            except (TypeError, ValueError):
                lim = np.zeros((0,))
            if lim.shape != (self.dof, 2) or not np.all(np.isfinite(lim)) or np.any(lim[:, 0] > lim[:, 1]):
                raise SkeletonError(
                    f"joint {self.name!r}: limits must be {self.dof} [low, high] pairs (degrees, "
                    f"then mm), low ≤ high, got {self.limits!r}"
                )
            object.__setattr__(self, "limits", tuple((float(lo), float(hi)) for lo, hi in lim))

    def outside_limits(self, angles) -> list[str]:
        """The values of ``angles`` outside the joint's limits, as ``"knee[0] = 1000° outside [-10, 150]"``.

        A joint without limits still takes its rotations within ±180° (``HALF_TURN_DEG``): a larger
        angle is the same rotation as one within it, and in a pose file it is a slip (1000 for 100, or
        radians × 100); its translations are not checked."""
        a = np.asarray(angles, dtype=float).reshape(-1)
        if self.limits is None:
            return [
                f"{self.name}[{k}] = {v:g}° is more than half a turn (the joint has no 'limits' in the skeleton; "
                f"its rotations are taken within ±{HALF_TURN_DEG:g}°)"
                for k, v in enumerate(a[:3])
                if not -HALF_TURN_DEG <= v <= HALF_TURN_DEG
            ]
        out = []
        for k, (v, (lo, hi)) in enumerate(zip(a, self.limits)):
            if not lo <= v <= hi:
                unit = "°" if k < 3 else " mm"
                out.append(f"{self.name}[{k}] = {v:g}{unit} outside [{lo:g}, {hi:g}]")
        return out

    def __eq__(self, other):
        if not isinstance(other, Joint):
            return NotImplemented
        return (self.name, self.parent, self.child, self.dof, self.center) == (
            other.name,
            other.parent,
            other.child,
            other.dof,
            other.center,
        ) and np.array_equal(self.axes, other.axes)

    __hash__ = None  # mutable-looking array field: not hashable

    @property
    def n_rotations(self) -> int:
        return min(self.dof, 3)

    def full_angles(self, angles) -> np.ndarray:
        """Pad ``angles`` (length ``dof``) to ``[rx, ry, rz, tx, ty, tz]``."""
        a = np.asarray(angles, dtype=float).reshape(-1)
        if a.shape != (self.dof,):
            raise SkeletonError(f"joint {self.name!r} has {self.dof} DOF but got {a.size} values: {list(a)}")
        if not np.all(np.isfinite(a)):
            raise SkeletonError(f"joint {self.name!r}: angles must be finite, got {list(a)}")
        out = np.zeros(6)
        out[: min(self.dof, 3)] = a[:3]
        if self.dof == 6:
            out[3:] = a[3:]
        return out

    def local_rotation(self, angles) -> np.ndarray:
        """3x3 ``R(θ)`` in the joint frame (intrinsic XYZ, degrees)."""
        full = self.full_angles(angles)
        return Rotation.from_euler("XYZ", full[:3], degrees=True).as_matrix()

    def motion(self, angles) -> np.ndarray:
        """4x4 child-relative-to-parent motion ``M(θ)`` in template world (see module doc)."""
        full = self.full_angles(angles)
        a = self.axes
        r = a @ Rotation.from_euler("XYZ", full[:3], degrees=True).as_matrix() @ a.T
        c = np.asarray(self.center)
        m = np.eye(4)
        m[:3, :3] = r
        m[:3, 3] = c - r @ c + a @ full[3:]
        return m

    def angles_from_motion(self, motion) -> np.ndarray:
        """Recover the joint's ``dof`` values from a relative motion ``M`` (inverse of :meth:`motion`).

        For joints with fewer than 3 DOF the rotation is projected onto the
        allowed axes (the unused Euler angles are dropped).
        """
        m = np.asarray(motion, dtype=float)
        a = self.axes
        r_local = a.T @ m[:3, :3] @ a
        rot = Rotation.from_matrix(r_local).as_euler("XYZ", degrees=True)
        if self.dof == 6:
            c = np.asarray(self.center)
            t = a.T @ (m[:3, 3] - c + m[:3, :3] @ c)
            return np.concatenate([rot, t])
        return rot[: self.dof]

    def to_dict(self) -> dict:
        a = self.axes
        return {
            "name": self.name,
            "parent": self.parent,
            "child": self.child,
            "dof": int(self.dof),
            "center": list(self.center),
            "axes": {"x": a[:, 0].tolist(), "y": a[:, 1].tolist(), "z": a[:, 2].tolist()},
            **({"limits": [list(p) for p in self.limits]} if self.limits is not None else {}),
        }

    @classmethod
    def from_dict(cls, d: dict) -> Joint:
        try:
            ax = d.get("axes")
            axes = np.eye(3) if ax is None else np.column_stack([ax["x"], ax["y"], ax["z"]])
            return cls(
                name=d["name"],
                parent=d["parent"],
                child=d["child"],
                dof=int(d["dof"]),
                center=d["center"],
                axes=axes,
                limits=d.get("limits"),
            )
        except KeyError as e:
            raise SkeletonError(f"joint entry {d!r} lacks the key {e}") from e


class Skeleton:
    """A tree of bones connected by joints, with forward kinematics.

    JSON schema (``skeleton.json``, ``to_dict()``)::

        {"format": "avw-skeleton", "version": 1, "name": "knee",
         "units": "mm", "angle_units": "deg", "euler": "intrinsic XYZ in the joint frame",
         "bones":  [{"name": "femur", "label": 1, "parent": null}, ...],
         "joints": [{"name": "knee", "parent": "femur", "child": "tibia", "dof": 3,
                     "center": [x, y, z],
                     "axes": {"x": [..], "y": [..], "z": [..]},
                     "limits": [[low, high], ...]}, ...]}     # optional: range of motion per DOF
    """

    def __init__(self, bones, joints, *, name: str = "skeleton"):
        self.name = str(name)
        self.bones: tuple[Bone, ...] = tuple(bones)
        self.joints: tuple[Joint, ...] = tuple(joints)
        self._validate()
        self._bone = {b.name: b for b in self.bones}
        self._joint = {j.name: j for j in self.joints}
        self._joint_of_child = {j.child: j for j in self.joints}
        self.order: tuple[str, ...] = self._topological_order()

    # -- validation ----------------------------------------------------------
    def _validate(self):
        names = [b.name for b in self.bones]
        if len(set(names)) != len(names):
            raise SkeletonError(f"skeleton {self.name!r}: bone names must be unique, got {names}")
        labels = [b.label for b in self.bones]
        if len(set(labels)) != len(labels) or min(labels, default=1) < 1:
            raise SkeletonError(f"skeleton {self.name!r}: bone labels must be unique positive integers, got {labels}")
        roots = [b.name for b in self.bones if b.parent is None]
        if len(roots) != 1:
            raise SkeletonError(f"skeleton {self.name!r}: exactly one root bone (parent null) expected, got {roots}")
        for b in self.bones:
            if b.parent is not None and b.parent not in names:
                raise SkeletonError(f"bone {b.name!r}: parent {b.parent!r} is not a bone of the skeleton")
        jnames = [j.name for j in self.joints]
        if len(set(jnames)) != len(jnames):
            raise SkeletonError(f"skeleton {self.name!r}: joint names must be unique, got {jnames}")
        parent_of = {b.name: b.parent for b in self.bones}
        children = [j.child for j in self.joints]
        for j in self.joints:
            if j.child not in parent_of:
                raise SkeletonError(f"joint {j.name!r}: child {j.child!r} is not a bone")
            if parent_of[j.child] != j.parent:
                raise SkeletonError(
                    f"joint {j.name!r} links {j.parent!r} → {j.child!r}, but bone {j.child!r} has parent "
                    f"{parent_of[j.child]!r}: make the joint's parent the bone's parent"
                )
        for b in self.bones:
            if b.parent is not None and children.count(b.name) != 1:
                raise SkeletonError(
                    f"bone {b.name!r} must hang from its parent by exactly one joint, found {children.count(b.name)}"
                )

    def _topological_order(self) -> tuple[str, ...]:
        order, seen = [], set()
        kids: dict[str | None, list[str]] = {}
        for b in self.bones:
            kids.setdefault(b.parent, []).append(b.name)
        stack = list(reversed(kids[None]))
        while stack:
            n = stack.pop()
            if n in seen:
                raise SkeletonError(f"skeleton {self.name!r} has a cycle through {n!r}")
            seen.add(n)
            order.append(n)
            stack.extend(reversed(kids.get(n, [])))
        if len(order) != len(self.bones):
            missing = sorted(set(b.name for b in self.bones) - seen)
            raise SkeletonError(f"skeleton {self.name!r}: bones {missing} are not connected to the root (cycle?)")
        return tuple(order)

    # -- access --------------------------------------------------------------
    @property
    def root(self) -> str:
        return self.order[0]

    @property
    def bone_names(self) -> list[str]:
        return [b.name for b in self.bones]

    @property
    def joint_names(self) -> list[str]:
        return [j.name for j in self.joints]

    def bone(self, name: str) -> Bone:
        try:
            return self._bone[name]
        except KeyError:
            raise SkeletonError(f"no bone {name!r} in skeleton {self.name!r}; bones: {self.bone_names}") from None

    def joint(self, name: str) -> Joint:
        try:
            return self._joint[name]
        except KeyError:
            raise SkeletonError(f"no joint {name!r} in skeleton {self.name!r}; joints: {self.joint_names}") from None

    def joint_of(self, child_bone: str) -> Joint | None:
        """The joint by which ``child_bone`` hangs from its parent (None for the root)."""
        return self._joint_of_child.get(child_bone)

    def label_of(self, bone_name: str) -> int:
        return self.bone(bone_name).label

    @property
    def n_dof(self) -> int:
        return sum(j.dof for j in self.joints)

    # -- kinematics ------------------------------------------------------------
    def zero_angles(self) -> dict[str, np.ndarray]:
        return {j.name: np.zeros(j.dof) for j in self.joints}

    def limit_problems(self, angles: dict) -> list[str]:
        """Every joint value of ``angles`` outside its joint's limits (for a joint without limits: a rotation beyond
        ±180°, :meth:`Joint.outside_limits`)."""
        return [p for name, v in angles.items() if name in self._joint for p in self._joint[name].outside_limits(v)]

    def forward_kinematics(self, angles: dict | None = None, *, root_transform=None) -> dict[str, np.ndarray]:
        """World transform (template → scan) of every bone for the given joint angles.

        Parameters
        ----------
        angles : dict joint name → sequence of ``dof`` values (degrees, mm)
            Missing joints stay at zero; unknown joint names are an error.
        root_transform : 4x4, optional
            World transform of the root bone (identity by default).
        """
        angles = {} if angles is None else dict(angles)
        unknown = set(angles) - set(self._joint)
        if unknown:
            raise SkeletonError(f"unknown joints {sorted(unknown)}; skeleton {self.name!r} has {self.joint_names}")
        root = np.eye(4) if root_transform is None else check_rigid(root_transform, name="root_transform")
        out: dict[str, np.ndarray] = {}
        for name in self.order:
            j = self._joint_of_child.get(name)
            if j is None:
                out[name] = root.copy()
            else:
                theta = angles.get(j.name, np.zeros(j.dof))
                out[name] = compose(out[j.parent], j.motion(theta))
        return out

    def relative_motion(self, transforms: dict, joint_name: str) -> np.ndarray:
        """``M = T_parent⁻¹ T_child``: the child's motion with the parent held in the template pose."""
        j = self.joint(joint_name)
        return compose(invert(transforms[j.parent]), transforms[j.child])  # Kurihara Eq. 1's M_{i,k}

    def pose(self, angles: dict | None = None, *, root_transform=None) -> Pose:
        """Forward kinematics packaged as a :class:`Pose` (transforms, angles and scan-space centres)."""
        transforms = self.forward_kinematics(angles, root_transform=root_transform)
        full = self.zero_angles()
        full.update({k: np.asarray(v, dtype=float) for k, v in (angles or {}).items()})
        centres = {j.name: apply(transforms[j.parent], j.center) for j in self.joints}
        return Pose(transforms, joint_angles=full, joint_centers=centres, skeleton=self.name)

    # -- (de)serialisation ---------------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "format": SKELETON_FORMAT,
            "version": 1,
            "name": self.name,
            "units": "mm",
            "angle_units": "deg",
            "euler": "intrinsic XYZ in the joint frame",
            "bones": [{"name": b.name, "label": int(b.label), "parent": b.parent} for b in self.bones],
            "joints": [j.to_dict() for j in self.joints],
        }

    @classmethod
    def from_dict(cls, d: dict) -> Skeleton:
        if d.get("format") != SKELETON_FORMAT:
            raise SkeletonError(
                f"not a skeleton description: 'format' is {d.get('format')!r}, expected {SKELETON_FORMAT!r}"
            )
        _check_version(d, "skeleton")
        try:
            bones = [Bone(b["name"], int(b["label"]), b.get("parent")) for b in d["bones"]]
        except KeyError as e:
            raise SkeletonError(f"a bone entry lacks the key {e}") from e
        joints = [Joint.from_dict(j) for j in d.get("joints", [])]
        return cls(bones, joints, name=d.get("name", "skeleton"))

    def __eq__(self, other):
        if not isinstance(other, Skeleton):
            return NotImplemented
        return self.name == other.name and self.bones == other.bones and self.joints == other.joints

    __hash__ = None

    def __repr__(self):
        return f"Skeleton({self.name!r}, {len(self.bones)} bones, {len(self.joints)} joints, {self.n_dof} DOF)"


@dataclass
class Pose:
    """One template → scan world transform per bone (Rhee §3.1's pose vector ``P_k``).

    ``joint_angles`` and ``joint_centers`` (scan world, mm) are optional
    extras recorded with ground truth or estimated by pose recovery.
    JSON schema (``pose.json``, ``to_dict()``)::

        {"format": "avw-pose", "version": 1, "skeleton": "knee",
         "bones": {"femur": [[4x4 rows]], ...},
         "joints": {"knee": {"angles_deg": [...], "center_scan": [x, y, z]}, ...}}
    """

    transforms: dict[str, np.ndarray]
    joint_angles: dict[str, np.ndarray] | None = None
    joint_centers: dict[str, np.ndarray] | None = None
    skeleton: str | None = None

    def __post_init__(self):
        self.transforms = {k: check_rigid(v, name=f"transform of bone {k!r}") for k, v in self.transforms.items()}
        if self.joint_angles is not None:
            self.joint_angles = {k: np.asarray(v, dtype=float) for k, v in self.joint_angles.items()}
        if self.joint_centers is not None:
            self.joint_centers = {k: np.asarray(v, dtype=float) for k, v in self.joint_centers.items()}

    def __getitem__(self, bone: str) -> np.ndarray:
        return self.transforms[bone]

    def to_dict(self) -> dict:
        d = {
            "format": POSE_FORMAT,
            "version": 1,
            "skeleton": self.skeleton,
            "bones": {k: np.asarray(v).tolist() for k, v in self.transforms.items()},
        }
        if self.joint_angles is not None or self.joint_centers is not None:
            names = sorted(set(self.joint_angles or {}) | set(self.joint_centers or {}))
            joints = {}
            for n in names:
                e = {}
                if self.joint_angles and n in self.joint_angles:
                    e["angles_deg"] = np.asarray(self.joint_angles[n]).tolist()
                if self.joint_centers and n in self.joint_centers:
                    e["center_scan"] = np.asarray(self.joint_centers[n]).tolist()
                joints[n] = e
            d["joints"] = joints
        return d

    @classmethod
    def from_dict(cls, d: dict) -> Pose:
        if d.get("format") != POSE_FORMAT:
            raise SkeletonError(f"not a pose: 'format' is {d.get('format')!r}, expected {POSE_FORMAT!r}")
        _check_version(d, "pose")
        if "bones" not in d:
            raise SkeletonError("a pose lacks the key 'bones' (one 4x4 transform per bone)")
        joints = d.get("joints")
        angles = centers = None
        if joints is not None:
            # An attribute that no joint entry carries was not recorded (None), as before writing.
            angles = {k: v["angles_deg"] for k, v in joints.items() if "angles_deg" in v} or None
            centers = {k: v["center_scan"] for k, v in joints.items() if "center_scan" in v} or None
        return cls(
            {k: np.asarray(v, dtype=float) for k, v in d["bones"].items()},
            joint_angles=angles,
            joint_centers=centers,
            skeleton=d.get("skeleton"),
        )
