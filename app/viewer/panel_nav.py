"""The panel's navigation and inspection widgets: scan stepping, play/pause, camera fit and follow, the
enlarged image toggle, the Inspect section (a clicked voxel) and the per-class confidence histograms.

Built by :class:`app.viewer.panel.ReviewPanel` (one call); the same session methods are reached from the
page's keys through :mod:`app.api.routes.viewer_nav`. Every class name goes through ``html.escape``.
"""

from __future__ import annotations

import html
import itertools
import threading
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt
import viser

from app.viewer.records import CorrectionRecord, Inspection, ObjectInfo
from app.viewer.session import ReviewSession

BROWSE = ("◀ Previous", "Play", "Next ▶")
"""Options of the "Browse" button group (the middle one reads "Pause" while playing)."""
FIT = ("Scan", "Map")
"""Options of the "Fit view" button group."""
_CLIP = "overflow:hidden;text-overflow:ellipsis;white-space:nowrap"


def _hex(rgb: Sequence[int] | npt.NDArray[np.uint8]) -> str:
    r, g, b = (int(v) for v in rgb)
    return f"#{r:02x}{g:02x}{b:02x}"


def _swatch(rgb: Sequence[int] | npt.NDArray[np.uint8]) -> str:
    return (
        f'<span style="display:inline-block;width:10px;height:10px;border-radius:2px;'
        f'background:{_hex(rgb)};margin-right:4px"></span>'
    )


ERASE_OPTION = "(erase: unlabeled)"
"""The object class picker's entry that erases the object to unlabeled."""


def object_html(found: ObjectInfo, names: Sequence[str]) -> str:
    """The Inspect section's object line: track id, class, scans seen, moving or not and speed."""

    def name(i: int) -> str:
        return "unlabeled" if i < 0 else html.escape(names[i] if i < len(names) else f"class {i}")

    motion = f"<b>moving</b> at {found.speed:.1f} m/s" if found.moving else f"static ({found.speed:.1f} m/s)"
    scans = "scan" if found.scans == 1 else "scans"
    fixed = "" if found.corrected_to is None else f"; relabelled to <b>{name(found.corrected_to)}</b>"
    return (
        f'<div class="leap-object" style="font-size:12px;margin-bottom:4px">Object <b>{found.track}</b>: '
        f"<b>{name(found.class_index)}</b>{fixed}; seen in <b>{found.scans}</b> {scans}, {motion}; "
        f"{found.points:,} points in scan {html.escape(found.frame_id)}.</div>"
    )


def distribution_html(
    found: Inspection, names: Sequence[str], palette: npt.ArrayLike, *, top: int = 6
) -> str:
    """The Inspect section: class distribution bars (the ``top`` most probable classes), shown class and
    confidence, number of scans that observed the voxel, and its correction history."""
    pal = np.asarray(palette, dtype=np.uint8).reshape(-1, 3)
    probs = np.asarray(found.probs, dtype=np.float64)
    order = [int(i) for i in np.argsort(-probs, kind="stable")[:top]]
    bars = []
    for i in order:
        name = html.escape(names[i] if i < len(names) else f"class {i}")
        p = float(probs[i])
        colour = _hex(pal[i]) if i < pal.shape[0] else "#888888"
        bars.append(
            '<div class="leap-dist-row" style="display:flex;align-items:center;gap:6px;font-size:12px">'
            f'<span style="width:96px;{_CLIP}">{name}</span>'
            '<span style="flex:1;background:#eee;height:10px;border-radius:2px">'
            f'<span style="display:block;width:{100.0 * p:.1f}%;height:10px;border-radius:2px;'
            f'background:{colour}"></span></span>'
            f'<span style="width:34px;text-align:right">{p:.2f}</span></div>'
        )
    if found.label >= 0:
        shown = html.escape(names[found.label] if found.label < len(names) else f"class {found.label}")
    else:
        shown = "unlabeled"
    how = "corrected" if found.corrected else f"confidence {found.conf:.2f}"
    x, y, z = found.centre
    scans = "scan" if found.views == 1 else "scans"
    lines = [
        f'<div style="font-size:12px;margin-bottom:4px">Voxel at ({x:.1f}, {y:.1f}, {z:.1f}) m: '
        f"<b>{shown}</b> ({how}); observed by <b>{found.views}</b> {scans}.</div>",
        *bars,
        history_html(found.history),
    ]
    return "".join(lines)


