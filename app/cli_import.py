"""``leap import ...``: convert recordings (ROS bags, nuScenes) into the KITTI layout the pipeline reads.

The conversion itself lives in ``leap_core.importers``; these commands parse options, show progress and
turn errors into one-line messages.
"""

from __future__ import annotations

from pathlib import Path

import typer
from tqdm import tqdm

from leap_core.errors import LeapError

import_cli = typer.Typer(
    name="import",
    help="Convert a recording (ROS 1/2 bag, nuScenes) into a KITTI-layout sequence folder.",
    no_args_is_help=True,
)


@import_cli.command("nuscenes")
def nuscenes_cmd(
    dataroot: str = typer.Argument(..., help="nuScenes folder (holding samples/, v1.0-mini/, lidarseg/)."),
    *,
    version: str = typer.Option("v1.0-mini", "--version", help="Table folder: v1.0-mini, v1.0-trainval, ..."),
    scene: str = typer.Option(..., "--scene", help="Scene name, e.g. scene-0061."),
    camera: str = typer.Option(
        "CAM_FRONT", "--camera", help="Camera channel whose keyframe images are used."
    ),
    out: str | None = typer.Option(
        None, "--out", help="Sequence folder to write (default: data/nuscenes/<scene>)."
    ),
    force: bool = typer.Option(False, "--force", help="Replace a previous import in --out."),
) -> None:
    """Write one nuScenes scene's LIDAR_TOP keyframes, camera images, calibration, ego poses and
    lidarseg labels as a KITTI-layout sequence (label it with --project-file projects/nuscenes.yaml)."""
    from app.cli import fail  # app.cli imports this module
    from leap_core.importers.nuscenes import import_nuscenes  # loads the devkit (matplotlib, sklearn)

    target = Path(out) if out is not None else Path("data") / "nuscenes" / scene
    bar: tqdm[None] | None = None

    def loaded(total: int) -> None:
        nonlocal bar
        bar = tqdm(total=total, desc="nuscenes", unit="frame", dynamic_ncols=True)

    def progress(done: int, total: int) -> None:
        if bar is not None:
            bar.total, bar.n = total, done
            bar.refresh()

    typer.echo(f"reading the {version} tables of {dataroot} (nuscenes-devkit)")
    try:
        summary = import_nuscenes(
            dataroot,
            target,
            version=version,
            scene=scene,
            camera=camera,
            force=force,
            progress=progress,
            on_loaded=loaded,
        )
    except KeyboardInterrupt:
        raise fail(f"interrupted; nothing was written to {target}") from None
    except LeapError as exc:
        raise fail(str(exc)) from None
    finally:
        if bar is not None:
            bar.close()
    typer.echo(summary.line())
