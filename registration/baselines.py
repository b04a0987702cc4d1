"""General-purpose deformable registrations (B-splines, greedy, demons), run in the same harness as the adaptive one.

The peers a researcher would otherwise reach for, on the same inputs and
returning the same thing — a ``scan_to_template`` field on the scan grid — so
that every comparison (``benchmarks/bench_registration.py``,
:mod:`validation.protocols.registration`) is made in one run on the same data:

* :func:`sitk_bspline` — SimpleITK's multi-resolution free-form deformation
  (cubic B-spline transform, MI or mean squares, gradient descent with line search, a control grid
  refined ×2 per level);
* :func:`elastix_bspline` — elastix's B-spline registration through
  ``itk-elastix`` (the optional ``bench`` extra: ``pip install -e '.[bench]'``),
  its default B-spline parameter map with a stated final grid spacing;
* :func:`greedy_register` — PICSL greedy (``picsl-greedy``, the ``bench``
  extra), Yushkevich's fast greedy deformable registration: local NCC, three
  levels, its documented update and field smoothing;
* :func:`sitk_demons` — SimpleITK's fast symmetric-forces demons on a shrink
  pyramid, the moving image histogram-matched to the fixed first.

With an initial field ``φ₀`` (e.g. VBD), the template is first resampled onto
the scan grid through ``φ₀``; the baseline registers the scan to that image,
giving ``T`` (scan point → point of the initialised image), and the result is
``φ₀ ∘ T`` (:func:`deformation.fields.displacement.compose`), never a sum.
"""

from __future__ import annotations

import os
import tempfile
import time
import warnings
from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk

from deformation.fields.displacement import compose, from_transform
from deformation.geometry import Volume

from .metrics import warp_template

__all__ = [
    "BaselineResult",
    "sitk_bspline",
    "elastix_bspline",
    "elastix_available",
    "greedy_register",
    "greedy_available",
    "sitk_demons",
    "ants_syn",
    "ants_available",
    "load_itk",
]


@dataclass
class BaselineResult:
    name: str
    correspondence: Volume  #: scan_to_template (mm) on the scan grid
    registered: Volume  #: the template resampled onto the scan grid through it
    seconds: float
    parameters: dict


def _initialised(fixed: Volume, moving: Volume, initial: Volume | None) -> Volume:
    if initial is None:
        if moving.geometry.is_close(fixed.geometry):
            return Volume(moving.data.astype(np.float32), fixed.geometry)
        initial = Volume(np.zeros(fixed.geometry.array_shape + (3,)), fixed.geometry)
    fixed.geometry.check_same(initial.geometry, names=("fixed image", "initial correspondence"))
    return warp_template(moving, initial)


def _finish(name, fixed, moving, initial, t_field: Volume, seconds, params) -> BaselineResult:
    corr = t_field if initial is None else compose(initial, t_field)
    corr = Volume(corr.data.astype(np.float32), fixed.geometry)
    return BaselineResult(name, corr, warp_template(moving, corr), seconds, params)


