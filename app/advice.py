"""How to fix what the pre-flight check finds, worded for where it is shown: the ``leap`` command line (it
may name ``leap`` commands and flags) or the web app (it names the app's own options, never a command-line
flag).

The check itself (:mod:`leap_core.pipeline.preflight`) reports neutral findings: a code, the file and what
is wrong. :data:`ADVICE` holds each code's fix for both places; :func:`render_cli` prints a whole report as
``leap check`` does, and :func:`report_dict` is the structured report the app sends (and ``leap check
--json`` prints), with the fixes in the audience's words.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any, Literal

from leap_core.pipeline.preflight import (
    DatasetReport,
    Finding,
    FrameCoverage,
    Verdict,
    alternative_labeler,
    describe,
    reason_text,
    report_data,
    stage_line,
    summary_text,
)

Audience = Literal["cli", "app"]


@dataclass(frozen=True)
class Advice:
    """How to fix one finding code, worded for each place it is shown."""

    cli: str
    """For the command line: may name ``leap`` commands and flags. ``{seq}`` = the sequence folder."""
    app: str
    """For the web app: names the app's own options; never a command-line flag."""
    setting: str = ""
    """The project setting the app's fix changes, as the web UI names it ('' when the fix is not a
    setting). Resume keeps a run's own settings, so a run that failed on one needs a new run instead."""


POSES_SETTING = "Estimate poses (KISS-ICP)"
LABELER_SETTING = "2D labeler"

