"""``workbench bones``: the template's bone label map, given or segmented from seeds (the bones stage)."""

from __future__ import annotations

from pathlib import Path

from workbench.cli.options import add_bones_options, add_common
from workbench.cli.running import read_output, run_study_stages


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "bones",
        help="the template's bone label map: given, or segmented from seeds",
        description="The bones stage (Rhee §3.1): the study's own label map, or one segmented "
        "from a seeds file (CT: threshold and connected components; MRI: each "
        "bone's marrow flooded from its seeds inside the dark cortex), and each bone's oriented box.  Writes "
        "bones/; every later "
        "stage uses these labels.  The seeds schema is in `workbench pose --help`.",
    )
    p.add_argument("study", type=Path, help="study folder (holding study.json)")
    add_bones_options(p)
    p.add_argument("--force", action="store_true", help="rerun even when up to date")
    add_common(p)
    p.set_defaults(func=handle)


def handle(args) -> int:
    from workbench.stages.bones import BonesSettings
    from workbench.stages.run import bones_settings

    bs = bones_settings(vars(args)) or BonesSettings(source="auto")
    study, _ = run_study_stages(args, ["bones"], {"bones": bs}, force={"bones"} if args.force else ())
    counts = read_output(study, "bones", "bones.json")
    print(f"bones ({counts['source']}): " + ", ".join(f"{b} {n}" for b, n in counts["voxels"].items()) + " voxels")
    print(f"wrote {study.root / 'bones'}")
    return 0
