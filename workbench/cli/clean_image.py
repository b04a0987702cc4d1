"""``workbench clean-image``: a copy of an image with its NaN and infinite voxels replaced."""

from __future__ import annotations

from pathlib import Path


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "clean-image",
        help="replace an image's NaN and infinite voxels (a copy; the input is kept)",
        description="Write a copy of an image whose NaN and infinite voxels are replaced by a value "
        "(default: the lowest finite value of the image, i.e. background), with the "
        "same geometry. The workbench refuses images with such voxels.",
    )
    p.add_argument("image", type=Path, help="the image (.nii.gz, .mha, .nrrd, a DICOM folder)")
    p.add_argument("--out", required=True, type=Path, help="the cleaned copy")
    p.add_argument(
        "--value", type=float, default=None, help="the value for the bad voxels (default: the lowest finite value)"
    )
    p.add_argument("--force", action="store_true", help="replace an existing --out")
    p.set_defaults(func=handle)


def handle(args) -> int:
    from workbench.io.nonfinite import clean_image

    s = clean_image(args.image, args.out, value=args.value, overwrite=args.force)
    print(f"{s['replaced']} of {s['voxels']} voxels replaced by {s['fill']:g}; wrote {args.out}")
    return 0
