"""``leap import ...``: convert recordings (ROS bags, nuScenes) into the KITTI layout the pipeline reads.

The conversion itself lives in ``leap_core.importers``; these commands parse options, show progress and
turn errors into one-line messages.
"""

from __future__ import annotations

import typer

import_cli = typer.Typer(
    name="import",
    help="Convert a recording (ROS 1/2 bag, nuScenes) into a KITTI-layout sequence folder.",
    no_args_is_help=True,
)