def history_html(history: Sequence[CorrectionRecord]) -> str:
    """The corrections that include a voxel, oldest first: when, class, active or undone."""
    if not history:
        return '<div style="font-size:12px;margin-top:4px">No corrections include this voxel.</div>'
    rows = []
    for rec in history:
        when = html.escape(rec.created_at.replace("T", " ")[:19]) if rec.created_at else "-"
        what = html.escape(rec.class_name) if rec.class_name else "unlabeled (erase)"
        state = "active" if rec.active else "undone"
        rows.append(f"<tr><td>{when}</td><td>{what}</td><td>{state}</td></tr>")
    return (
        '<div style="font-size:12px;margin-top:4px">Corrections of this voxel:</div>'
        '<table style="font-size:12px;border-collapse:collapse;width:100%">'
        "<tr><th align=left>when (UTC)</th><th align=left>class</th><th align=left>state</th></tr>"
        f"{''.join(rows)}</table>"
    )


def histogram_html(hist: npt.NDArray[np.int64], names: Sequence[str], palette: npt.ArrayLike) -> str:
    """Per class (rows with at least one voxel), a small bar chart of its voxels' confidence bins
    (:func:`app.viewer.nav_logic.confidence_histograms`), bars scaled to the class's largest bin."""
    pal = np.asarray(palette, dtype=np.uint8).reshape(-1, 3)
    rows = []
    for c in range(hist.shape[0]):
        counts = hist[c]
        total = int(counts.sum())
        if total == 0:
            continue
        peak = float(counts.max())
        colour = _hex(pal[c]) if c < pal.shape[0] else "#888888"
        bars = "".join(
            f'<span title="{int(n):,}" style="display:inline-block;width:7px;margin-right:1px;'
            f"height:{max(1.0, 16.0 * float(n) / peak):.0f}px;background:{colour};"
            'vertical-align:bottom"></span>'
            for n in counts
        )
        name = html.escape(names[c] if c < len(names) else f"class {c}")
        rows.append(
            '<div style="display:flex;align-items:flex-end;gap:6px;font-size:12px">'
            f'<span style="width:110px;{_CLIP}">{name}</span>'
            f'<span style="height:16px;white-space:nowrap">{bars}</span>'
            f'<span style="opacity:0.7">{total:,}</span></div>'
        )
    head = (
        '<div style="font-size:11px;opacity:0.7;margin-bottom:2px">Voxels per confidence bin, 0 → 1 '
        f"({hist.shape[1]} bins), per shown class</div>"
    )
    return head + "".join(rows)


