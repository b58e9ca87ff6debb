"""``leap import ...``: convert recordings (ROS bags, nuScenes) into the KITTI layout the pipeline reads.

The conversion itself lives in ``leap_core.importers``; these commands parse options, show progress and
turn errors into one-line messages.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer
from tqdm import tqdm

from leap_core.errors import Cancelled, LeapError

import_cli = typer.Typer(
    name="import",
    help="Convert a recording (ROS 1/2 bag, nuScenes) into a KITTI-layout sequence folder.",
    no_args_is_help=True,
)


def _fail(message: str) -> typer.Exit:
    """Print a one-line error to stderr and return the exit to raise (as ``app.cli.fail``, which imports
    this module)."""
    typer.secho(f"error: {message}", err=True, fg=typer.colors.RED)
    return typer.Exit(code=2)


class _Bar:
    """A tqdm bar opened at the first ``progress(done, total)`` call (a refusal prints only the error)."""

    def __init__(self, desc: str, unit: str) -> None:
        self.desc, self.unit = desc, unit
        self.bar: Any = None

    def __call__(self, done: int, total: int) -> None:
        if self.bar is None:
            self.bar = tqdm(total=total, desc=self.desc, unit=self.unit, dynamic_ncols=True)
        self.bar.total = total
        self.bar.update(done - self.bar.n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


@import_cli.command("rosbag")
def rosbag_cmd(  # noqa: PLR0913  # typer: one parameter per command-line option
    bag: str = typer.Argument(..., help="ROS 1 .bag file, or ROS 2 bag folder (or its .db3 / .mcap file)."),
    *,
    lidar_topic: str = typer.Option(..., "--lidar-topic", help="sensor_msgs/PointCloud2 topic."),
    camera_topic: list[str] = typer.Option(
        ...,
        "--camera-topic",
        help="sensor_msgs/Image or sensor_msgs/CompressedImage topic; repeat it for a rig of cameras (the "
        "first is image_2, the others are calibrated from the bag's CameraInfo and /tf_static).",
    ),
    calib: str | None = typer.Option(
        None,
        "--calib",
        help="Calibration YAML (docs/IMPORT.md) or KITTI calib.txt; default: the bag's CameraInfo + "
        "/tf_static.",
    ),
    out: str | None = typer.Option(
        None, "--out", help="Sequence folder to write (default data/<bag name>/sequences/00)."
    ),
    max_offset_ms: float = typer.Option(
        50.0,
        "--max-offset-ms",
        help="Largest scan-to-camera stamp difference; scans without a partner are dropped.",
    ),
    camera_info_topic: str | None = typer.Option(
        None,
        "--camera-info-topic",
        help="sensor_msgs/CameraInfo topic (default: the one of the images' frame).",
    ),
    fixed_frame: str | None = typer.Option(
        None,
        "--fixed-frame",
        help="/tf frame the poses are taken in (default: the root of the LiDAR's tree).",
    ),
    force: bool = typer.Option(False, "--force", help="Replace a non-empty output folder."),
) -> None:
    """Convert a ROS bag (ROS 1, ROS 2 sqlite3 or mcap) into a KITTI sequence folder: scans paired with the
    nearest camera frame, calib.txt, times.txt, and poses.txt when /tf moves the LiDAR frame."""
    # rosbags and scipy load with the command that needs them, not with `leap --help`.
    try:
        from leap_core.importers.rosbag import RosbagImportConfig, import_rosbag
    except LeapError as exc:  # MissingExtra: rosbags is not installed
        raise _fail(str(exc)) from None

    bag_path = Path(bag)
    name = bag_path.parent.name if bag_path.suffix in (".db3", ".mcap", ".yaml") else bag_path.stem
    target = Path(out) if out is not None else Path("data") / (name or "rosbag") / "sequences" / "00"
    bar = _Bar("import", "msg")
    try:
        cfg = RosbagImportConfig(
            lidar_topic=lidar_topic,
            camera_topic=camera_topic[0],
            more_camera_topics=tuple(camera_topic[1:]),
            camera_info_topic=camera_info_topic,
            calib_file=None if calib is None else Path(calib),
            max_offset_ms=max_offset_ms,
            fixed_frame=fixed_frame,
        )
        summary = import_rosbag(bag_path, target, cfg, force=force, progress=bar)
    except (KeyboardInterrupt, Cancelled):
        bar.close()
        raise _fail("interrupted; nothing was written") from None
    except LeapError as exc:
        bar.close()
        raise _fail(str(exc)) from None
    bar.close()
    line = summary.line()
    if summary.pose_source is None:
        line += f": estimate them with `leap poses {target}` or run with `leap run --estimate-poses`"
    typer.echo(line)


@import_cli.command("nuscenes")
def nuscenes_cmd(
    dataroot: str = typer.Argument(..., help="nuScenes folder (holding samples/, v1.0-mini/, lidarseg/)."),
    *,
    version: str = typer.Option("v1.0-mini", "--version", help="Table folder: v1.0-mini, v1.0-trainval, ..."),
    scene: str = typer.Option(..., "--scene", help="Scene name, e.g. scene-0061."),
    camera: str = typer.Option(
        "CAM_FRONT",
        "--camera",
        help="Camera channel whose keyframe images are used; several separated by commas, or all: a rig.",
    ),
    out: str | None = typer.Option(
        None, "--out", help="Sequence folder to write (default: data/nuscenes/<scene>)."
    ),
    force: bool = typer.Option(False, "--force", help="Replace a previous import in --out."),
) -> None:
    """Write one nuScenes scene's LIDAR_TOP keyframes, camera images, calibration, ego poses and
    lidarseg labels as a KITTI-layout sequence (label it with --project-file nuscenes)."""
    try:
        from leap_core.importers.nuscenes import import_nuscenes  # loads the devkit (matplotlib, sklearn)
    except LeapError as exc:  # MissingExtra: the devkit or one of its imports is not installed
        raise _fail(str(exc)) from None

    target = Path(out) if out is not None else Path("data") / "nuscenes" / scene
    typer.echo(f"reading the {version} tables of {dataroot} (nuscenes-devkit)")
    bar = _Bar("nuscenes", "frame")
    try:
        summary = import_nuscenes(
            dataroot, target, version=version, scene=scene, camera=camera, force=force, progress=bar
        )
    except (KeyboardInterrupt, Cancelled):
        bar.close()
        raise _fail(f"interrupted; nothing was written to {target}") from None
    except LeapError as exc:
        bar.close()
        raise _fail(str(exc)) from None
    bar.close()
    typer.echo(summary.line())
