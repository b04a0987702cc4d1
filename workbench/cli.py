"""The ``workbench`` command line.

Thin entry points (nibabel ``cmdline`` style): each subcommand parses its
arguments, calls one library function, writes or prints, and returns an exit
status.  Heavy imports happen inside the subcommands so ``--help`` is fast.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

from workbench import __version__

DESCRIPTION = """\
Articulated Volume Workbench: posable, person-specific volume models of an
articulated body region (hand, knee) from a few CT/MRI scans in different
poses, validated against synthetic ground truth.  Implements Kurihara &
Miyata 2004 and Rhee et al. 2011.

A *study* is a folder with a study.json manifest naming the template scan, its
bone label map, the skeleton and the posed scans (see README.md).
"""

EPILOG = """\
examples:
  workbench phantom knee --out knee-study                 # small MRI-like knee, 4 poses
  workbench run knee-study                                # every stage: bones ... register, model, validate
  workbench phantom hand --out hand --size paper --modality ct
  workbench phantom knee --out bend10 --posing vbd --poses-file bend10.json
  workbench info knee-study
  workbench pose knee-study                               # bone poses, joint centres and angles
  workbench pose knee-study --method surface --force
  workbench weights knee-study                            # harmonic skinning weights (tet mesh kept in the study)
  workbench model knee-study                              # EVD model from the registrations (Rhee Eq. 7)
  workbench deform knee-study --pose bend.json --out bent.nii.gz
  workbench register knee-study                           # polyrigid start + dense registration
  workbench render knee-study --out knee.png --clip z:0.5 --bones
  workbench animate knee-study --out knee.mp4             # bend and straighten (ready keyframes)
  workbench reproduce all --out tables                    # the papers' tables on phantoms
  workbench report knee-study --out report.html           # HTML validation report
"""

REPORT_HELP = """Write one self-contained HTML validation report (opens offline, in any browser).

For a study (the report stage, which `workbench run` ends with; the file is
also kept as STUDY/report/report.html):
  - bone poses: joint angles per scan, Kurihara Eq. 1 residual per joint
  - registration: similarity (SSD, CC, MI) before and after, folded voxels,
    time, convergence plots, the registration's displacement and Jacobian maps
  - overlays of the registered template (green) on its scan (magenta) on three
    planes, with a toggle / flicker between the two
  - with ground truth: MED (body, markers), SSD, CC, MI per volume, error maps,
    each marker's error
  - pictures in STUDY/renders/ (e.g. from `workbench render STUDY --out
    STUDY/renders/knee.png`)
  - software versions, every stage's settings, the study digest
For a `workbench reproduce` folder: every table with its definitions, then the
last registration of each study it ran.

examples:
  workbench report knee-study --out knee-report.html
  workbench report tables --out tables.html
"""

REPRODUCE_HELP = """Reproduce the papers' tables on phantoms with exact ground truth.

Each table runs the pipeline's stages (bones, pose, weights, init, register,
validate) on a phantom study written under DIR/studies/, then writes
DIR/<table>.csv, .md and .json with the paper's figures beside ours and the
definition of every measure, and prints it:

  table2      Rhee Table 2: the knee bent 10 deg by VBD, registered without initialisation
  table3      Rhee Table 3: knee, 4 poses, template registered to the other 3 after VBD
              from the estimated poses; MED (body, markers), SSD, CC, MI, folded
  table4      Rhee Table 4: hand, 10 poses, the same over 9 registrations
              (tables 2-4: the pipeline's registration and, beside it, Rhee's
              Algorithm 1 as implemented here, run as --method adaptive would
              from the same start; rerun every time, no stage keeps it)
  loo         leave one scan out: VBD against EVD built from the other scans'
              registrations, both against the held-out truth (knee and hand)
  eigenposes  principal components of 71 documented grasp/sign/gesture hand poses
  kurihara    Kurihara Eq. 1 joint centres of a CT hand in 5 poses (ICP of bones)
  kurihara_skin  Kurihara §4-5 on the same study: fitted skin meshes against the true
              skin, touching fingers (nearest vs regularised fit), leave one pose out
              and one finger alone by SSD, PSD and WPSD
  all         every one of them

