"""Real wrist bones in three poses: a loader with exact ground-truth bone motion.

The data (``../shared/data/wrist-bones-mri/`` beside the project; see
``/work/shared/data/README.md``) are bone surfaces segmented from wrist MRI of
two volunteers (Foster et al. 2019, J. Biomechanics; MIT licence, from
ajchaudhari/PCA-Kinematics).  Each file
``volunteer<k>_<pose>.ply`` holds all bones of one volunteer in one pose
(``neutral``, ``radial_deviation``, ``ulnar_deviation``); the three files of a
volunteer have the same vertices in the same order and the same triangles, so
vertex *i* is the same anatomical point in every pose.

:func:`load_wrist_study` splits the mesh into its bones — the large connected
components; a few tiny components are segmentation debris and are dropped —
and :func:`true_motion` fits each bone's rigid motion between two poses
(least squares over all its vertices), the ground truth for ICP and
joint-centre experiments.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from deformation.kinematics.rigid_fit import fit_rigid, rigid_residuals
from deformation.meshes.mesh import SurfaceMesh, connected_components, submesh
from workbench.errors import InputFileError, MissingFileError
from workbench.io.meshes import read_mesh

__all__ = [
    "POSES",
    "WristBone",
    "WristBoneStudy",
    "BoneMotion",
    "WristDataError",
    "default_wrist_root",
    "find_wrist_data",
    "wrist_volunteers",
    "load_wrist_study",
    "true_motion",
]

#: Poses present for every volunteer, neutral first.
POSES = ("neutral", "radial_deviation", "ulnar_deviation")

_FILE_PATTERN = re.compile(r"volunteer(\d+)_(" + "|".join(POSES) + r")\.ply$")


class WristDataError(InputFileError):
    """The wrist files do not split into the same bones in every pose."""


@dataclass(frozen=True, eq=False)
class WristBone:
    """One bone of a volunteer, in every pose.

    Attributes
    ----------
    index : int
        Position of the bone in ``WristBoneStudy.bones`` (0-based; bones
        are ordered by their lowest vertex index in the source mesh, which is
        the same in every pose).
    vertex_ids : (n,) ndarray of int64
        Indices of the bone's vertices in the source PLY files (ascending).
    triangles : (m, 3) ndarray of int64
        Triangles, indexing into ``vertex_ids`` (local indices).
    positions : dict[str, (n, 3) ndarray]
        Vertex positions (mm) per pose, rows matching ``vertex_ids``.
    """

    index: int
    vertex_ids: np.ndarray
    triangles: np.ndarray
    positions: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def n_vertices(self) -> int:
        return int(self.vertex_ids.size)

    @property
    def n_triangles(self) -> int:
        return int(self.triangles.shape[0])

    def mesh(self, pose: str) -> SurfaceMesh:
        """The bone's surface in one pose."""
        return SurfaceMesh(self.positions[pose], self.triangles)


@dataclass(frozen=True, eq=False)
class WristBoneStudy:
    """The bones of one volunteer in several poses.

    Attributes
    ----------
    volunteer : int
        Volunteer number from the file names.
    poses : tuple of str
        Poses loaded, in :data:`POSES` order.
    bones : list of WristBone
        The bones, ordered by lowest source vertex index.
    debris_sizes : tuple of int
        Triangle count of each small component that was dropped (debris).
    files : dict[str, pathlib.Path]
        Source file of each pose.
    """

    volunteer: int
    poses: tuple[str, ...]
    bones: list[WristBone]
    debris_sizes: tuple[int, ...] = ()
    files: dict[str, Path] = field(default_factory=dict)

    @property
    def n_debris_triangles(self) -> int:
        """Triangles dropped as debris."""
        return int(sum(self.debris_sizes))