def sitk_bspline(
    fixed: Volume,
    moving: Volume,
    *,
    initial: Volume | None = None,
    metric: str = "mi",
    grid_spacing_mm: float = 40.0,
    shrink=(4, 2, 1),
    smoothing_voxels=(2.0, 1.0, 0.0),
    iterations: int = 100,
    sampling: float = 0.25,
    bins: int = 32,
    seed: int = 0,
) -> BaselineResult:
    """SimpleITK multi-resolution B-spline registration of the template to a scan.

    ``grid_spacing_mm`` is the control-point spacing at the finest level (the
    coarsest is ``2**(levels-1)`` times coarser: the mesh is refined ×2 per
    level).  ``metric`` is ``"mi"`` (Mattes, ``bins`` bins) or ``"ssd"`` (mean
    squares).  Random metric sampling (``sampling`` of the voxels) uses
    ``seed``.
    """
    if metric not in ("mi", "ssd"):
        raise ValueError(f"metric must be 'mi' or 'ssd', got {metric!r}")
    if len(shrink) != len(smoothing_voxels):
        raise ValueError("shrink and smoothing_voxels need one entry per level")
    t0 = time.perf_counter()
    f = sitk.Cast(fixed.to_sitk(), sitk.sitkFloat32)
    m = sitk.Cast(_initialised(fixed, moving, initial).to_sitk(), sitk.sitkFloat32)
    levels = len(shrink)
    extent = np.asarray(fixed.geometry.extent_mm)
    coarse = grid_spacing_mm * 2 ** (levels - 1)
    mesh = [max(1, int(round(e / coarse))) for e in extent]
    tx = sitk.BSplineTransformInitializer(f, mesh, 3)
    r = sitk.ImageRegistrationMethod()
    if metric == "mi":
        r.SetMetricAsMattesMutualInformation(numberOfHistogramBins=bins)
    else:
        r.SetMetricAsMeanSquares()
    r.SetMetricSamplingStrategy(r.RANDOM)
    r.SetMetricSamplingPercentage(float(sampling), int(seed))
    r.SetInterpolator(sitk.sitkLinear)
    # Gradient descent with line search and physical-shift scales (SimpleITK's multi-resolution B-spline
    # example): L-BFGS-B keeps the scales of the first mesh and fails once the mesh is refined.
    r.SetOptimizerAsGradientDescentLineSearch(
        learningRate=5.0, numberOfIterations=iterations, convergenceMinimumValue=1e-5, convergenceWindowSize=5
    )
    r.SetOptimizerScalesFromPhysicalShift()
    r.SetShrinkFactorsPerLevel(list(shrink))
    r.SetSmoothingSigmasPerLevel(list(smoothing_voxels))
    r.SmoothingSigmasAreSpecifiedInPhysicalUnitsOff()
    r.SetInitialTransformAsBSpline(tx, inPlace=True, scaleFactors=[2**k for k in range(levels)])
    out = r.Execute(f, m)
    field = from_transform(out, fixed.geometry)
    params = {
        "metric": metric,
        "grid_spacing_mm": grid_spacing_mm,
        "shrink": list(shrink),
        "smoothing_voxels": list(smoothing_voxels),
        "iterations": iterations,
        "sampling": sampling,
        "bins": bins,
        "seed": seed,
        "initial_mesh": mesh,
        "final_metric": float(r.GetMetricValue()),
        "stop": r.GetOptimizerStopConditionDescription(),
    }
    return _finish("sitk-bspline", fixed, moving, initial, field, time.perf_counter() - t0, params)