ADVICE: dict[str, Advice] = {
    "not_a_folder": Advice(
        "give the path of a sequence folder (…/sequences/NN)",
        "pick an existing sequence folder inside a data root",
    ),
    "not_a_sequence": Advice(
        "give a KITTI sequence folder, the one holding velodyne/ (e.g. …/sequences/00)",
        "pick a KITTI sequence folder, the one holding velodyne/ (e.g. …/sequences/00)",
    ),
    "no_scans": Advice(
        "add the LiDAR scans as velodyne/NNNNNN.bin (float32 x, y, z, remission)",
        "add the LiDAR scans as velodyne/NNNNNN.bin (float32 x, y, z, remission)",
    ),
    "scans_damaged": Advice(
        "replace the damaged scans",
        "replace the damaged scans",
    ),
    "calib_missing": Advice(
        "write calib.txt with a 'P2:' line (the colour camera's 3×4 projection) and a 'Tr:' line (the 3×4 "
        "LiDAR→camera transform)",
        "add calib.txt to the dataset, with a 'P2:' line (the colour camera's 3×4 projection) and a 'Tr:' "
        "line (the 3×4 LiDAR→camera transform)",
    ),
    "calib_invalid": Advice(
        "fix calib.txt ('P2:' and 'Tr:', 12 numbers each)",
        "fix calib.txt in the dataset ('P2:' and 'Tr:', 12 numbers each)",
    ),
    "unreadable": Advice(
        "fix the file named above",
        "fix the file named above in the dataset",
    ),
    "linked_outside": Advice(
        "replace each link with a copy of the file it points to, or link the whole folder instead of its "
        "files (the pipeline reads no file linked out of the sequence folder)",
        "replace each link with a copy of the file it points to (the app reads no file linked out of the "
        "sequence folder)",
    ),
    "not_a_file": Advice(
        "put the file itself in place of each entry named (or remove the entry)",
        "put the file itself in place of each entry named in the dataset (or remove the entry)",
    ),
    "images_damaged": Advice(
        "replace the damaged images (a complete PNG or JPEG each)",
        "replace the damaged images in the dataset's image_2/ folder (a complete PNG or JPEG each)",
    ),
    "images_size": Advice(
        "give every image the size the calibration (calib.txt P2) was made for",
        "give every image in the dataset's image_2/ folder the size the calibration (calib.txt P2) was "
        "made for",
    ),
    "no_2d_input": Advice(
        "add camera images as image_2/NNNNNN.png (or .jpg) for --labeler grounded-sam",
        "add camera images as image_2/NNNNNN.png (or .jpg) to the dataset for the "
        "Grounding DINO + SAM labeler",
    ),
    "images_missing": Advice(
        "add camera images as image_2/NNNNNN.png (or .jpg) to use --labeler grounded-sam",
        "add camera images as image_2/NNNNNN.png (or .jpg) to the dataset to use the "
        "Grounding DINO + SAM labeler",
    ),
    "images_partial": Advice(
        "add the missing images, or label only frames that have one (--frames A:B)",
        "add the missing images to the dataset's image_2/ folder",
    ),
    "gt2d_missing": Advice(
        "",
        "",
    ),
    "gt2d_partial": Advice(
        "add the missing gt2d/semantic and gt2d/instance masks, or use --labeler grounded-sam",
        "add the missing 2D ground-truth masks, or choose the Grounding DINO + SAM labeler under Parameters",
        setting=LABELER_SETTING,
    ),
    "labels_missing": Advice(
        "",
        "",
    ),
    "labels_partial": Advice(
        "add the missing labels/NNNNNN.label files (evaluation needs one per scan)",
        "add the missing labels/NNNNNN.label files to the dataset (evaluation needs one per scan)",
    ),
    "poses_missing": Advice(
        "estimate them with `leap poses {seq}` (KISS-ICP LiDAR odometry), or add --estimate-poses to "
        "`leap run`",
        'turn on "Estimate poses (KISS-ICP)" (on the project page, or when creating the project), or add '
        "a poses.txt to the dataset",
        setting=POSES_SETTING,
    ),
    "poses_will_estimate": Advice(
        "",
        "",
    ),
    "poses_invalid": Advice(
        "fix or remove poses.txt, then estimate poses with `leap poses {seq} --force`",
        "fix or remove the dataset's poses.txt, then create the project with \"Estimate "
        'poses (KISS-ICP)" ticked',
        setting=POSES_SETTING,
    ),
    "poses_unreadable": Advice(
        "fix or remove poses.txt (then `leap poses {seq}` estimates new ones)",
        "fix or remove the dataset's poses.txt, then create the project with "
        '"Estimate poses (KISS-ICP)" ticked',
        setting=POSES_SETTING,
    ),
    "poses_short": Advice(
        "poses.txt needs one line per frame number: add the missing lines, or estimate "
        "poses with `leap poses {seq} --force`",
        "poses.txt needs one line per frame number: add the missing lines, or remove it "
        'and create the project with "Estimate poses (KISS-ICP)" ticked',
        setting=POSES_SETTING,
    ),
    "poses_extra": Advice(
        "",
        "",
    ),
    "poses_estimated": Advice(
        "",
        "",
    ),
    "models_missing": Advice(
        "pass --models DIR holding the folders named above (README 'Real 2D labels'); "
        "`leap make-tiny-models DIR` writes random-weight stand-ins to try the code path",
        "the server needs a models folder holding the folders named above: whoever runs it "
        "sets it (LEAP_MODELS_DIR) and restarts it",
    ),
    "models_random": Advice(
        "use real weights (README 'Real 2D labels')",
        "the server's models folder holds test models with random weights: ask whoever "
        "runs it for real weights",
    ),
    "labeler_cannot_run": Advice(
        "use --labeler {alt}",
        'choose "{alt_label}" as the 2D labeler under Parameters',
        setting=LABELER_SETTING,
    ),
    "off": Advice(
        "",
        "",
    ),
}
"""Every finding code (``leap_core.pipeline.preflight.REASONS``) with its fix for the command line and for
the app ('' where there is nothing to do)."""


def advice(finding: Finding, audience: Audience, report: DatasetReport) -> str:
    """The fix for ``finding`` worded for the command line or the app ('' when there is nothing to do)."""
    entry = ADVICE.get(finding.code)
    if entry is None:
        return ""
    text = entry.cli if audience == "cli" else entry.app
    if finding.code == "labeler_cannot_run":
        alt = alternative_labeler(report)
        if alt is None:
            return (
                "fix the problems listed for the labelers"
                if audience == "cli"
                else ("fix the problems listed for the 2D labelers")
            )
        return text.format(alt=alt.name, alt_label=alt.label)
    return text.format(seq=report.root)


