"""Run ANTs SyN (antspyx) in its own interpreter: ``python _ants_runner.py FIXED MOVING OUT_WARP SEED``.

antspyx pins an older NumPy and SciPy than this project's, so it lives in a
virtual environment of its own (``make bench-ants`` makes ``.venv-ants``) and
:func:`registration.baselines.ants_syn` calls this file there with image
paths.  Only antspyx is imported here.  The warp written is SyN's forward
displacement field: for every fixed-image point, the displacement (mm, ITK
physical space) to its moving-image point.
"""

import shutil
import sys

import ants

fixed, moving, out, seed = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
reg = ants.registration(
    ants.image_read(fixed),
    ants.image_read(moving),
    type_of_transform="SyNOnly",
    random_seed=seed,
    aff_metric="mattes",
    syn_metric="mattes",
)
warps = [t for t in reg["fwdtransforms"] if t.endswith((".nii.gz", ".nii"))]
shutil.copyfile(warps[0], out)
