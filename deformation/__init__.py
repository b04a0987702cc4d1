"""From transforms to deformed volumes and meshes.

* :mod:`deformation.geometry` — where a volume's voxels sit in world millimetres (spacing, origin, direction);
* :mod:`deformation.filters` — Gaussian smoothing of volumes, the one helper every package uses;
* :mod:`deformation.kinematics` — rigid transforms, skeletons, poses, rigid fits, dual quaternions;
* :mod:`deformation.meshes` — triangle meshes, tetrahedral meshes of the body, isosurfaces;
* :mod:`deformation.fields` — displacement fields, sampling and warping, the backward map, splines;
* :mod:`deformation.models` — skinning and harmonic weights, the polyrigid flow, EVD (Rhee Eq. 6–7), PSD and WPSD
  (Kurihara Eq. 6–8, 12–16), Kurihara's surface model.

``models`` uses ``fields``, ``meshes`` and ``kinematics``, which use only ``geometry`` and ``filters``
(import-linter's contract in pyproject.toml).
"""

import numba as _numba

# numba's threading layer, set once for every package (each imports deformation): Open3D ships an older TBB, and
# once it is loaded numba's default layer tries that TBB and warns; OpenMP (libgomp, a declared Debian dependency)
# instead.  A layer the user chose (NUMBA_THREADING_LAYER) is kept.
if _numba.config.THREADING_LAYER == "default":
    _numba.config.THREADING_LAYER = "omp"