@dataclass(frozen=True)
class BoneMotion:
    """Least-squares rigid motion of a bone between two poses.

    Attributes
    ----------
    transform : (4, 4) ndarray
        Maps the bone's positions in ``from_pose`` to those in ``to_pose``
        (``T @ [p_from, 1] ≈ [p_to, 1]``), world mm.
    rms_mm : float
        Root-mean-square residual distance over the bone's vertices.
    max_mm : float
        Largest residual distance.
    rotation_deg : float
        Rotation angle of ``transform``.
    translation_mm : float
        Length of the translation part of ``transform``.
    """

    transform: np.ndarray
    rms_mm: float
    max_mm: float
    rotation_deg: float
    translation_mm: float


def default_wrist_root() -> Path:
    """``<project root>/../shared/data/wrist-bones-mri`` (resolved from this file)."""
    return (Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "wrist-bones-mri").resolve()


def find_wrist_data(root: str | os.PathLike | None = None) -> Path | None:
    """The wrist data folder, or None when it (or its PLY files) is absent.

    Parameters
    ----------
    root : str or os.PathLike, optional
        Folder holding ``volunteer<k>_<pose>.ply``; :func:`default_wrist_root`
        by default.

    Returns
    -------
    pathlib.Path or None
        The folder if it holds at least one complete volunteer (all poses).
    """
    folder = Path(root) if root is not None else default_wrist_root()
    if not folder.is_dir():
        return None
    return folder if wrist_volunteers(folder) else None


def wrist_volunteers(root: str | os.PathLike | None = None) -> list[int]:
    """Volunteer numbers for which every pose's file is present, ascending."""
    folder = Path(root) if root is not None else default_wrist_root()
    if not folder.is_dir():
        return []
    found: dict[int, set[str]] = {}
    for p in folder.iterdir():
        m = _FILE_PATTERN.match(p.name)
        if m:
            found.setdefault(int(m.group(1)), set()).add(m.group(2))
    return sorted(v for v, poses in found.items() if poses == set(POSES))


def _bone_triangle_sets(mesh: SurfaceMesh, min_triangles: int) -> tuple[list[np.ndarray], tuple[int, ...]]:
    """Triangle indices of each large component (ordered by lowest vertex), and the debris sizes."""
    n, labels = connected_components(mesh)
    sizes = np.bincount(labels, minlength=n)
    keep = [np.flatnonzero(labels == c) for c in range(n) if sizes[c] >= min_triangles]
    debris = tuple(int(k) for k in sizes[sizes < min_triangles])
    return keep, debris