class NavPanel:
    """Navigation widgets in the Scan folder, the Inspect folder and the confidence histogram folder."""

    def __init__(
        self,
        session: ReviewSession,
        gui: viser.GuiApi,
        scan_folder: viser.GuiFolderHandle,
        guard: Callable[[Callable[..., Any]], Callable[..., Any]],
    ) -> None:
        self.s = session
        with scan_folder:
            self.browse = gui.add_button_group("Browse", BROWSE, order=-3)
            self.fit = gui.add_button_group("Fit view", FIT, order=-2)
            self.follow = gui.add_checkbox(
                "Follow ego",
                session.player.follow_ego,
                order=-1,
                hint="Move the camera behind the ego vehicle on every scan change (key G)",
            )
            self.enlarge = gui.add_button("Enlarge image", hint="Show the image across the view (key I)")
        # Right under Run: a click's answer shows without scrolling, whatever else is expanded.
        self.inspect_folder = gui.add_folder("Inspect", order=0.5, expand_by_default=True, visible=False)
        with self.inspect_folder:
            self.object_info = gui.add_html("", visible=False)
            self.object_class = gui.add_dropdown("Object class", ["-"], initial_value="-", visible=False)
            self.relabel_object = gui.add_button(
                "Relabel object",
                visible=False,
                hint="Give the class to every point of this object in every scan (one object correction)",
            )
            self.split_object = gui.add_button(
                "Split here",
                visible=False,
                hint="The tracker carried this id onto another object: give its points from the scan shown "
                "on a new id (one object correction)",
            )
            self.merge_with = gui.add_number(
                "Merge with",
                0,
                min=0,
                max=0xFFFF,
                step=1,
                visible=False,
                hint="The id of another object (colour by objects, click it to read its id) that is part of "
                "this one",
            )
            self.merge_object = gui.add_button(
                "Merge into this object",
                visible=False,
                hint="The object 'Merge with' names becomes part of this one: one id and this object's class "
                "in every scan (one object correction)",
            )
            self.inspect = gui.add_html("")
        with gui.add_folder("Confidence by class", order=7, expand_by_default=False):
            self.histogram = gui.add_html("")

        s, player = session, session.player
        self.browse.on_click(guard(lambda e: self._browse(str(e.target.value))))
        self.fit.on_click(
            guard(lambda e: player.fit_scan() if e.target.value == "Scan" else player.fit_map())
        )
        self.follow.on_update(guard(lambda _: self._follow_changed()))
        self.enlarge.on_click(guard(lambda _: player.set_image_open(None)))
        s.scene.on_click(guard(self._clicked))
        self.relabel_object.on_click(guard(lambda _: self._relabel_object()))
        self.split_object.on_click(guard(lambda _: session.corrections.split_object()))
        self.merge_object.on_click(guard(lambda _: self._merge_object()))

    def _browse(self, option: str) -> None:
        if option == BROWSE[0]:
            self.s.player.step_scan(-1)
        elif option == BROWSE[2]:
            self.s.player.step_scan(1)
        else:
            self.s.player.set_playing(None)

    def _follow_changed(self) -> None:
        if bool(self.follow.value) != self.s.player.follow_ego:
            self.s.player.set_follow(bool(self.follow.value))

    def _clicked(self, event: viser.SceneClickEvent) -> None:
        self.s.tools.inspect_ray(event.ray_origin, event.ray_direction)

    # ---------------------------------------------------------------------------- session → panel
    def on_nav(self) -> None:
        s = self.s.player
        options = (BROWSE[0], "Pause" if s.playing else BROWSE[1], BROWSE[2])
        if tuple(self.browse.options) != options:
            self.browse.options = options
        if bool(self.follow.value) != s.follow_ego:
            self.follow.value = s.follow_ego  # type: ignore[misc]  # viser: split setter (see panel.py)
        label = "Shrink image" if s.image_open else "Enlarge image"
        if self.enlarge.label != label:
            self.enlarge.label = label

    def _relabel_object(self) -> None:
        chosen = str(self.object_class.value)
        self.s.corrections.relabel_object("" if chosen == ERASE_OPTION else chosen)

    def _merge_object(self) -> None:
        other = int(self.merge_with.value)
        if other < 1:
            raise ValueError("Merge with: type the id of the other object (colour by objects, click it)")
        self.s.corrections.merge_object(other)

    def on_run_loaded(self, names: Sequence[str]) -> None:
        """A run was loaded: the object class picker offers its classes (and erasing)."""
        options = [*names, ERASE_OPTION]
        self.object_class.options = options
        if self.object_class.value not in options:
            self.object_class.value = options[0]  # type: ignore[misc]  # viser: split setter (see panel.py)
        self.on_object(None)

    def on_object(self, found: ObjectInfo | None) -> None:
        """Show the clicked point's object (or hide the object widgets: no object was hit)."""
        shown = found is not None
        for widget in (
            self.object_info,
            self.object_class,
            self.relabel_object,
            self.split_object,
            self.merge_with,
            self.merge_object,
        ):
            widget.visible = shown
        if found is None:
            return
        self.object_info.content = object_html(found, self.s.class_names())
        self.inspect_folder.visible = True

    def on_inspect(self, found: Inspection) -> None:
        self.inspect.content = distribution_html(found, self.s.class_names(), self.s.palette)
        self.inspect_folder.visible = True

    _histogram_runs = itertools.count()
    _histogram_latest = 0

    def update_histogram(self) -> None:
        """Recount the confidence histograms: at once for a map drawn exactly, on a thread for a big one (a
        pass over every voxel, which must not hold up its first draw or a correction)."""
        run = self._histogram_latest = next(self._histogram_runs)
        if self.s.renderer.lod_index is None:
            self._fill_histogram(run)
        else:
            fill = threading.Thread(target=self._fill_histogram, args=(run,), name="viewer-histogram")
            fill.daemon = True
            fill.start()

    def _fill_histogram(self, run: int) -> None:
        s = self.s
        content = histogram_html(s.shared.confidence_histograms(), s.class_names(), s.palette)
        if run == self._histogram_latest:  # a later recount has started: its result wins
            self.histogram.content = content


__all__ = [
    "BROWSE",
    "ERASE_OPTION",
    "FIT",
    "NavPanel",
    "distribution_html",
    "histogram_html",
    "history_html",
    "object_html",
]