def load_itk():
    """``import itk`` with its import-time warnings silenced: under ``-W error`` (our test suite) a warning
    raised half-way through ITK's lazy module loading crashes the interpreter."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import itk

        _ = itk.elastix_registration_method  # the lazy loader imports the elastix module here
    return itk


def elastix_available() -> bool:
    """Whether itk-elastix is installed — checked without importing ITK (importing it into a process that
    also runs our test suite made the interpreter crash at exit)."""
    from importlib import metadata

    try:
        metadata.version("itk-elastix")
    except metadata.PackageNotFoundError:
        return False
    return True


def _to_itk(vol: Volume):
    itk = load_itk()
    img = itk.image_from_array(np.ascontiguousarray(vol.data, dtype=np.float32))
    g = vol.geometry
    img.SetSpacing([float(v) for v in g.spacing])
    img.SetOrigin([float(v) for v in g.origin])
    img.SetDirection(itk.matrix_from_array(np.ascontiguousarray(g.direction_matrix, dtype=np.float64)))
    return img


def elastix_bspline(
    fixed: Volume,
    moving: Volume,
    *,
    initial: Volume | None = None,
    metric: str = "mi",
    grid_spacing_mm: float = 20.0,
    resolutions: int = 3,
    iterations: int = 500,
    seed: int = 0,
    rigidity_labels: Volume | None = None,
    rigidity_weight: float = 0.1,
) -> BaselineResult:
    """elastix B-spline registration (itk-elastix), its default B-spline map with the given grid and metric.

    ``rigidity_labels`` (the template's bone label map) adds elastix's
    ``TransformRigidityPenalty`` (Staring et al. 2007) on the bones, weighted
    ``rigidity_weight`` against the similarity: the strongest bone-aware
    general-purpose peer.  The bones are pulled through ``initial`` onto the
    scan grid (where elastix's moving image lives) and dilated by one voxel.

    Raises ``ImportError`` naming the extra to install when itk-elastix is absent.
    """
    if not elastix_available():
        raise ImportError("elastix baseline needs itk-elastix: pip install -e '.[bench]' (or pip install itk-elastix)")
    itk = load_itk()

    if metric not in ("mi", "ssd"):
        raise ValueError(f"metric must be 'mi' or 'ssd', got {metric!r}")
    t0 = time.perf_counter()
    f = _to_itk(fixed)
    m = _to_itk(_initialised(fixed, moving, initial))
    po = itk.ParameterObject.New()
    p = po.GetDefaultParameterMap("bspline", int(resolutions))
    p["FinalGridSpacingInPhysicalUnits"] = [str(float(grid_spacing_mm))]
    p["Metric"] = ["AdvancedMattesMutualInformation" if metric == "mi" else "AdvancedMeanSquares"]
    p["MaximumNumberOfIterations"] = [str(int(iterations))]
    p["RandomSeed"] = [str(int(seed))]
    p["WriteResultImage"] = ["false"]
    with tempfile.TemporaryDirectory(prefix="avw-elastix-") as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # ITK's lazy loader imports more modules here (see load_itk)
        if rigidity_labels is not None:
            from scipy import ndimage

            from deformation.fields.interpolate import sample_displaced_array

            g = fixed.geometry
            u = initial.data if initial is not None else np.zeros(g.array_shape + (3,), np.float32)
            bones = (
                sample_displaced_array(
                    np.asarray(rigidity_labels.data), rigidity_labels.geometry.world_to_index_matrix, g, u, 0, 0
                )
                > 0
            )
            bones = ndimage.binary_dilation(bones)
            path = os.path.join(tmp, "rigidity.mha")
            itk.imwrite(_to_itk(Volume(bones.astype(np.float32), g)), path)
            p["Registration"] = ["MultiMetricMultiResolutionRegistration"]
            p["Metric"] = [p["Metric"][0], "TransformRigidityPenalty"]
            p["Metric0Weight"] = ["1.0"]
            p["Metric1Weight"] = [str(float(rigidity_weight))]
            p["MovingRigidityImageName"] = [path]
            p["UseLinearityCondition"] = ["true"]
            p["UseOrthonormalityCondition"] = ["true"]
            p["UsePropernessCondition"] = ["true"]
        po.AddParameterMap(p)
        cwd = os.getcwd()
        os.chdir(tmp)  # elastix may drop log files into the working folder
        try:
            _, result = itk.elastix_registration_method(
                f, m, parameter_object=po, log_to_console=False, output_directory=tmp
            )
            field = itk.transformix_deformation_field(m, result)
        finally:
            os.chdir(cwd)
    u = np.asarray(itk.array_from_image(field), dtype=np.float64)  # (nz, ny, nx, 3): fixed x → x + u in moving
    t_field = Volume(u, fixed.geometry)
    params = {
        "metric": metric,
        "grid_spacing_mm": grid_spacing_mm,
        "resolutions": resolutions,
        "iterations": iterations,
        "seed": seed,
        "parameter_map": "elastix default 'bspline'",
        "rigidity_weight": rigidity_weight if rigidity_labels is not None else None,
    }
    name = "elastix-bspline" if rigidity_labels is None else "elastix-bspline-rigidity"
    return _finish(name, fixed, moving, initial, t_field, time.perf_counter() - t0, params)


def greedy_available() -> bool:
    """Whether picsl-greedy is installed (found without importing it)."""
    from importlib.util import find_spec

    return find_spec("picsl_greedy") is not None


def greedy_register(
    fixed: Volume,
    moving: Volume,
    *,
    initial: Volume | None = None,
    ncc_radius: int = 2,
    iterations=(100, 50, 20),
    smoothing_voxels=(2.0, 0.5),
    step: float = 1.0,
    threads: int | None = None,
    seed: int = 0,
) -> BaselineResult:
    """PICSL greedy's deformable registration (``picsl-greedy``) of the template to a scan.

    The settings of greedy's documentation and its Python package's example:
    ``-m NCC 2x2x2`` (local normalised cross-correlation, ``ncc_radius`` voxels
    each way), ``-n 100x50x20`` (``iterations`` per level, coarsest first: 4×,
    2× and 1× shrink), ``-s 2.0vox 0.5vox`` (``smoothing_voxels``: the
    Gaussian σ of the update (fluid-like) and of the total field (elastic-like),
    in voxels) and step ``-e 1.0``.  The images are passed and the warp taken
    back in memory (SimpleITK images, ITK's physical frame, as ours): greedy's
    warp maps a fixed point ``x`` to ``x + w(x)`` in the moving image, in mm —
    the scan → template convention — saved at full precision (``-wp 0``, not its
    default 0.1-voxel quantisation).  ``threads`` (default: ITK's global default,
    as the other in-process peers) is ``-threads``; greedy's random generator
    (the small noise its NCC adds) is seeded ``-seed seed + 1`` (its 0 means
    unseeded).

    Raises ``ImportError`` naming the extra to install when picsl-greedy is absent.
    """
    if not greedy_available():
        raise ImportError(
            "the greedy baseline needs picsl-greedy: pip install -e '.[bench]' (or pip install picsl-greedy)"
        )
    from picsl_greedy import Greedy3D

    if len(smoothing_voxels) != 2:
        raise ValueError("smoothing_voxels is greedy's pair (update sigma, field sigma), in voxels")
    threads = int(threads or sitk.ProcessObject.GetGlobalDefaultNumberOfThreads())
    t0 = time.perf_counter()
    f = sitk.Cast(fixed.to_sitk(), sitk.sitkFloat32)
    m = sitk.Cast(_initialised(fixed, moving, initial).to_sitk(), sitk.sitkFloat32)
    r = int(ncc_radius)
    cmd = (
        f"-d 3 -i fixed moving -m NCC {r}x{r}x{r} -n {'x'.join(str(int(n)) for n in iterations)} "
        f"-s {float(smoothing_voxels[0])}vox {float(smoothing_voxels[1])}vox -e {float(step)} -wp 0 "
        f"-threads {threads} -seed {int(seed) + 1} -V 0 -o warp"
    )
    g = Greedy3D()
    g.execute(cmd, fixed=f, moving=m, warp=None)  # raises RuntimeError with greedy's message when it fails
    warp = g["warp"]  # a vector image on the fixed grid: x -> x + w(x) in the moving image, mm
    Volume.from_sitk(warp).geometry.check_same(fixed.geometry, names=("greedy's warp", "fixed image"))
    t_field = Volume(sitk.GetArrayFromImage(warp), fixed.geometry)
    params = {
        "metric": f"NCC {r}x{r}x{r}",
        "iterations": list(iterations),
        "smoothing_voxels": list(smoothing_voxels),
        "step": step,
        "threads": threads,
        "seed": seed,
        "command": cmd,
    }
    return _finish("greedy", fixed, moving, initial, t_field, time.perf_counter() - t0, params)


def _shrunk(img, factor: int, sigma_voxels: float):
    """``img`` smoothed by a Gaussian of ``sigma_voxels`` (its own voxels, per axis) and resampled ``factor``×
    coarser over the same physical extent (SimpleITK's demons examples' ``smooth_and_resample``)."""
    if factor == 1 and sigma_voxels == 0:
        return img
    spacing = np.asarray(img.GetSpacing())
    if sigma_voxels > 0:
        img = sitk.SmoothingRecursiveGaussian(img, [float(v) for v in sigma_voxels * spacing])
    size = [max(2, int(n / factor + 0.5)) for n in img.GetSize()]
    new_spacing = [(n - 1) * s / (k - 1) for n, s, k in zip(img.GetSize(), spacing, size)]
    return sitk.Resample(
        img,
        size,
        sitk.Transform(),
        sitk.sitkLinear,
        img.GetOrigin(),
        new_spacing,
        img.GetDirection(),
        0.0,
        img.GetPixelID(),
    )


def sitk_demons(
    fixed: Volume,
    moving: Volume,
    *,
    initial: Volume | None = None,
    shrink=(4, 2, 1),
    smoothing_voxels=(2.0, 1.0, 0.0),
    iterations=(100, 100, 50),
    field_sd_voxels: float = 1.5,
    histogram_match: bool = True,
    seed: int = 0,
) -> BaselineResult:
    """SimpleITK's fast symmetric-forces demons (Vercauteren et al.'s ESM forces) of the template to a scan.

    As SimpleITK's demons examples: the moving image first histogram-matched
    to the fixed (1024 levels, 7 match points, voxels below the mean left
    out; demons' force is a difference of intensities), then a pyramid of
    ``shrink`` levels, each image smoothed by ``smoothing_voxels`` (σ in the
    full grid's voxels) and resampled over the same extent; at each level
    ``iterations`` demons iterations with the displacement field smoothed by a
    Gaussian of ``field_sd_voxels`` (that level's voxels) after each, the
    field carried to the next level by linear resampling.  The field is ITK's
    physical displacement (mm), fixed ``x`` → moving ``x + u(x)``.  Demons is
    deterministic: ``seed`` is accepted for the peers' common signature and
    recorded.
    """
    if len(shrink) != len(smoothing_voxels) or len(shrink) != len(iterations):
        raise ValueError("shrink, smoothing_voxels and iterations need one entry per level")
    t0 = time.perf_counter()
    f = sitk.Cast(fixed.to_sitk(), sitk.sitkFloat32)
    m = sitk.Cast(_initialised(fixed, moving, initial).to_sitk(), sitk.sitkFloat32)
    if histogram_match:
        m = sitk.HistogramMatching(
            m, f, numberOfHistogramLevels=1024, numberOfMatchPoints=7, thresholdAtMeanIntensity=True
        )
    demons = sitk.FastSymmetricForcesDemonsRegistrationFilter()
    demons.SetSmoothDisplacementField(True)
    demons.SetStandardDeviations(float(field_sd_voxels))
    field, levels = None, []
    for factor, sigma, n in zip(shrink, smoothing_voxels, iterations):
        fs, ms = _shrunk(f, int(factor), float(sigma)), _shrunk(m, int(factor), float(sigma))
        if field is None:
            field = sitk.Image(fs.GetSize(), sitk.sitkVectorFloat64)
            field.CopyInformation(fs)
        else:
            field = sitk.Resample(field, fs)  # physical displacements: the values carry over unscaled
        demons.SetNumberOfIterations(int(n))
        field = demons.Execute(fs, ms, field)
        levels.append(
            {"shrink": int(factor), "iterations": demons.GetElapsedIterations(), "metric": demons.GetMetric()}
        )
    if not Volume.from_sitk(field).geometry.is_close(fixed.geometry):  # a last level coarser than the scan
        field = sitk.Resample(field, f)
    t_field = Volume(sitk.GetArrayFromImage(field), fixed.geometry)
    params = {
        "shrink": list(shrink),
        "smoothing_voxels": list(smoothing_voxels),
        "iterations": list(iterations),
        "field_sd_voxels": field_sd_voxels,
        "histogram_match": histogram_match,
        "seed": seed,
        "levels": levels,
    }
    return _finish("sitk-demons", fixed, moving, initial, t_field, time.perf_counter() - t0, params)


def _ants_python() -> str | None:
    """The interpreter with antspyx: ``$AVW_ANTS_PYTHON``, else ``.venv-ants`` at the project root
    (``make bench-ants``)."""
    from pathlib import Path

    exe = os.environ.get("AVW_ANTS_PYTHON") or str(
        Path(__file__).resolve().parents[1] / ".venv-ants" / "bin" / "python"
    )
    return exe if os.path.exists(exe) else None


def ants_available() -> bool:
    return _ants_python() is not None


def ants_syn(
    fixed: Volume, moving: Volume, *, initial: Volume | None = None, seed: int = 0, threads: int | None = None
) -> BaselineResult:
    """ANTs SyN (antspyx's ``SyNOnly``, Mattes MI) of the template to a scan, in antspyx's own interpreter.

    antspyx pins older NumPy/SciPy than this project, so it runs in
    ``.venv-ants`` (``make bench-ants``) through ``registration/_ants_runner.py``
    with image files; raises ``RuntimeError`` naming that target when it is absent.
    """
    import subprocess
    from pathlib import Path

    exe = _ants_python()
    if exe is None:
        raise RuntimeError(
            "the ANTs baseline needs antspyx in its own environment: run `make bench-ants`, "
            "or set AVW_ANTS_PYTHON to a Python that has antspyx"
        )
    t0 = time.perf_counter()
    m = _initialised(fixed, moving, initial)
    env = dict(os.environ, ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS=str(threads or os.cpu_count() or 1))
    with tempfile.TemporaryDirectory(prefix="avw-ants-") as tmp:
        fp, mp, wp = (os.path.join(tmp, n) for n in ("fixed.nii.gz", "moving.nii.gz", "warp.nii.gz"))
        sitk.WriteImage(sitk.Cast(fixed.to_sitk(), sitk.sitkFloat32), fp)
        sitk.WriteImage(sitk.Cast(m.to_sitk(), sitk.sitkFloat32), mp)
        run = subprocess.run(
            [exe, str(Path(__file__).with_name("_ants_runner.py")), fp, mp, wp, str(int(seed))],
            capture_output=True,
            text=True,
            env=env,
            cwd=tmp,
        )
        if run.returncode != 0:
            raise RuntimeError(
                f"ANTs SyN failed: {run.stderr.strip().splitlines()[-1] if run.stderr.strip() else run.returncode}"
            )
        warp = sitk.ReadImage(wp, sitk.sitkVectorFloat64)
    t_field = Volume(sitk.GetArrayFromImage(warp), fixed.geometry)
    params = {"transform": "SyNOnly", "metric": "mattes", "seed": seed}
    return _finish("ants-syn", fixed, moving, initial, t_field, time.perf_counter() - t0, params)