def load_wrist_study(
    volunteer: int,
    *,
    root: str | os.PathLike | None = None,
    poses: tuple[str, ...] = POSES,
    min_bone_triangles: int = 100,
    expected_bones: int | None = 10,
) -> WristBoneStudy:
    """Load one volunteer's bones in several poses.

    Parameters
    ----------
    volunteer : int
        Volunteer number (1 or 2 in the published data).
    root : str or os.PathLike, optional
        Data folder; :func:`default_wrist_root` by default.
    poses : tuple of str, optional
        Poses to load (a subset of :data:`POSES`).
    min_bone_triangles : int, optional
        Components with fewer triangles are debris and are dropped (the data's
        debris has at most 4 triangles, its smallest bone 4,950).
    expected_bones : int or None, optional
        Number of bones the split must give (10 for these data); None skips
        the check.

    Returns
    -------
    WristBoneStudy

    Raises
    ------
    MissingFileError
        A pose's file is absent.
    WristDataError
        The poses do not share vertex count and triangles, the components
        differ between poses, or the number of bones is not ``expected_bones``.
    """
    folder = Path(root) if root is not None else default_wrist_root()
    unknown = set(poses) - set(POSES)
    if unknown or not poses:
        raise ValueError(f"poses must be a non-empty subset of {POSES}, got {poses!r}")
    poses = tuple(p for p in POSES if p in poses)
    files = {pose: folder / f"volunteer{volunteer}_{pose}.ply" for pose in poses}
    for pose, f in files.items():
        if not f.is_file():
            have = wrist_volunteers(folder)
            raise MissingFileError(
                f"{f}: wrist data for volunteer {volunteer}, pose {pose!r} not found. "
                f"Volunteers with all poses in {folder}: {have or 'none'}. Check root= and volunteer=.",
                f,
            )
    meshes = {pose: read_mesh(f) for pose, f in files.items()}
    first_pose = poses[0]
    reference = meshes[first_pose]
    for pose in poses[1:]:
        m = meshes[pose]
        if m.n_vertices != reference.n_vertices or not np.array_equal(m.triangles, reference.triangles):
            raise WristDataError(
                f"{files[pose]}: does not share the vertex list and triangles of {files[first_pose].name} "
                f"({m.n_vertices} vs {reference.n_vertices} vertices, {m.n_triangles} vs "
                f"{reference.n_triangles} triangles), so vertices cannot be matched across poses. "
                "Use the original files of the data set.",
                files[pose],
            )
    components = {pose: _bone_triangle_sets(meshes[pose], min_bone_triangles) for pose in poses}
    bone_tris, debris = components[first_pose]
    for pose in poses[1:]:
        other, _ = components[pose]
        same = len(other) == len(bone_tris) and all(np.array_equal(a, b) for a, b in zip(other, bone_tris))
        if not same:
            raise WristDataError(
                f"{files[pose]}: splits into {len(other)} bones whose triangle sets differ from the "
                f"{len(bone_tris)} bones of {files[first_pose].name}; the poses must share the mesh. "
                "Use the original files of the data set.",
                files[pose],
            )
    if expected_bones is not None and len(bone_tris) != expected_bones:
        sizes = sorted((t.size for t in bone_tris), reverse=True)
        raise WristDataError(
            f"{files[first_pose]}: found {len(bone_tris)} components with at least "
            f"{min_bone_triangles} triangles (sizes {sizes}), expected {expected_bones} bones. "
            "Adjust min_bone_triangles= or expected_bones=.",
            files[first_pose],
        )
    bones = []
    for index, tri_ids in enumerate(bone_tris):
        mask = np.zeros(reference.n_triangles, dtype=bool)
        mask[tri_ids] = True
        sub, vertex_ids = submesh(reference, mask)
        positions = {pose: meshes[pose].vertices[vertex_ids] for pose in poses}
        for p in positions.values():
            p.flags.writeable = False
        bones.append(WristBone(index=index, vertex_ids=vertex_ids, triangles=sub.triangles, positions=positions))
    return WristBoneStudy(volunteer=volunteer, poses=poses, bones=bones, debris_sizes=debris, files=files)


def _rotation_angle_deg(rotation: np.ndarray) -> float:
    cos = np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos)))


def true_motion(study: WristBoneStudy, bone: WristBone | int, from_pose: str, to_pose: str) -> BoneMotion:
    """Ground-truth rigid motion of a bone between two poses.

    Parameters
    ----------
    study : WristBoneStudy
        A loaded study.
    bone : WristBone or int
        The bone, or its index in ``study.bones``.
    from_pose, to_pose : str
        Poses of ``study``.

    Returns
    -------
    BoneMotion
        Least-squares rigid fit (:func:`deformation.kinematics.rigid_fit.fit_rigid`) over
        all the bone's vertices, template = ``from_pose``, scan = ``to_pose``,
        and its residuals.
    """
    b = study.bones[bone] if isinstance(bone, (int, np.integer)) else bone
    for pose in (from_pose, to_pose):
        if pose not in b.positions:
            raise ValueError(f"pose {pose!r} not loaded; the study has {study.poses}")
    src, dst = b.positions[from_pose], b.positions[to_pose]
    T = fit_rigid(src, dst)
    r = rigid_residuals(T, src, dst)
    return BoneMotion(
        transform=T,
        rms_mm=float(np.sqrt(np.mean(r**2))),
        max_mm=float(r.max()),
        rotation_deg=_rotation_angle_deg(T[:3, :3]),
        translation_mm=float(np.linalg.norm(T[:3, 3])),
    )