A second run into the same DIR reuses every finished stage (loo reuses the
registrations of table3 and table4).  --size test takes minutes, --size paper
(Rhee's grids) hours.

examples:
  workbench reproduce all --out tables
  workbench reproduce table3 loo --out tables --with-peers
"""

RENDER_HELP = """Render a volume (or a study's template, scan or registered template) off-screen to a PNG.

VTK volume ray casting without a display: EGL, else OSMesa (AVW_OPENGL=egl|osmesa
forces one); on software OpenGL the CPU ray caster (vtkFixedPointVolumeRayCastMapper),
with a GPU the GPU ray caster.  The volume is placed in world mm by its origin,
spacing and direction; the camera is fitted to the visible tissue.

presets (--preset): 'mri' (T1-like: fat and marrow bright; relative to the volume's
0.5-99.5 % intensity range, so any units work), 'ct' (Hounsfield units: bone
ivory and dense, soft tissue faint), or your own JSON file:
  {"color": [[value, r, g, b], ...], "opacity": [[value, alpha], ...],
   "relative": false, "unit_mm": 4.0, "shade": true}
with r, g, b in 0..1, alpha per unit_mm of ray, and values in intensity units
(or fractions of the robust range when "relative" is true).

views (--camera): auto (from the thinnest side of the anatomy, longest axis up, turned
30 deg / 15 deg), iso, or a world axis +x -x +y -y +z -z (ITK/LPS physical space);
--azimuth/--elevation turn it further, --zoom enlarges.

--clip AXIS:FRACTION cuts across a world axis at that fraction of the anatomy's
extent, removing the side facing the camera (Rhee Fig. 10); +AXIS keeps the larger
coordinates, -AXIS the smaller.  --bones draws the template's label map as opaque
surfaces; --overlay draws a second volume in magenta against the first in cyan
(Rhee Figs. 1, 8, 9, 11); --difference shows the signed difference (red: first
brighter, blue: darker).  --markers draws the ground truth's skin markers (white),
--control-points the control points a registration allocated, coloured by block
level (Rhee Fig. 9).  --mesh draws a mesh (world mm: `workbench surface`'s skins,
`surface-deform`'s posed skin) with the volume (opaque: it hides the tissue behind
it; --clip cuts both); a mesh file as the source is rendered alone (the camera
fitted to it).

examples:
  workbench render knee-study --out template.png
  workbench render knee-study --out interior.png --clip z:0.5 --bones
  workbench render knee-study --scan pose02 --out scan.png --preset mri --camera +z
  workbench render knee-study --registered pose02 --overlay pose02 --out overlay.png
  workbench render knee-study --registered pose02 --overlay pose02 --control-points --markers --out fig9.png
  workbench render bent.nii.gz --out bent.png --size 1280x960 --background white
  workbench render hand-study/surface/pose02_fitted.ply --out skin.png        # a mesh alone
  workbench render hand-study --scan pose02 --mesh hand-study/surface/pose02_fitted.ply --out fit.png
"""

ANIMATE_HELP = """Animate the study's template through keyframe poses and write a video.

Each frame: joint angles interpolated between keyframes, the template deformed
(EVD, Rhee Eq. 6-7, when the study has a model - `workbench model` - else VBD,
Eq. 2), volume-rendered off-screen (see `workbench render --help`) and encoded:
.mp4 (H.264 through the ffmpeg binary of imageio-ffmpeg; no system ffmpeg needed),
.gif, or .png (numbered frames NAME_0000.png ...).  The camera is fitted once to
the anatomy over all keyframe poses, so nothing leaves the picture.

keyframes (--keyframes FILE, JSON; ready files for the knee - bend to 60 deg and
straighten - and the hand - open, fist, point with the index finger - are used
when it is omitted; see workbench/viz/keyframes/):
  {"format": "avw-keyframes", "version": 1, "skeleton": "knee",
   "interpolation": "smooth",      # smoothstep between keyframes, or "linear"
   "fps": 24, "camera": {"view": "auto", "azimuth": 0, "elevation": 0, "zoom": 1, "orbit": 0},
   "keyframes": [{"time": 0.0, "angles": {"knee": [0, 0, 0]}},
                 {"time": 1.25, "angles": {"knee": [60, 0, 0]}}]}
Joints left out of a keyframe stay at 0; angles in degrees (then mm for 6-DOF joints).
--keyframes scans goes from the rest pose through every scan's estimated pose and
back (Kurihara Fig. 9).  --skin ssd|psd|wpsd animates Kurihara's skin mesh
(`workbench surface`) instead of the volume: milliseconds a frame.

examples:
  workbench animate knee-study --out knee.mp4
  workbench animate hand-study --out hand.gif --fps 12 --size 480x360
  workbench animate knee-study --keyframes my.json --out frames/knee.png --clip z:0.5 --orbit 90
  workbench animate hand-study --skin wpsd --out skin.mp4     # Kurihara's skin mesh, same keyframes
  workbench animate hand-study --skin psd --keyframes scans --out fig9.mp4   # through the example poses
"""

WEIGHTS_HELP = """Skinning weights for every template voxel (Kurihara Eq. 3; DESIGN step 4).

'harmonic' (default): the body is segmented from the template and filled
with tetrahedra on a lattice of its voxel centres (each cube that is mostly
body cut into 6 Kuhn tetrahedra; every voxel, or every few voxels above 150 k
vertices, or --edge-length-mm), and each bone's weight solved as the harmonic
function that is 1 on that bone and 0 on the others (P1 finite elements, one
sparse LU); voxels take the barycentric interpolation of the vertex weights,
bones are one-hot, at most 4 influences per voxel.  The mesh is written to
skinning/tetmesh.vtu, with each bone's weight as a point array for ParaView.
'distance': inverse-distance weights on each voxel's distance to the bones
(fast; a fallback and a comparison).

Writes skinning/weights.json with weights_index.mha and weights_value.mha
(4-component images on the template grid) and skinning/body_mask.nii.gz.
A template of more than 60 M voxels (a CT the size of Kurihara's, 512×512×750)
gets its weights and body mask on every 2nd (3rd, ...) voxel along each axis
instead, which keeps the stage and `workbench deform` within 8 GiB: deform
then solves its maps on that grid and pulls the full-resolution template
through them (VBD only: register after a VBD start, model and validate need --grid-factor 1).
Options left out keep the setting the stage last ran with in this study
(else the default shown); an up-to-date stage is skipped.
"""

MODEL_HELP = """Build an example-based volume deformation model (Rhee Eq. 7) from the
study's scans: for each scan, the displacement of every template voxel in
the template frame after undoing VBD with the scan's pose.

--source registration (the default): the correspondences of `workbench
register` (their inverse fields) and the poses of `workbench pose` — a
model from your own scans, no truth needed.  --source truth: a phantom's
exact correspondences and true poses (a protocol's reference model; never
taken unless asked).

Writes model/evd.json and model/evd_displacements.mha; `workbench deform`
and `workbench animate` then pose the template by EVD.  Runs the stages it
needs first when they have not run (weights; pose and register for the
registration source).
"""

SURFACE_HELP = """Kurihara's consistent skin meshes (Kurihara & Miyata 2004, §3-4).

The template's skin becomes the base mesh S0 (an isosurface between air and
tissue, cleaned of debris, decimated to --target-triangles; the paper's
hand: ~100k).  For each scan: S0 posed by SSD with the scan's estimated bone
transforms (Eq. 2-3), moved by RBF feature points (Eq. 4-5: --features
registration takes their targets from `workbench register`'s map of the
template onto the scan, --features closest from confident closest points on
the scan's skin, --landmarks FILE from points picked on the template's and
each scan's skin, as the paper did: 70-150 per pose), then fitted to the scan's
skin: --fit regularised (default) follows the skin where it is seen and keeps
the mesh's shape where it is not (fingers touching), --fit nearest is the
paper's nearest-point fit.  Every fitted mesh has S0's connectivity, so
`workbench surface-deform` interpolates them to any pose (SSD, PSD, WPSD).

Writes surface/template_skin.vtp (with the vertices' skinning weights),
surface/template_bones.vtp, and per scan <scan>_skin.ply, _ssd.ply, _rbf.ply
and _fitted.ply (world mm: they open in ParaView and 3D Slicer), and
surface/surface.json.  Runs the stages it needs first (weights, pose, and
register for --features registration).

Example:
  workbench surface hand-study
  workbench surface hand-study --fit nearest --force
  workbench surface hand-study --landmarks picked.csv
"""

SURFACE_DEFORM_HELP = """Pose Kurihara's surface model (workbench surface's meshes) and write the skin.

--method ssd: S0 skinned by the pose's bone transforms (Kurihara Eq. 2);
psd: the scans' meshes taken back to the base pose (Eq. 6), blended with one
set of RBF weights of the pose (Eq. 7, 12-14), then skinned (Eq. 8); wpsd:
the blend weighted per vertex by its bones' joints (Eq. 16), so each finger
follows its own joints.  POSE.json: joint angles or bone transforms (as for
`workbench deform`).

Example:
  workbench surface-deform hand-study --pose fist.json --method wpsd --out fist.ply
"""

REGISTER_HELP = """\
Register the template to each scan by intensity alone, starting from an
articulated start to the scan's estimated pose.

--method dense (default) moves every voxel at every iteration: local
normalised cross-correlation (3 mm window) pulls the template, each step is
smoothed and composed so that no step folds (det > 0.2 everywhere) and is
taken only when it raises the level's similarity (a trust region), the bones
stay where the pose stage put them up to a rigid refinement, coarse to fine
over 3 levels (registration.dense).  --dense NAME=VALUE sets any of its
settings (registration.dense.DenseSettings; the value is JSON), e.g.
--dense holdout=true --dense 'iterations=[200, 200, 50]'.

--method adaptive is Rhee et al. 2011's locally adaptive block registration
(§4, Algorithm 1): the worst-matching block gets 8 clamped-plate-spline
control points whose 24 displacements an NLopt simplex optimises, level by
level; --preset paper gives its published settings (levels 3-5, Nelder-Mead,
tolerance 1.5 x the base MI, no regulariser) and selects --method adaptive.
Issue I's benchmark (README, "Registration") compares both with elastix,
SimpleITK and ANTs on the same starts.

--init polyrigid (default) starts from the bones' rigid motions to the
scan's pose blended as a flow: one-to-one by construction (no fold in the
crease), bones exactly rigid.  --init vbd starts from VBD (Rhee Eq. 2), which
folds in the crease of a flexed joint (~0.2 % of the body voxels; --method
adaptive never adds a fold but keeps those; dense's final local repair cannot
remove them; --unfold-init repairs them first by local smoothing).  --init none starts from the identity (Rhee's Table 2
protocol).  The pose comes from `workbench pose` (--pose truth: a phantom's
true pose, for protocols such as Rhee's Table 4; never taken silently); the
stages a start needs run first when they have not.

Writes init/<scan>/ (the start) and registration/<scan>/ (correspondence.mha:
scan -> template field in mm on the scan grid, the convention of the truth
field; template_to_scan.mha and inverse_status.nii.gz, its inverse on the
template grid; registered.nii.gz; log.json) and records them in study.json,
scan by scan: an interrupted run resumes with the first unfinished scan, and
scans already registered with the same settings are skipped.  Open the field in
3D Slicer as a transform, the registered volume beside the scan.

Options left out keep the setting the stage last ran with in this study (else
the default shown), so a scan registered later is treated like the others.

examples:
  workbench register knee-study                       # all scans: polyrigid start, dense
  workbench register knee-study --scan pose01 --init none
  workbench register knee-study --preset paper --init vbd --seed 3   # Rhee as published
  workbench register knee-study --method adaptive --levels 3 5
  workbench register knee-study --dense window_mm=4 --dense refine_bones=false
  workbench register knee-study --dense default          # the dense settings' defaults again
"""


DEFORM_HELP = """Deform the template to a pose and write the posed volume and its label map
on the template's grid (same geometry), by EVD (Rhee Eq. 6) when the study
has a model, otherwise by VBD (Rhee Eq. 2).  The pose file is an avw-pose
(one 4x4 template-to-pose transform per bone, as truth/<id>_pose.json) or
joint angles: {"angles": {"knee": [45, 0, 0]}} (degrees; missing joints
stay at 0).  The posed volume is resampled through the backward map (Newton
on the trilinear forward map; intensities trilinear, labels nearest); the
summary counts voxels where the forward map folds.
"""

PHANTOM_HELP = """\
Write a synthetic study with exact ground truth: the template scan, its bone
label map, skeleton.json, N posed scans and, for every posed scan, its bone
transforms and joint angles (truth/<id>_pose.json), the dense scan-to-template
correspondence as an ITK displacement field (truth/<id>_correspondence.mha:
template position minus voxel position, mm; sitk.DisplacementFieldTransform
resamples the template onto the scan with it directly) and 12 skin markers
(truth/<id>_markers.json).  Open the .nii.gz/.mha files in 3D Slicer or
ITK-SNAP.
"""

POSE_HELP = """\
Recover every bone's rigid transform in every scan, then each joint's centre
of rotation and each scan's joint angles (Rhee §3.1, Kurihara §3).

Bones are registered root first, then down the skeleton: each child starts
from its parent's transform, a grid search over rotations about the joint
picks the start, and the bone is refined by intensity (Rhee Eq. 1) or by
surfaces (Kurihara's ICP).  Each joint's centre minimises Eq. 1 of Kurihara
(Σ|M c − c|², closed form, with a quasi-Newton cross-check); joints that only
flex (a hinge) get an axis, and the centre is put on it nearest the bones'
contact.  Angles are intrinsic XYZ in the skeleton's joint frame (degrees).

Writes poses/<scan>_pose.json (the same schema as the phantoms' truth),
joints.json, fits.json (per bone: status, metric, iterations) and
report.txt into the study, and records them in study.json.  Bones that leave
the field of view, do not converge or match poorly are listed, with the scan
and the metric.  The pose stage never reads a phantom's ground truth:
`workbench validate` compares the poses with it.  With --seeds the bones
stage first segments the template's bones (bones/template_labels.nii.gz,
used by every later stage).

Like every stage command it skips work that is up to date (same images,
labels and settings).  Options left out keep the setting the stage last ran
with in this study (else the default shown), so every scan of a study is
treated alike; --scan chooses this run's scans only.

Seeds file for --seeds:
  {"format": "avw-seeds", "version": 1, "units": "mm",
   "seeds": {"femur": [[x, y, z]], "tibia": [[x, y, z]], ...}}
"""

POSES_FILE_HELP = """\
JSON file of explicit joint angles (degrees; 6-DOF joints add mm):
{"poses": [{"id": "bend10", "angles": {"knee": [10, 0, 0]}}]}.
Joints left out stay at 0; on the knee the fibula and patella follow the
knee's angles automatically. Overrides --poses.
"""


RUN_HELP = """\
Run the whole pipeline on a study, stage by stage, each through one mechanism:

  bones     the template's bone labels (given, or segmented from --seeds)
  pose      every bone's transform in every scan, joint centres and angles
  weights   harmonic skinning weights of every template voxel
  init      the articulated start to each scan's estimated pose  (per scan)
  register  dense registration (or Rhee Algorithm 1, --method)  (per scan)
  model     EVD (Rhee Eq. 7) from the registrations and the estimated poses
  surface   Kurihara's consistent skin meshes (S0, and each scan's fitted mesh)
  validate  each scan against its ground truth, when it has one  (per scan)
  report    one self-contained HTML validation report (report/report.html)

The ground truth of a phantom is read by `validate` alone.  Each stage
records in study.json a digest of its inputs and settings; a stage whose
digest is unchanged is skipped (and says so), so a second `run` does nothing
and a changed setting reruns only the stages that depend on it.  Per-scan
stages commit each scan as it finishes: after Ctrl-C (or SIGTERM) no partial
file is left and the next `run` resumes with the first unfinished scan.

Settings: each stage keeps the settings it last ran with (e.g. those given to
`workbench register`); --set STAGE.SETTING=VALUE changes one for this run and
after (JSON values: --set register.method=adaptive,
--set register.levels=[3,4], --set weights.method=distance).  Each value is
checked against the setting's type before anything runs or is recorded.

Before any work the study folder and study.json must be writable; a scan
whose field of view holds none of the template's bones, or of which no bone
could be placed, stops the pose stage with one line naming it.  A write that
does not complete (a full disk) is an error naming the file; nothing is left
half-written, and the previous outputs stay.

examples:
  workbench run knee-study                        # everything; truth only in validate
  workbench run knee-study                        # again: every stage skipped
  workbench run knee-study --until register       # stop after the registrations
  workbench run knee-study --force register       # rerun register, then model, surface, validate, report
  workbench run my-ct-study --seeds seeds.json    # no label map: segment the bones first
  workbench run knee-study --scan pose01 --until register
"""


def _common(p) -> None:
    """--quiet / -v on every subcommand."""
    p.add_argument("--quiet", action="store_true", help="no progress lines (warnings still show)")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log lines (-vv: debug)")


def _scale_options(p) -> None:
    """--workers / --scheduler on the commands with per-scan work (workbench.scale)."""
    g = p.add_argument_group("many scans (Dask)")
    g.add_argument(
        "--workers",
        type=_positive_int,
        default=None,
        metavar="N",
        help="run the per-scan work (pose, init, register, surface, validate) as Dask tasks on a local "
        "cluster of N processes; the results are the same bits as with one. Default: 1 (no Dask)",
    )
    g.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        default=None,
        help="run the per-scan work on an existing Dask cluster (e.g. tcp://head-node:8786, started with "
        "`dask scheduler` and `dask worker ADDRESS`, or by dask-jobqueue on Slurm/PBS); every "
        "worker must see the study folder at the same path",
    )


def _positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {v}")
    return v


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="workbench", description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")

    ph = sub.add_parser(
        "phantom",
        help="write a synthetic knee or hand study with exact ground truth",
        description=PHANTOM_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ph.add_argument("region", choices=["knee", "hand"], help="body region")
    ph.add_argument("--out", required=True, type=Path, metavar="DIR", help="study folder to create")
    ph.add_argument(
        "--size",
        choices=["test", "paper"],
        default="test",
        help="'test': ≤64 voxels a side, seconds; 'paper': the papers' grids (knee "
        "255×255×123 at 1.25×1.25×1.2 mm, hand 255×255×90 at 0.78×0.78×1.0 mm; "
        "minutes). Default: test",
    )
    ph.add_argument(
        "--spacing",
        metavar="MM|X,Y,Z",
        help="voxel spacing in mm (one value, or x,y,z) instead of the size's; the field of view is "
        "kept, so e.g. --size test --spacing 2.5 gives a knee of 128x128x59 voxels, between the "
        "test and paper grids",
    )
    ph.add_argument(
        "--modality",
        choices=["mri", "ct"],
        default="mri",
        help="MRI-like (dark cortex, overlapping soft tissues, Rician noise, bias field) "
        "or CT-like (bright cortex, Gaussian noise, HU). Default: mri",
    )
    ph.add_argument(
        "--poses",
        type=_positive_int,
        metavar="N",
        help="number of posed scans (default: knee 4, straight to 70° flexion; hand 10, spread to fist)",
    )
    ph.add_argument("--poses-file", type=Path, metavar="FILE", help=POSES_FILE_HELP)
    ph.add_argument(
        "--posing",
        choices=["soft", "vbd"],
        default="soft",
        help="'soft': rigid bones, soft tissue blended by dual quaternions with flexor-side "
        "bulge and skin sliding (not linear blending, so a VBD initialisation leaves a "
        "residual); 'vbd': plain volume blend deformation (Rhee Eq. 2), as in Rhee's "
        "Table 2 protocol. Default: soft",
    )
    ph.add_argument("--seed", type=int, default=0, help="random seed (texture, noise, jitter, markers). Default: 0")
    ph.add_argument(
        "--noise-free", action="store_true", help="no noise and no bias field (for exact-resampling checks)"
    )
    ph.add_argument(
        "--acquisition",
        choices=["fixed", "random"],
        default="fixed",
        help="'fixed': every image gets the modality's tissue intensities, noise and bias; 'random': "
        "drawn from the seed: per study a tissue-intensity table between the MRI (T1-like, bright "
        "fat) and CT (dark fat, bright cortex) ones and, without --spacing, anisotropic voxels "
        "(one axis up to 3x coarser relative to the others, same field of view); per image Rician or Gaussian "
        "noise at an SNR of 8-40 (muscle signal above air over sigma), a 0-20%% bias field, a "
        "gain of 0.9-1.1 (and a small offset with Gaussian noise). Recorded in study.json "
        "(phantom.acquisition_drawn). Default: fixed",
    )
    ph.add_argument("--force", action="store_true", help="replace DIR if it exists")
    _common(ph)
    ph.set_defaults(func=cmd_phantom)

    info = sub.add_parser(
        "info",
        help="summarise a study folder",
        description="Print what a study folder holds: grids, skeleton, scans and ground truth.",
    )
    info.add_argument("study", type=Path, help="study folder (holding study.json)")
    info.add_argument(
        "--check",
        action="store_true",
        help="also read every image of the study (template, labels, scans, ground truth) and list "
        "each that cannot be used (unreadable, NaN voxels, another grid's labels); exit 1 if any",
    )
    info.set_defaults(func=cmd_info)

    ci = sub.add_parser(
        "clean-image",
        help="replace an image's NaN and infinite voxels (a copy; the input is kept)",
        description="Write a copy of an image whose NaN and infinite voxels are replaced by a value "
        "(default: the lowest finite value of the image, i.e. background), with the "
        "same geometry. The workbench refuses images with such voxels.",
    )
    ci.add_argument("image", type=Path, help="the image (.nii.gz, .mha, .nrrd, a DICOM folder)")
    ci.add_argument("--out", required=True, type=Path, help="the cleaned copy")
    ci.add_argument(
        "--value", type=float, default=None, help="the value for the bad voxels (default: the lowest finite value)"
    )
    ci.add_argument("--force", action="store_true", help="replace an existing --out")
    ci.set_defaults(func=cmd_clean_image)

    po = sub.add_parser(
        "pose",
        help="recover bone poses, joint centres and joint angles of a study's scans",
        description=POSE_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    po.add_argument("study", type=Path, help="study folder (holding study.json)")
    po.add_argument(
        "--method",
        choices=["intensity", "surface"],
        default=argparse.SUPPRESS,
        help="'intensity': Rhee Eq. 1, the bone region's intensities (SimpleITK, then a least-squares "
        "polish); 'surface': Kurihara §3, ICP of bone isosurfaces (VTK flying edges + Open3D). "
        "Default: intensity",
    )
    _bones_options(po)
    po.add_argument(
        "--init",
        default=argparse.SUPPRESS,
        metavar="identity|moments|FILE",
        help="root bone's starting pose: 'identity' (scans share the template's scanner frame), "
        "'moments' (align the images' centres of mass), or a JSON file (an avw-pose file, or "
        "{'format': 'avw-initial-poses', 'version': 1, 'scans': {id: 4x4}}). Default: identity",
    )
    po.add_argument(
        "--scan",
        action="append",
        metavar="ID",
        help="only this scan (repeatable; default: all — Kurihara Eq. 1 pools the scans estimated)",
    )
    po.add_argument(
        "--metric",
        choices=["ncc", "ssd"],
        default=argparse.SUPPRESS,
        help="cost of the coarse search and the polish: 'ssd' is Eq. 1 as printed; 'ncc' is Eq. 1 "
        "after the best linear intensity map per bone (insensitive to an MRI bias field). "
        "Default: ncc",
    )
    po.add_argument(
        "--interpolation",
        choices=["linear", "bspline"],
        default=argparse.SUPPRESS,
        help="'linear' is the papers' trilinear; 'bspline' (cubic) leaves a residual about 4x smaller "
        "for a rotated bone on coarse grids. Default: bspline",
    )
    po.add_argument(
        "--prior-deg",
        type=float,
        default=argparse.SUPPRESS,
        metavar="DEG",
        help="width (degrees) of the weak prior tying each bone's rotation to its hierarchical "
        "initialisation (the translation prior is 2 mm; with --method surface, combined with "
        "the ICP fit); 0 turns it off (plain Eq. 1 through SimpleITK, plain ICP). Default: 2",
    )
    po.add_argument(
        "--margin-mm",
        default=argparse.SUPPRESS,
        type=float,
        metavar="MM",
        help="dilation of each bone's region for the intensity cost (Rhee: 'slightly dilated'); "
        "default one voxel, at least 2 mm.  Smaller keeps non-rigid soft tissue out on fine grids",
    )
    po.add_argument(
        "--bias-correction",
        choices=["auto", "on", "off"],
        default=argparse.SUPPRESS,
        help="N4 bias-field correction of template and scans before registration; 'auto' does it "
        "for MRI-like images. Default: auto",
    )
    po.add_argument(
        "--min-ncc",
        type=float,
        default=argparse.SUPPRESS,
        help="a bone whose final correlation with the template is lower is reported as a poor match. Default: 0.5",
    )
    po.add_argument(
        "--max-joint-gap-mm",
        type=float,
        default=argparse.SUPPRESS,
        metavar="MM",
        help="a bone whose joint centre (from skeleton.json) lands farther than this from where its "
        "parent puts it has left its joint and is reported as 'joint_detached'; raise it for a "
        "rough skeleton, 0 switches the check off. Default: 10",
    )
    po.add_argument(
        "--outlier-factor",
        type=float,
        default=argparse.SUPPRESS,
        metavar="K",
        help="Eq. 1 consistency check: with 4 or more scans, a bone whose motion misses its joint's "
        "centre (estimated from all scans) by more than K times the joint's median miss, and by "
        "more than half a voxel, is reported as 'joint_outlier'; 0 switches the check off. "
        "Default: 4",
    )
    po.add_argument(
        "--grid-factor",
        type=_positive_int,
        default=argparse.SUPPRESS,
        metavar="F",
        help="register the bones on every F-th voxel along each axis of the template and scans "
        "(smoothed first; F³ fewer voxels and bytes, about F times coarser). Default: 1, or the "
        "smallest F that leaves at most 60 M voxels (2 for a 512×512×750 CT)",
    )
    po.add_argument("--force", action="store_true", help="rerun even when up to date")
    _scale_options(po)
    _common(po)
    po.set_defaults(func=cmd_pose)

    we = sub.add_parser(
        "weights",
        help="skinning weights of every template voxel (harmonic on a tet mesh)",
        description=WEIGHTS_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    we.add_argument("study", type=Path, help="study folder (holding study.json)")
    we.add_argument(
        "--method",
        choices=["harmonic", "distance"],
        default=argparse.SUPPRESS,
        help="'harmonic' (tet mesh + Laplace solve) or 'distance' (inverse distance). Default: harmonic",
    )
    we.add_argument(
        "--edge-length-mm",
        default=argparse.SUPPRESS,
        type=float,
        metavar="MM",
        help="spacing of the tet lattice in mm, rounded to whole voxels along each axis (default: every "
        "voxel, or every 2nd, 3rd, ... when that would make more than 150 k vertices)",
    )
    we.add_argument(
        "--grid-factor",
        type=_positive_int,
        default=argparse.SUPPRESS,
        metavar="F",
        help="weights on every F-th template voxel along each axis (F³ fewer voxels and bytes). "
        "Default: 1, or the smallest F that leaves at most 60 M voxels",
    )
    we.add_argument("--force", action="store_true", help="rerun even when up to date")
    _common(we)
    we.set_defaults(func=cmd_weights)

    mo = sub.add_parser(
        "model",
        help="build an EVD model (Rhee Eq. 7) from the study's correspondences",
        description=MODEL_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    mo.add_argument("study", type=Path, help="study folder (holding study.json)")
    mo.add_argument(
        "--source",
        choices=["registration", "truth"],
        default="registration",
        help="correspondences: 'registration' (`workbench register` + estimated poses) or 'truth' (a "
        "phantom's exact ones and true poses; never taken unless asked). Default: registration",
    )
    mo.add_argument("--scan", action="append", metavar="ID", help="only this scan (repeatable; default: all)")
    mo.add_argument("--force", action="store_true", help="rebuild even when up to date")
    _common(mo)
    mo.set_defaults(func=cmd_model)

    su = sub.add_parser(
        "surface",
        help="Kurihara's consistent skin meshes of the template and every scan",
        description=SURFACE_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    su.add_argument("study", type=Path, help="study folder (holding study.json)")
    su.add_argument(
        "--target-triangles",
        type=int,
        default=argparse.SUPPRESS,
        metavar="N",
        help="decimate S0 and the scans' skins to about N triangles. Default: 100000",
    )
    su.add_argument(
        "--features",
        choices=["registration", "closest", "landmarks"],
        default=argparse.SUPPRESS,
        help="targets of the RBF feature points. Default: registration (landmarks with --landmarks)",
    )
    su.add_argument(
        "--landmarks",
        type=Path,
        default=argparse.SUPPRESS,
        metavar="FILE",
        help="landmark pairs picked on the template's skin and each scan's (JSON "
        '{"format": "avw-landmarks", "scans": {id: [{"template": [x,y,z], "scan": [x,y,z]}]}} or '
        "CSV scan,template_x,template_y,template_z,scan_x,scan_y,scan_z; mm): every one is a "
        "feature point",
    )
    su.add_argument(
        "--features-count",
        dest="n_features",
        type=int,
        default=argparse.SUPPRESS,
        metavar="N",
        help="feature points per scan, spread over S0. Default: 150",
    )
    su.add_argument(
        "--fit",
        choices=["regularised", "nearest"],
        default=argparse.SUPPRESS,
        help="the fit to the scan's skin. Default: regularised",
    )
    su.add_argument(
        "--stiffness",
        type=float,
        default=argparse.SUPPRESS,
        help="the regularised fit's weight on keeping the mesh's shape. Default: 1",
    )
    su.add_argument("--scan", action="append", metavar="ID", help="only this scan (repeatable; default: all)")
    su.add_argument("--force", action="store_true", help="rerun even when up to date")
    _scale_options(su)
    _common(su)
    su.set_defaults(func=cmd_surface)

    sd = sub.add_parser(
        "surface-deform",
        help="pose the surface model (SSD, PSD or WPSD) and write the skin mesh",
        description=SURFACE_DEFORM_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sd.add_argument("study", type=Path, help="study folder (holding study.json, after `workbench surface`)")
    sd.add_argument("--pose", required=True, type=Path, metavar="POSE.json", help="target pose")
    sd.add_argument(
        "--method",
        choices=["ssd", "psd", "wpsd"],
        default="wpsd",
        help="SSD (Eq. 2), PSD (Eq. 6-8) or WPSD (Eq. 16). Default: wpsd",
    )
    sd.add_argument("--out", required=True, type=Path, metavar="MESH", help="output mesh (.ply, .vtp, .obj, .stl)")
    sd.add_argument("--force", action="store_true", help="overwrite --out")
    _common(sd)
    sd.set_defaults(func=cmd_surface_deform)

    de = sub.add_parser(
        "deform",
        help="deform the template to a pose (EVD or VBD) and write the posed volume",
        description=DEFORM_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    de.add_argument("study", type=Path, help="study folder (holding study.json)")
    de.add_argument("--pose", required=True, type=Path, metavar="POSE.json", help="target pose (see above)")
    de.add_argument(
        "--out",
        required=True,
        type=Path,
        metavar="VOLUME",
        help="posed volume (.nii.gz, .mha, .nrrd); the labels go to VOLUME's name + _labels",
    )
    de.add_argument("--labels-out", type=Path, metavar="LABELS", help="posed label map (default: beside --out)")
    de.add_argument(
        "--field-out",
        type=Path,
        metavar="FIELD",
        help="also write the posed-to-template displacement field (ITK vector image, mm)",
    )
    de.add_argument(
        "--grow",
        action="store_true",
        help="write the posed volume on the template's grid extended (same spacing and direction) to "
        "hold the whole posed body, instead of the template's grid itself",
    )
    de.add_argument(
        "--method",
        choices=["auto", "vbd", "evd"],
        default="auto",
        help="'auto': EVD when the study has a model, else VBD. Default: auto",
    )
    de.add_argument(
        "--map-factor",
        type=_positive_int,
        default=1,
        metavar="F",
        help="solve the forward and backward maps on every F-th voxel along each axis (F³ fewer "
        "voxels) and blend the map up; the template is still resampled at full resolution. On "
        "the paper-size hand, F=2 is about 3x faster, with a mean residual |F(x)-y| of 0.07 mm "
        "(up to a few mm where the map jumps between touching fingers). Default: 1 (exact), or the "
        "weights' --grid-factor when they lie on a coarse grid (a big template)",
    )
    de.add_argument(
        "--weighting",
        choices=["psd", "wpsd"],
        default="psd",
        help="EVD pose weights: 'psd' one set for all voxels (Rhee); 'wpsd' per voxel from the "
        "skinning weights (Kurihara Eq. 16). Default: psd",
    )
    de.add_argument("--force", action="store_true", help="replace existing output files")
    _common(de)
    de.set_defaults(func=cmd_deform)

    re_ = sub.add_parser(
        "render",
        help="volume-render a volume or a study off-screen to a PNG (presets, clipping, overlays)",
        description=RENDER_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    re_.add_argument(
        "source",
        type=Path,
        metavar="VOLUME_OR_STUDY",
        help="an image file (.nii.gz, .mha, .nrrd, a DICOM folder), a study folder (its template), or "
        "a mesh (.ply, .vtp, .stl, .obj: the mesh alone)",
    )
    re_.add_argument(
        "--mesh",
        action="append",
        type=Path,
        metavar="MESH",
        help="a mesh in world mm (.ply, .vtp, .stl, .obj; e.g. `workbench surface` or "
        "`surface-deform` output) drawn over the volume; repeatable",
    )
    re_.add_argument(
        "--mesh-opacity",
        type=float,
        default=1.0,
        metavar="A",
        help="the meshes' opacity, 0..1. VTK's CPU ray caster (software OpenGL) draws a translucent "
        "mesh behind the volume's tissue: clip the volume (--clip) to see a mesh inside it. "
        "Default: 1",
    )
    re_.add_argument("--out", required=True, type=Path, metavar="IMAGE.png", help="the PNG to write")
    re_.add_argument("--scan", metavar="ID", help="with a study: render this scan instead of the template")
    re_.add_argument(
        "--registered",
        metavar="ID",
        help="with a study: render the template registered to scan ID (`workbench register`)",
    )
    re_.add_argument(
        "--overlay",
        metavar="OTHER",
        help="a second volume (file, or a scan ID of the study) in magenta over the first in cyan",
    )
    re_.add_argument(
        "--difference", metavar="OTHER", help="render the signed difference first − OTHER (file or scan ID) instead"
    )
    re_.add_argument(
        "--labels", type=Path, metavar="LABELS", help="a label map on the volume's grid, drawn as surfaces"
    )
    re_.add_argument("--bones", action="store_true", help="with a study's template: draw its bone labels")
    re_.add_argument(
        "--markers",
        action="store_true",
        help="with a study: draw the skin markers of the ground truth (white; the scan's positions "
        "with --scan/--registered, the template's otherwise)",
    )
    re_.add_argument(
        "--control-points",
        action="store_true",
        help="with --registered ID: draw the control points the registration allocated, coloured by "
        "block level (green 3, yellow 4, orange 5, ...; Rhee Fig. 9)",
    )
    _render_options(re_)
    re_.add_argument("--force", action="store_true", help="replace an existing PNG")
    _common(re_)
    re_.set_defaults(func=cmd_render)

    an = sub.add_parser(
        "animate",
        help="animate the template through keyframe poses to MP4, GIF or PNG frames",
        description=ANIMATE_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    an.add_argument("study", type=Path, help="study folder (with skinning weights: `workbench weights`)")
    an.add_argument(
        "--out",
        required=True,
        type=Path,
        metavar="ANIM",
        help="anim.mp4, anim.gif, or frames/anim.png (numbered frames)",
    )
    an.add_argument(
        "--keyframes",
        type=Path,
        metavar="KEYS.json",
        help="keyframe poses (default: the ready ones); 'scans': rest, each scan's estimated pose, "
        "rest (Kurihara Fig. 9's interpolation between the example poses)",
    )
    an.add_argument(
        "--method",
        choices=["auto", "vbd", "evd"],
        default="auto",
        help="'auto': EVD when the study has a model, else VBD. Default: auto",
    )
    an.add_argument("--weighting", choices=["psd", "wpsd"], default="psd", help="EVD pose weights. Default: psd")
    an.add_argument(
        "--map-factor",
        type=_positive_int,
        default=1,
        metavar="F",
        help="each frame's maps solved on every F-th voxel and blended up (as `workbench deform "
        "--map-factor`): F=2 is about 3x faster per frame. Default: 1 (exact), or the weights' "
        "--grid-factor when they lie on a coarse grid",
    )
    an.add_argument("--fps", type=float, metavar="FPS", help="frames per second (default: the file's, else 24)")
    an.add_argument("--frames", type=_positive_int, metavar="N", help="number of frames (default: duration × fps + 1)")
    an.add_argument("--orbit", type=float, metavar="DEG", help="turn the camera by DEG of azimuth over the animation")
    an.add_argument("--bones", action="store_true", help="draw the posed bone labels as surfaces")
    an.add_argument(
        "--skin",
        choices=["ssd", "psd", "wpsd"],
        metavar="ssd|psd|wpsd",
        help="animate Kurihara's skin mesh (`workbench surface`) posed by this method instead of the "
        "volume, through the same keyframes (--method, --weighting and --preset are the "
        "volume's and do not apply)",
    )
    _render_options(an, camera_default=None)
    an.add_argument("--force", action="store_true", help="replace existing output")
    _common(an)
    an.set_defaults(func=cmd_animate)

    rg = sub.add_parser(
        "register",
        help="non-rigid registration of the template to the scans (dense, or Rhee §4's locally adaptive one)",
        description=REGISTER_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    rg.add_argument("study", type=Path, help="study folder (holding study.json)")
    rg.add_argument("--scan", action="append", metavar="ID", help="only this scan (repeatable; default: all)")
    rg.add_argument(
        "--method",
        choices=["dense", "adaptive"],
        default=argparse.SUPPRESS,
        help="dense LNCC steps over the whole scan, or Rhee's Algorithm 1. Default: dense (adaptive "
        "with --preset paper)",
    )
    rg.add_argument(
        "--init",
        choices=["polyrigid", "vbd", "none"],
        default=argparse.SUPPRESS,
        help="start from the bones' motions blended as a one-to-one flow, from VBD (Rhee Eq. 2), or "
        "from the identity. Default: polyrigid",
    )
    rg.add_argument(
        "--unfold-init",
        default=argparse.SUPPRESS,
        action="store_true",
        help="repair the folds of the VBD initialisation in the crease of a flexed joint before "
        "registering (one-to-one wherever the map reaches into the template; ~0.1-1 mm less "
        "accurate on the knee phantom, more on the hand)",
    )
    rg.add_argument(
        "--map-factor",
        type=int,
        default=argparse.SUPPRESS,
        metavar="F",
        help="integrate the polyrigid start on every F-th voxel and blend it up (exactly where the map "
        "jumps, where fingers touch): ~4x less work at F=2, 0.07 mm off on average on the test "
        "hand at 1.6 mm, 0.02 mm at 0.8 mm. Default: 1 up to 16 M voxels a grid, else the smallest F within",
    )
    rg.add_argument(
        "--pose",
        choices=["estimated", "truth"],
        default=argparse.SUPPRESS,
        dest="pose_source",
        help="pose of the start: the pose stage's estimate, or a phantom's true pose (protocols). Default: estimated",
    )
    rg.add_argument(
        "--preset",
        choices=["default", "paper"],
        default=argparse.SUPPRESS,
        help="--method adaptive's settings: ours (after an articulated start its 'initialised' "
        "variant), or Rhee's as published (selects --method adaptive). Default: default",
    )
    rg.add_argument(
        "--levels",
        default=argparse.SUPPRESS,
        nargs=2,
        type=int,
        metavar=("FIRST", "LAST"),
        help="block levels (2**level blocks a side; level 3 = 32^3-voxel blocks on a 256^3 grid). "
        "--method adaptive only. Default: 3 4 after an articulated start, 1 4 after --init none "
        "(paper preset: 3 5)",
    )
    rg.add_argument(
        "--optimizer",
        default=argparse.SUPPRESS,
        choices=["neldermead", "sbplx", "bobyqa", "cobyla"],
        help="NLopt algorithm of each local step (--method adaptive). Default: bobyqa (paper preset: neldermead)",
    )
    rg.add_argument(
        "--metric",
        default=argparse.SUPPRESS,
        choices=["auto", "ssd", "mi"],
        help="--method adaptive: 'auto' is normalised MI at coarse levels, SSD from level 4 (Rhee §4.1). Default: auto",
    )
    rg.add_argument(
        "--max-steps",
        default=argparse.SUPPRESS,
        type=int,
        metavar="N",
        help="local steps per level at most (--method adaptive). Default: 200",
    )
    rg.add_argument(
        "--seed",
        type=int,
        default=argparse.SUPPRESS,
        help="seed of the simplex restarts (--method adaptive; after an articulated start the default "
        "preset makes none, so the seed has no effect there; the dense method's one random choice, "
        "--dense holdout=true's noise, has its own seed: --dense holdout_seed=N). "
        "Default: 0",
    )
    rg.add_argument(
        "--no-unfold-init",
        action="store_false",
        dest="unfold_init",
        default=argparse.SUPPRESS,
        help="start from the plain VBD field again after an earlier --unfold-init",
    )
    rg.add_argument(
        "--dense",
        action="append",
        default=argparse.SUPPRESS,
        metavar="NAME=VALUE",
        help="a setting of the dense registration (registration.dense.DenseSettings), the value as JSON "
        "(true, 4, [200, 200, 50], null); repeatable; given, the list replaces the one the study "
        "last ran with; 'default' alone clears it",
    )
    rg.add_argument(
        "--no-fix-bones",
        default=argparse.SUPPRESS,
        action="store_true",
        help="let the bones move with the soft tissue (dense: no force is zeroed on them; adaptive: no "
        "zero-displacement control points on bone voxels)",
    )
    rg.add_argument("--force", action="store_true", help="register these scans again even when up to date")
    _scale_options(rg)
    _common(rg)
    rg.set_defaults(func=cmd_register)

    bo = sub.add_parser(
        "bones",
        help="the template's bone label map: given, or segmented from seeds",
        description="The bones stage (Rhee §3.1): the study's own label map, or one segmented "
        "from a seeds file (CT: threshold and connected components; MRI: each "
        "bone's marrow flooded from its seeds inside the dark cortex), and each bone's oriented box.  Writes "
        "bones/; every later "
        "stage uses these labels.  The seeds schema is in `workbench pose --help`.",
    )
    bo.add_argument("study", type=Path, help="study folder (holding study.json)")
    _bones_options(bo)
    bo.add_argument("--force", action="store_true", help="rerun even when up to date")
    _common(bo)
    bo.set_defaults(func=cmd_bones)

    va = sub.add_parser(
        "validate",
        help="each scan's registration and pose against its ground truth",
        description="The validate stage (Rhee §6.1, Tables 2-4): for each scan with ground truth, "
        "MED over body voxels and at the markers (mm), SSD, CC, MI (nats, 32 bins) and "
        "the folded fraction of body voxels for the source, the initialised and the "
        "registered template, and the estimated pose's errors.  Writes "
        "validation/<scan>/measures.json.  The only stage that reads the truth.",
    )
    va.add_argument("study", type=Path, help="study folder (holding study.json)")
    va.add_argument("--scan", action="append", metavar="ID", help="only this scan (repeatable; default: all)")
    va.add_argument("--force", action="store_true", help="rerun even when up to date")
    _scale_options(va)
    _common(va)
    va.set_defaults(func=cmd_validate)

    ru = sub.add_parser(
        "run",
        help="run every stage in order: bones, pose, weights, init, register, model, validate, report",
        description=RUN_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ru.add_argument("study", type=Path, help="study folder (holding study.json)")
    ru.add_argument("--until", metavar="STAGE", choices=_stage_names(), help="stop after this stage")
    ru.add_argument(
        "--force",
        action="append",
        default=[],
        metavar="STAGE",
        choices=_stage_names(),
        help="rerun this stage even when up to date, and what depends on it (repeatable)",
    )
    ru.add_argument("--scan", action="append", metavar="ID", help="per-scan stages only for this scan (repeatable)")
    ru.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="STAGE.SETTING=VALUE",
        dest="set_",
        help="change one stage setting (repeatable; see above)",
    )
    ru.add_argument(
        "--seeds",
        type=Path,
        metavar="FILE",
        help="segment the template's bones from this seeds file (a study without a label map)",
    )
    _scale_options(ru)
    _common(ru)
    ru.set_defaults(func=cmd_run)

    rr = sub.add_parser(
        "report",
        help="one self-contained HTML validation report of a study or a reproduce folder",
        description=REPORT_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    rr.add_argument(
        "source",
        type=Path,
        metavar="STUDY_OR_DIR",
        help="a study folder (holding study.json) or a `workbench reproduce` output folder",
    )
    rr.add_argument("--out", type=Path, required=True, metavar="FILE.html", help="the report to write")
    rr.add_argument(
        "--force",
        action="store_true",
        help="replace an existing --out file; for a study, also rebuild the report stage's report",
    )
    rr.add_argument(
        "--no-pictures", action="store_true", help="tables and plots only, no slice pictures (a smaller file)"
    )
    _common(rr)
    rr.set_defaults(func=cmd_report)

    rp = sub.add_parser(
        "reproduce",
        help="reproduce the papers' tables on phantoms (CSV, Markdown, JSON per table)",
        description=REPRODUCE_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    rp.add_argument(
        "tables",
        nargs="+",
        metavar="TABLE",
        choices=["table2", "table3", "table4", "loo", "eigenposes", "kurihara", "kurihara_skin", "all"],
        help="table2, table3, table4, loo, eigenposes, kurihara, kurihara_skin, or all",
    )
    rp.add_argument(
        "--out",
        type=Path,
        required=True,
        metavar="DIR",
        help="folder for the tables (<table>.csv/.md/.json) and the phantom studies they run on "
        "(DIR/studies/); an existing folder's finished stages are reused",
    )
    rp.add_argument(
        "--size",
        choices=["test", "paper"],
        default="test",
        help="phantom grid: test (minutes for all) or paper (Rhee's grids; hours). Default: test",
    )
    rp.add_argument("--seed", type=int, default=0, help="phantom seed (noise, texture, pose jitter). Default: 0")
    rp.add_argument(
        "--with-peers",
        action="store_true",
        help="add elastix's and SimpleITK's B-spline registrations from the same start (tables 2-4)",
    )
    rp.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help="run the protocols' phantom studies side by side in N processes (Dask); the tables are "
        "the same. Default: 2 at --size test on a machine with 2 or more cores (all tables: "
        "11 min against 15.5 in one process here), 1 at --size paper (memory)",
    )
    rp.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        default=None,
        help="run the protocols' studies as tasks on an existing Dask cluster instead (e.g. "
        "tcp://head-node:8786; README, 'Many scans, big machines'); workers must see --out at the "
        "same path",
    )
    _common(rp)
    rp.set_defaults(func=cmd_reproduce)
    return p


def _stage_names():
    """workbench.stages.ORDER, written out so that --help does not import every stage (a test keeps them equal)."""
    return ["bones", "pose", "weights", "init", "register", "model", "surface", "validate", "report"]


def _bones_options(p) -> None:
    p.add_argument(
        "--seeds",
        type=Path,
        metavar="FILE",
        help="seeds file (one or more world points in mm inside each bone): segment the template's "
        "bones from it instead of using the study's label map",
    )
    p.add_argument(
        "--modality",
        choices=["ct", "mri"],
        help="segmentation method for --seeds (default: guessed from the intensities: CT if air is "
        "below -500 HU; a CT cropped to the limb, with no air, needs --modality ct and "
        "--bias-correction off)",
    )
    p.add_argument("--threshold", type=float, metavar="HU", help="bone threshold for CT segmentation (default 400)")


def _render_options(p, camera_default="auto") -> None:
    p.add_argument(
        "--preset", default="mri", metavar="mri|ct|FILE.json", help="transfer function (see above). Default: mri"
    )
    p.add_argument("--clip", metavar="[+|-]AXIS:FRACTION", help="clipping plane, e.g. z:0.5 (see above)")
    p.add_argument(
        "--camera",
        default=camera_default,
        metavar="VIEW",
        help="auto, iso, +x, -x, +y, -y, +z, -z"
        + (" (default: the keyframe file's, else auto)" if camera_default is None else ". Default: auto"),
    )
    p.add_argument("--azimuth", type=float, default=None, metavar="DEG", help="turn the camera about the view-up axis")
    p.add_argument("--elevation", type=float, default=None, metavar="DEG", help="turn the camera up or down")
    p.add_argument("--zoom", type=float, default=None, metavar="Z", help="> 1 enlarges. Default: 1")
    p.add_argument(
        "--size",
        default="640x480",
        metavar="WxH",
        help="image size in pixels, both even (video encoders need it). Default: 640x480",
    )
    p.add_argument("--background", default="black", metavar="COLOUR", help="black, white, or R,G,B in 0..1")
    p.add_argument(
        "--mapper",
        choices=["auto", "fixed", "gpu"],
        default="auto",
        help="'auto': the CPU ray caster on software OpenGL, the GPU one otherwise",
    )


def _spacing(text):
    if text is None:
        return None
    try:
        v = tuple(float(t) for t in text.split(","))
    except ValueError:
        v = ()
    if len(v) == 1:
        v = v * 3
    if len(v) != 3 or not all(x > 0 for x in v):
        raise ValueError(f"--spacing {text!r}: expected one positive number (mm) or three, x,y,z")
    return v


def _background(text: str) -> tuple:
    named = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0), "grey": (0.5, 0.5, 0.5), "gray": (0.5, 0.5, 0.5)}
    if text.lower() in named:
        return named[text.lower()]
    try:
        rgb = tuple(float(v) for v in text.split(","))
    except ValueError:
        rgb = ()
    if len(rgb) != 3 or not all(0.0 <= v <= 1.0 for v in rgb):
        raise ValueError(f"--background {text!r}: expected black, white, grey or R,G,B with each in 0..1")
    return rgb


def _camera(args):
    from workbench.viz.animate import camera_from

    return camera_from({}, view=args.camera, azimuth=args.azimuth, elevation=args.elevation, zoom=args.zoom)


def _say(args):
    """A line printer for the commands that are not stages (deform, render, animate), through the same
    progress printer as the stages' events (``None`` with --quiet)."""
    if args.quiet:
        return None
    from workbench.stages.mechanism import Event

    printer = _progress(args)
    return lambda line: printer(Event(args.command, None, 0, 0, line, "message"))


def cmd_deform(args) -> int:
    from deformation.geometry import every_nth
    from workbench.deform import deform_study

    s = deform_study(
        args.study,
        args.pose,
        args.out,
        method=args.method,
        weighting=args.weighting,
        labels_out=args.labels_out,
        field_out=args.field_out,
        grow=args.grow,
        overwrite=args.force,
        map_factor=args.map_factor,
        progress=_say(args),
    )
    n, f = s["n_voxels"], s.get("map_factor", 1)
    print(
        f"{s['method'].upper()}: forward {s['forward_seconds']:.2f} s, backward map + resampling "
        f"{s['backward_seconds']:.2f} s for {n:,} voxels"
        + (f" (the maps on {every_nth(f)} voxel along each axis, blended up to the volume's grid)" if f > 1 else "")
    )
    print(
        f"backward map{' (coarse voxels)' if f > 1 else ''}: {s['n_ok']:,} ok, {s['n_folded']:,} where the "
        f"forward map folds "
        f"({100 * s['fraction_folded']:.3f} %), {s['n_not_converged']:,} not converged, {s['n_outside']:,} "
        f"outside the template (fill value)"
    )
    print(f"wrote {s['out']} and {s['labels']}" + (f" and {s['field']}" if s["field"] else ""))
    return 0


def _progress(args):
    from workbench.progress import ProgressPrinter, setup_logging

    setup_logging(-1 if args.quiet else args.verbose)
    return ProgressPrinter(quiet=args.quiet)


def _stages(args, targets, settings=None, *, force=(), scans=None, options=None):
    """Run ``targets`` (and the stages they need) on the study of ``args``; returns (study, outcomes)."""
    from workbench.scale import open_runner
    from workbench.stages.run import run_stages
    from workbench.study import read_study

    study = read_study(args.study)
    printer = _progress(args)
    try:
        with open_runner(getattr(args, "workers", None), getattr(args, "scheduler", None)) as runner:
            outcomes = run_stages(
                study,
                targets,
                settings=settings or {},
                force=force,
                scans=scans,
                progress=printer,
                options=options,
                runner=runner,
            )
    finally:
        printer.close()
    return study.reload(), outcomes


def _given(args, study_path, stage: str, options: dict, implied: dict | None = None):
    """The stage's settings for a single-stage command: those it last ran with in the study (else the
    defaults), with the options given on the command line — ``{setting: (attribute, convert)}`` — applied,
    and ``implied`` settings (those the given options imply, e.g. no VBD repair after ``--init none``) for
    whatever was not given itself."""
    from workbench.stages.run import settings_for
    from workbench.study import read_study

    base = settings_for(read_study(study_path), stage)
    over = {k: conv(getattr(args, a)) for k, (a, conv) in options.items() if hasattr(args, a)}
    for k, v in (implied or {}).items():
        over.setdefault(k, v)
    return dataclasses.replace(base, **over)


def _same(v):
    return v


def _dense_options(items) -> tuple:
    """``--dense NAME=VALUE`` options as ``(name, value)`` pairs (values JSON, else text); ``default`` alone: none.
    The names and types are checked by :class:`workbench.stages.register.RegisterSettings`."""
    from workbench.stages.run import json_value

    if list(items) == ["default"]:
        return ()
    out = []
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise ValueError(f"--dense {item!r}: expected NAME=VALUE (e.g. --dense window_mm=4), or 'default' alone")
        out.append((name.strip(), json_value(value)))
    return tuple(out)


def _bones_settings(args):
    from workbench.stages.bones import BonesSettings

    if getattr(args, "seeds", None) is None:
        if args.modality or args.threshold is not None:
            raise ValueError("--modality and --threshold choose how --seeds segments the bones: pass --seeds FILE")
        return None
    return BonesSettings(source="seeds", seeds=str(args.seeds), modality=args.modality, threshold=args.threshold)


def cmd_bones(args) -> int:
    from workbench.stages.bones import BonesSettings

    bs = _bones_settings(args) or BonesSettings(source="auto")
    study, _ = _stages(args, ["bones"], {"bones": bs}, force={"bones"} if args.force else ())
    counts = _read_output(study, "bones", "bones.json")
    print(f"bones ({counts['source']}): " + ", ".join(f"{b} {n}" for b, n in counts["voxels"].items()) + " voxels")
    print(f"wrote {study.root / 'bones'}")
    return 0


def _read_output(study, stage, name, scan=None):
    from workbench.io.jsonio import read_json

    return read_json(study.output(stage, name, scan))


def cmd_pose(args) -> int:
    ps = _given(
        args,
        args.study,
        "pose",
        {
            "method": ("method", _same),
            "init": ("init", str),
            "metric": ("metric", _same),
            "interpolation": ("interpolation", lambda v: 3 if v == "bspline" else 1),
            "prior_deg": ("prior_deg", lambda v: v or None),
            "min_ncc": ("min_ncc", _same),
            "bias_correction": ("bias_correction", {"auto": None, "on": True, "off": False}.get),
            "margin_mm": ("margin_mm", _same),
            "max_joint_gap_mm": ("max_joint_gap_mm", lambda v: v or None),
            "outlier_factor": ("outlier_factor", lambda v: v or None),
            "grid_factor": ("grid_factor", _same),
        },
    )
    ps = dataclasses.replace(ps, scans=tuple(args.scan) if args.scan else None)  # --scan: this run's scans only
    settings = {"pose": ps}
    bs = _bones_settings(args)
    if bs is not None:
        settings["bones"] = bs
    study, _ = _stages(args, ["pose"], settings, force={"pose"} if args.force else ())
    print(study.pose_report()["text"])
    if any(study.has_truth(sid) for sid in study.scan_ids):
        print(f"\n(accuracy against the ground truth: `workbench validate {study.root}`)")
    print(f"\nwrote {study.root / 'poses'} and updated {study.manifest_path}")
    return 0


def cmd_weights(args) -> int:
    ws = _given(
        args,
        args.study,
        "weights",
        {
            "method": ("method", _same),
            "edge_length_mm": ("edge_length_mm", _same),
            "grid_factor": ("grid_factor", _same),
        },
    )
    study, out = _stages(args, ["weights"], {"weights": ws}, force={"weights"} if args.force else ())
    e = study.stage_entry("weights")
    when = "up to date" if out[-1].status == "skipped" else f"{e['seconds']:.1f} s"
    print(f"{e['settings']['method']} weights ({when}); in {study.root / 'skinning'}")
    return 0


def cmd_model(args) -> int:
    from workbench.stages.model import ModelSettings

    source = args.source
    ms = ModelSettings(source=source, scans=tuple(args.scan) if args.scan else None)
    study, out = _stages(args, ["model"], {"model": ms}, force={"model"} if args.force else ())
    doc = _read_output(study, "model", "evd.json")
    print(
        f"EVD model from the {doc.get('source', source)} correspondences of {len(doc['scans'])} scans "
        f"({', '.join(doc['scans'])}){' (up to date)' if out[-1].status == 'skipped' else ''}; "
        f"in {study.root / 'model'}"
    )
    return 0


def cmd_surface(args) -> int:
    ss = _given(
        args,
        args.study,
        "surface",
        {
            **{k: (k, _same) for k in ("target_triangles", "features", "n_features", "fit", "stiffness")},
            "landmarks": ("landmarks", str),
        },
        implied={"features": "landmarks"}
        if hasattr(args, "landmarks")
        else {"landmarks": None}
        if getattr(args, "features", "landmarks") != "landmarks"
        else None,
    )
    ss = dataclasses.replace(ss, scans=tuple(args.scan) if args.scan else None)
    if ss.landmarks is not None:  # a bad landmarks file is reported before the stages it needs run
        from workbench.io.inputs import read_landmarks
        from workbench.study import read_study

        st = read_study(args.study)
        read_landmarks(ss.landmarks, st.scan_ids, st.check_scan_ids(ss.scans))
    study, out = _stages(args, ["surface"], {"surface": ss}, force={"surface"} if args.force else ())
    doc = _read_output(study, "surface", "surface.json")
    t = doc["template"]
    print(
        f"S0: {t['triangles']} triangles, {t['vertices']} vertices (weights: {t['weights']})"
        f"{' (up to date)' if out[-1].status == 'skipped' else ''}"
    )
    for sid, r in doc["per_scan"].items():
        f = r["fit_distance_mm"]
        print(
            f"  {sid}: {r['features']} feature points ({r['feature_source']}), {r['fit']} fit: distance to the "
            f"scan's skin mean {f['mean']:.2f} mm, P95 {f['p95']:.2f} mm"
        )
    print(f"in {study.root / 'surface'}")
    return 0


def cmd_surface_deform(args) -> int:
    from workbench.deform import surface_deform

    s = surface_deform(args.study, args.pose, args.out, method=args.method, overwrite=args.force)
    print(f"{args.method.upper()}: {s['vertices']} vertices in {s['seconds']:.3f} s; wrote {s['out']}")
    return 0


def _register_settings(args):
    # a recorded setting that a given option contradicts gives way to it: an earlier --unfold-init repaired a
    # VBD start (not another), --preset paper is Rhee's method, --method dense has no preset
    init_implied = {"unfold": False} if getattr(args, "init", "vbd") != "vbd" else {}
    if getattr(args, "init", "polyrigid") != "polyrigid":
        init_implied["map_factor"] = None  # the polyrigid start's
    reg_implied = {}
    if getattr(args, "preset", None) == "paper":
        reg_implied["method"] = "auto"
    if getattr(args, "preset", None) == "paper" or getattr(args, "method", None) == "adaptive":
        reg_implied["dense_settings"] = ()  # the dense registration's, recorded by an earlier run
    if getattr(args, "method", None) == "dense":  # nor Algorithm 1's options recorded by an earlier run
        reg_implied.update(preset="auto", levels=None, optimizer=None, metric=None, max_steps_per_level=None)
    init = _given(
        args,
        args.study,
        "init",
        {
            "method": ("init", lambda v: "identity" if v == "none" else v),
            "pose": ("pose_source", _same),
            "unfold": ("unfold_init", _same),
            "map_factor": ("map_factor", _same),
        },
        init_implied,
    )
    reg = _given(
        args,
        args.study,
        "register",
        {
            "method": ("method", _same),
            "preset": ("preset", lambda v: "paper" if v == "paper" else "auto"),
            "levels": ("levels", tuple),
            "optimizer": ("optimizer", _same),
            "metric": ("metric", _same),
            "max_steps_per_level": ("max_steps", _same),
            "fix_bones": ("no_fix_bones", lambda v: not v),
            "seed": ("seed", _same),
            "dense_settings": ("dense", _dense_options),
        },
        reg_implied,
    )
    given = [
        opt
        for opt, a in (
            ("--levels", "levels"),
            ("--optimizer", "optimizer"),
            ("--metric", "metric"),
            ("--max-steps", "max_steps"),
        )
        if hasattr(args, a)
    ]
    if given and reg.resolved_method == "dense":  # the dense method would ignore them without a word
        raise ValueError(
            f"{', '.join(given)} {'is a setting' if len(given) == 1 else 'are settings'} of Rhee's "
            "Algorithm 1, not of the dense registration: add --method adaptive, or leave "
            f"{'it' if len(given) == 1 else 'them'} out"
        )
    return {"init": init, "register": reg}


def cmd_register(args) -> int:
    force = {"init", "register"} if args.force else ()
    study, _ = _stages(args, ["init", "register"], _register_settings(args), force=force, scans=args.scan)
    print(format_registration_table(study, study.check_scan_ids(args.scan)))
    print(f"in {study.root / 'registration'}")
    return 0


def cmd_validate(args) -> int:
    study, _ = _stages(args, ["validate"], force={"validate"} if args.force else (), scans=args.scan)
    print(format_registration_table(study, study.check_scan_ids(args.scan)))
    return 0


def cmd_run(args) -> int:
    from workbench.stages import ORDER
    from workbench.stages.run import merged_settings, parse_set
    from workbench.study import read_study

    study = read_study(args.study)
    settings = merged_settings(study, parse_set(args.set_))
    if args.seeds is not None:
        from workbench.stages.run import settings_for

        settings["bones"] = dataclasses.replace(
            settings.get("bones") or settings_for(study, "bones"), source="seeds", seeds=str(args.seeds)
        )
    targets = list(ORDER[: ORDER.index(args.until) + 1]) if args.until else list(ORDER)
    from workbench.stages.run import dependents

    force = dependents(args.force) & set(targets) if args.force else set()
    t0 = time.perf_counter()
    study, outcomes = _stages(args, targets, settings, force=force, scans=args.scan)
    ran = [o for o in outcomes if o.status == "ran"]
    print(
        f"{len(ran)} stage run(s), {len(outcomes) - len(ran)} up to date or nothing to do; "
        f"{time.perf_counter() - t0:.1f} s"
    )
    if "validate" in targets:
        print(format_registration_table(study, study.check_scan_ids(args.scan)))
    return 0


def _is_table(path: Path) -> bool:
    import json

    try:
        return json.loads(path.read_text(encoding="utf-8")).get("format") == "avw-table"
    except (OSError, ValueError, AttributeError):
        return False


def cmd_report(args) -> int:
    from workbench.errors import InputFileError, OutputExistsError
    from workbench.io.atomic import write_text_atomic

    out = args.out
    if out.suffix.lower() not in (".html", ".htm"):
        raise ValueError(f"--out {out}: the report is an HTML file; give a name ending in .html")
    if out.exists() and not args.force:
        raise OutputExistsError(out, f"{out}: already exists; choose another --out or pass --force to replace it.")
    if not out.parent.exists():
        raise InputFileError(f"--out {out}: the folder {out.parent} does not exist; create it first", out.parent)
    src = args.source
    if (src / "study.json").exists():
        from workbench.stages.report import ReportSettings

        args.study = src
        study, _ = _stages(
            args,
            ["report"],
            {"report": ReportSettings(pictures=not args.no_pictures)},
            force={"report"} if args.force else (),
        )
        html = study.output("report", "report.html").read_text(encoding="utf-8")
    elif src.is_dir() and any(_is_table(p) for p in src.glob("*.json")):
        from workbench.report import tables_report

        html = tables_report(src)
    else:
        raise InputFileError(
            f"{src}: neither a study folder (no study.json) nor a `workbench reproduce` folder "
            "(no tables); give one of them",
            src,
        )
    write_text_atomic(out, html, overwrite=args.force)
    print(f"wrote {out} ({len(html.encode()) / 2**20:.1f} MB)")
    return 0


def cmd_reproduce(args) -> int:
    from workbench.reproduce import format_markdown, reproduce

    args.out.mkdir(parents=True, exist_ok=True)
    printer = _progress(args)
    say = (lambda m: None) if args.quiet else (lambda m: print(f"reproduce: {m}", file=sys.stderr, flush=True))
    t0 = time.perf_counter()

    def emit(table, seconds):
        print(format_markdown(table))
        print(f"({table.id}: {seconds:.0f} s; written to {args.out}/{table.id}.csv, .md, .json)\n", flush=True)

    try:
        workers = (
            args.workers
            if args.workers is not None
            else (1 if args.scheduler else min(2, os.cpu_count() or 1) if args.size == "test" else 1)
        )
        reproduce(
            args.tables,
            args.out,
            size=args.size,
            seed=args.seed,
            with_peers=args.with_peers,
            progress=printer,
            say=say,
            emit=emit,
            workers=workers,
            scheduler=args.scheduler,
        )
    finally:
        printer.close()
    print(f"reproduce: {', '.join(args.tables)} in {time.perf_counter() - t0:.0f} s")
    return 0


def format_registration_table(study, scans) -> str:
    """One row per scan and volume (source / initialised / registered): the validate stage's measures when the
    scan has truth, else the registration's similarity before and after (MED columns empty)."""
    lines = [
        "| scan | volume | MED mm | marker MED mm | SSD | CC | MI | folded | control pts | s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]

    def num(v, fmt):
        return "" if v is None or v != v else format(v, fmt)

    for sid in scans:
        if not study.has_registration(sid):
            continue
        log = study.registration_log(sid)["summary"]
        e = study.stage_entry("register", sid)
        if study.has_output("validate", "measures.json", sid):
            rows = study.validation(sid)["rows"]
        else:
            b, a = log["similarity_before"], log["similarity_after"]
            rows = {"before": dict(b), "registered": {**a, "folded_fraction": log["folding"].get("fraction_folded")}}
        for name in [k for k in ("source", "before", "initialised", "registered") if k in rows]:
            r, last = rows[name], name == "registered"
            lines.append(
                f"| {sid} | {name} | {num(r.get('med_mm'), '.2f')} | {num(r.get('marker_med_mm'), '.2f')} | "
                f"{num(r.get('ssd'), '.1f')} | {num(r.get('cc'), '.3f')} | {num(r.get('mi'), '.3f')} | "
                f"{num(r.get('folded_fraction'), '.4f')} | {num(log.get('control_points'), 'd') if last else ''} | "
                f"{e['seconds'] if last else ''} |"
            )
    lines.append(
        "(MED: mean |recovered − true| template position over the scan's body voxels; folded: fraction of "
        "body voxels with det ≤ 0 when validated, else as the registration counted it: over the scan's body (dense) "
        "or the whole grid (adaptive); MI in nats, 32 bins)"
    )
    return "\n".join(lines)


def cmd_render(args) -> int:
    from workbench.viz.render import (
        SKIN_COLOUR,
        ClipPlane,
        label_colour,
        opengl_backend,
        parse_size,
        render_difference,
        render_overlay,
        render_volume,
        transfer_function,
        write_png,
    )

    say = _say(args) or (lambda line: None)
    size = parse_size(args.size)
    clip = ClipPlane.parse(args.clip) if args.clip else None
    cam = _camera(args)
    bg = _background(args.background)
    tf = transfer_function(args.preset)
    if args.out.suffix.lower() != ".png":
        raise ValueError(f"--out {args.out}: stills are PNG; name it *.png")
    from workbench.io.atomic import check_output_folder

    check_output_folder(args.out, "--out")
    if args.out.exists() and not args.force:
        from workbench.errors import OutputExistsError

        raise OutputExistsError(args.out, f"{args.out} exists; pass --force to replace it.")
    from workbench.io.meshes import MESH_SUFFIXES, read_mesh

    alone = args.source.name.lower().endswith(MESH_SUFFIXES)
    mesh_files = ([args.source] if alone else []) + list(args.mesh or [])
    opacity = args.mesh_opacity
    if not 0.0 < opacity <= 1.0:
        raise ValueError(f"--mesh-opacity must be in (0, 1], got {opacity}")
    if mesh_files and (args.overlay or args.difference):
        raise ValueError(
            f"{args.source} is a mesh: --overlay/--difference compare two volumes"
            if alone
            else "--mesh draws on a single-volume render; leave out --overlay/--difference"
        )
    if alone and any(getattr(args, k) for k in ("scan", "registered", "labels", "bones", "markers", "control_points")):
        raise ValueError(
            f"{args.source} is a mesh: --scan, --registered, --labels, --bones, --markers and "
            "--control-points need a volume or a study"
        )
    meshes = [
        (read_mesh(m), SKIN_COLOUR if k == 0 else label_colour(k + 1), opacity) for k, m in enumerate(mesh_files)
    ]  # every mesh read (and checked) before any rendering
    if alone:
        kw = dict(size=size, camera=cam, clip=clip, background=bg)
        t0 = time.perf_counter()
        img = render_volume(None, meshes=meshes, **kw)
        dt = time.perf_counter() - t0
        write_png(img, args.out, overwrite=args.force)
        print(f"rendered {size[0]}x{size[1]} in {dt:.2f} s; wrote {args.out}")
        return 0
    from workbench.viz.scene import render_inputs

    vol, labels, other, points = render_inputs(
        args.source,
        scan=args.scan,
        registered=args.registered,
        bones=args.bones,
        labels=args.labels,
        overlay=args.overlay,
        difference=args.difference,
        markers=args.markers,
        control_points=args.control_points,
        progress=say,
    )
    kw = dict(size=size, camera=cam, clip=clip, background=bg, mapper=args.mapper)
    b = opengl_backend()
    say(f"{b.describe()}; {b.mapper if args.mapper == 'auto' else args.mapper} mapper")
    t0 = time.perf_counter()
    if args.overlay:
        img = render_overlay(vol, other, transfer=tf, points=points, **kw)
    elif args.difference:
        if points:
            raise ValueError("--markers/--control-points are drawn on renders and overlays, not difference views")
        img = render_difference(vol, other, transfer=tf, **kw)
    else:
        img = render_volume(vol, labels=labels, points=points, meshes=meshes, transfer=tf, **kw)
    dt = time.perf_counter() - t0
    write_png(img, args.out, overwrite=args.force)
    print(f"rendered {size[0]}x{size[1]} in {dt:.2f} s; wrote {args.out}")
    return 0


def cmd_animate(args) -> int:
    from workbench.viz.animate import animate_study
    from workbench.viz.render import ClipPlane, parse_size

    size = parse_size(args.size)
    clip = ClipPlane.parse(args.clip) if args.clip else None
    bg = _background(args.background)
    from workbench.study import read_study
    from workbench.viz.animate import builtin_keyframes, camera_from, read_keyframes

    study = read_study(args.study)
    sk = study.skeleton()
    if args.keyframes is not None and str(args.keyframes) == "scans":
        from workbench.viz.animate import scan_keyframes

        kf = scan_keyframes(study)
    else:
        kf = read_keyframes(args.keyframes, sk) if args.keyframes else builtin_keyframes(sk)
    cam = camera_from(kf.camera, view=args.camera, azimuth=args.azimuth, elevation=args.elevation, zoom=args.zoom)
    s = animate_study(
        args.study,
        args.out,
        keyframes=kf,
        method=args.method,
        weighting=args.weighting,
        fps=args.fps,
        size=size,
        n_frames=args.frames,
        transfer=args.preset,
        camera=cam,
        orbit=args.orbit,
        clip=clip,
        bones=args.bones,
        background=bg,
        mapper=args.mapper,
        skin=args.skin,
        overwrite=args.force,
        map_factor=args.map_factor,
        progress=_say(args),
    )
    n = s["frames"]
    print(
        f"{n} frames {s['size'][0]}x{s['size'][1]} at {s['fps']:g} fps ({s['method'].upper()}, {s['mapper']} "
        f"mapper): deformation {s['deform_seconds']:.1f} s ({s['deform_seconds_per_frame']:.3f} s/frame), "
        f"rendering {s['render_seconds']:.1f} s ({s['render_seconds_per_frame']:.3f} s/frame), encoding "
        f"{s['encode_seconds']:.1f} s; total {s['total_seconds']:.1f} s"
    )
    print(f"wrote {s['out']}" + (f" ({s['files']} files)" if s["files"] > 1 else ""))
    return 0


def cmd_phantom(args) -> int:
    from validation.phantoms import Phantom, PhantomSpec
    from workbench.errors import InputFileError, OutputExistsError
    from workbench.study import write_phantom_study

    if args.out.exists() and not args.force:
        raise OutputExistsError(
            args.out, f"{args.out}: already exists; choose another --out or pass --force to replace it."
        )
    from workbench.io.inputs import read_poses_file

    poses = read_poses_file(args.poses_file) if args.poses_file else None
    try:
        spec = PhantomSpec(
            region=args.region,
            size=args.size,
            modality=args.modality,
            n_poses=args.poses,
            posing=args.posing,
            seed=args.seed,
            noise=not args.noise_free,
            poses=poses,
            spacing=_spacing(args.spacing),
            acquisition=args.acquisition,
        )
        phantom = Phantom(spec)
    except ValueError as e:
        if args.poses_file:
            raise InputFileError(f"{args.poses_file}: {e}", args.poses_file) from e
        raise
    bar = None
    if not args.quiet:
        from tqdm import tqdm

        bar = tqdm(
            total=len(phantom.poses) + 1, desc=f"{args.region} phantom ({args.size})", unit="image", file=sys.stderr
        )
    t0 = time.perf_counter()

    def progress(stage, done, total):
        if bar is not None:
            bar.update(1)

    try:
        study = write_phantom_study(phantom, args.out, overwrite=args.force, progress=progress)
    finally:
        if bar is not None:
            bar.close()
    if not args.quiet:
        print(f"wrote {args.out} in {time.perf_counter() - t0:.1f} s")
        print(summarize(study))
    return 0


def summarize(study) -> str:
    """A human-readable summary of a study folder."""
    import numpy as np

    from workbench.io.jsonio import read_json
    from workbench.io.volumes import read_image_geometry

    m = study.manifest
    sk = study.skeleton()
    g = read_image_geometry(study.path(m["template"]))
    lines = [
        f"study: {study.root}  ({m.get('name', '')})",
        f"template: {m['template']}  size {g.size} voxels, spacing "
        f"{tuple(round(s, 4) for s in g.spacing)} mm, extent {tuple(round(e, 1) for e in g.extent_mm)} mm",
        f"skeleton: {sk.name}, {len(sk.bones)} bones, {len(sk.joints)} joints, {sk.n_dof} DOF "
        f"(6-DOF joints: {', '.join(j.name for j in sk.joints if j.dof == 6) or 'none'})",
    ]
    drawn = (m.get("phantom") or {}).get("acquisition_drawn")
    if isinstance(drawn, dict):  # a random-acquisition phantom: what it drew
        from validation.phantoms.generate import describe_acquisition

        lines.append(describe_acquisition(drawn))
    vox_ml = float(np.prod(g.spacing)) / 1000.0
    if study.has_template_labels:
        labels = study.template_labels().data
        counts = np.bincount(labels.ravel(), minlength=max(b.label for b in sk.bones) + 1)
        lines.append(
            "bones (label: voxels, ml): "
            + ", ".join(f"{b.name} ({b.label}: {counts[b.label]}, {counts[b.label] * vox_ml:.1f})" for b in sk.bones)
        )
    else:
        lines.append("bones: no label map yet (segment them with `workbench pose STUDY --seeds FILE`)")
    log_path = study.root / "logs" / "phantom.json"
    stats = {s["id"]: s for s in read_json(log_path)["scans"]} if log_path.exists() else {}
    lines.append(f"scans: {len(m['scans'])}")
    header = f"  {'id':<10}{'joint angles (deg)':<44}{'max |u| body':>13}{'folded':>9}{'inv. resid.':>12}{'markers':>8}"
    lines.append(header)
    poses = {s["id"]: study.truth_pose(s["id"]) for s in m["scans"] if "truth" in s}
    # Show the three joints that flex most over the study (first angle = flexion).
    span = {
        j.name: max(
            (abs(p.joint_angles[j.name][0]) for p in poses.values() if p.joint_angles and j.name in p.joint_angles),
            default=0.0,
        )
        for j in sk.joints
    }
    shown = [j for j in sorted(span, key=span.get, reverse=True)[:3] if span[j] > 0]
    shown.sort(key=[j.name for j in sk.joints].index)
    for s in m["scans"]:
        sid = s["id"]
        angles = ""
        nm = 0
        if sid in poses:
            ja = poses[sid].joint_angles or {}
            angles = " ".join(f"{j}={ja[j][0]:.0f}" if j in ja else f"{j}=?" for j in shown)
            nm = len(study.truth_markers(sid))
        st = stats.get(sid, {})
        lines.append(
            f"  {sid:<10}{angles[:43]:<44}{st.get('max_displacement_mm', float('nan')):>10.1f} mm"
            f"{100 * st.get('folded_fraction_body', float('nan')):>8.2f}%"
            f"{st.get('inverse_residual_body_p99_mm', float('nan')):>9.1e} mm{nm:>8}"
        )
    if stats:
        lines.append(
            "  (max |u|: largest correspondence displacement inside the body; folded: body voxels whose "
            "correspondence has Jacobian determinant ≤ 0; inv. resid.: 99th percentile of |F(φ(x)) − x| "
            "in the body)"
        )
    from workbench.stages import ORDER
    from workbench.stages.mechanism import recorded_times

    times = recorded_times(study, ORDER)  # study.json's: the stages' files hold no time
    if times:
        lines.append("stages run (wall-clock seconds, from study.json):")
        lines += times
    return "\n".join(lines)


def cmd_info(args) -> int:
    from workbench.study import read_study

    study = read_study(args.study)
    print(summarize(study))
    if not args.check:
        return 0
    from workbench.checks import check_study_images, study_warnings

    problems = check_study_images(study)
    warnings = [] if problems else study_warnings(study)
    if warnings:
        print(f"\n{len(warnings)} warning(s):", file=sys.stderr)
        for w in warnings:
            print(f"  {w}", file=sys.stderr)
    if problems:
        print(f"\n{len(problems)} problem(s):", file=sys.stderr)
        for p in problems:
            print(f"  {p}", file=sys.stderr)
        return 1
    print("\nevery image read: no problem found" + (f" ({len(warnings)} warning(s) above)" if warnings else ""))
    return 0


def cmd_clean_image(args) -> int:
    import numpy as np

    from workbench.errors import OutputExistsError
    from workbench.io.atomic import check_output_folder
    from workbench.io.volumes import image_format, read_volume, write_volume

    if args.out.resolve() == args.image.resolve():
        raise ValueError(f"--out {args.out} is the input: write the cleaned copy elsewhere (the input is kept)")
    if args.value is not None and not np.isfinite(args.value):
        raise ValueError(f"--value must be a finite number, got {args.value}")
    check_output_folder(args.out, "--out")
    image_format(args.out, for_writing=True)
    if args.out.exists() and not args.force:
        raise OutputExistsError(args.out, f"{args.out} exists; pass --force to replace it.")
    v = read_volume(args.image, allow_nonfinite=True)
    data = np.asarray(v.data)
    bad = ~np.isfinite(data)
    if bad.all() and args.value is None:
        raise ValueError(f"{args.image}: no finite voxel at all; give --value")
    fill = float(args.value) if args.value is not None else float(data[~bad].min())
    clean = np.where(bad, fill, data).astype(data.dtype)
    write_volume(type(v)(clean, v.geometry), args.out, overwrite=args.force)
    print(f"{int(bad.sum())} of {bad.size} voxels replaced by {fill:g}; wrote {args.out}")
    return 0


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    import signal

    from workbench.errors import WorkbenchError

    def terminate(signum, frame):  # SIGTERM: unwind like Ctrl-C, so staging folders are removed
        raise KeyboardInterrupt

    from workbench.progress import tolerate_kernel_cache_failures

    tolerate_kernel_cache_failures()
    previous = signal.signal(signal.SIGTERM, terminate)
    try:
        return args.func(args)
    except (WorkbenchError, ValueError, OSError) as e:
        print(f"workbench {args.command}: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(
            f"workbench {args.command}: interrupted; nothing was left half-written (run it again to resume).",
            file=sys.stderr,
        )
        return 130
    finally:
        signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