def setting_fix(error: str | None) -> str | None:
    """The project setting a run's error says to change (its advice's :attr:`Advice.setting`), or None
    when the error carries no such advice. A run's error holds the app's advice verbatim (the worker and
    the job manager append it), so the longest fixed part of each advice text is looked for in it."""
    if not error:
        return None
    for entry in ADVICE.values():
        if entry.setting and entry.app:
            fixed = max(re.split(r"\{[^}]*\}", entry.app), key=len)
            if fixed and fixed in error:
                return entry.setting
    return None


def _coverage_line(cover: FrameCoverage, what: str) -> str:
    return f"{cover.present} of {cover.total} scans have {what}"


def render_cli(report: DatasetReport, exit_codes: dict[Verdict, int] | None = None) -> str:
    """The report as ``leap check`` prints it (advice names commands and flags)."""
    lines = [f"dataset   {report.root}"]
    if report.frames:
        plural = "s" if report.frames != 1 else ""
        lines.append(f"frames    {report.frames} scan{plural} ({report.first_frame} … {report.last_frame})")
        lines.append(f"images    {_coverage_line(report.images, 'a camera image (image_2/)')}")
        cal = report.calib
        lines.append(
            "calib     "
            + ("calib.txt: P2 and Tr read" if cal.valid else f"calib.txt: {cal.problem or 'missing'}")
        )
        p = report.poses
        pose_text = {
            "file": f"poses.txt, {p.lines} poses",
            "estimated": f"poses.txt, {p.lines} poses, estimated ({p.method or 'method not recorded'})",
            "missing": "missing (no poses.txt)",
            "invalid": "poses.txt cannot be read",
            "will-estimate": "missing: estimated before the 3D stages",
        }[p.source]
        lines.append(f"poses     {pose_text}")
        lines.append(
            f"labels    {report.ground_truth.kind}: "
            f"{_coverage_line(report.ground_truth, 'ground truth (labels/)')}"
        )
        gt2d = _coverage_line(report.gt2d, "2D ground truth (gt2d/)")
        lines.append(f"gt2d      {report.gt2d.kind}: {gt2d}")
        if len(report.cameras) > 1:
            lines.append(f"cameras   {len(report.cameras)}, each painting the points in its view")
            for cam in report.cameras:
                lines.append(
                    f"  {cam.name:<14} {cam.source}; {cam.images.present} of {cam.images.total} scans have "
                    f"its image, {cam.gt2d.present} its 2D ground truth"
                )
        lines.append("")
        lines.append("labelers")
        for lab in report.labelers:
            why = ", ".join(map(reason_text, lab.reasons))
            state = "can run" if lab.can_run else f"cannot run ({why})"
            lines.append(f"  {lab.name:<14} {state}")
        how = "" if report.labeler_chosen else ", picked by the check; --labeler picks another"
        lines.append("")
        lines.append(f"stages (labeler {report.labeler}{how})")
        for st in report.stages:
            lines.append(f"  {st.name:<14} {stage_line(st)}")
    order = {"blocker": 0, "warning": 1, "info": 2}
    if report.findings:
        lines.append("")
        lines.append("findings")
    for f in sorted(report.findings, key=lambda f: order[f.severity]):
        lines.append(f"  {f.severity:<8} {describe(f)}")
        fix = advice(f, "cli", report) if f.severity != "info" else ""
        if fix:
            lines.append(f"           fix: {fix}")
    lines.append("")
    code = f" (exit code {exit_codes[report.verdict]})" if exit_codes else ""
    lines.append(f"verdict: {summary_text(report)}{code}")
    return "\n".join(lines)


def report_dict(report: DatasetReport, audience: Audience) -> dict[str, Any]:
    """The report as plain JSON-able data (``leap_core.pipeline.preflight.report_data``), each finding
    with its ``fix`` worded for ``audience`` (the app sends ``"app"``)."""
    data = report_data(report)
    data["findings"] = [
        {**entry, "fix": advice(f, audience, report)}
        for entry, f in zip(data["findings"], report.findings, strict=True)
    ]
    return data


__all__ = [
    "ADVICE",
    "LABELER_SETTING",
    "POSES_SETTING",
    "Advice",
    "Audience",
    "advice",
    "render_cli",
    "report_dict",
    "setting_fix",
]
