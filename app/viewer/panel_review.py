"""The panel's "Review queue" folder: rank regions, step through them, accept / skip / relabel.

Built by :class:`app.viewer.panel.ReviewPanel` inside its folder; the same actions are reachable from the
viewer page's keys (web/viewer/review.js through app/api/routes/viewer_review.py).
"""

from __future__ import annotations

import html
import threading
from typing import TYPE_CHECKING, Any

from app.viewer.object_queue import QueuedObject
from app.viewer.records import ObjectInfo, QueueKind, SessionConfig
from app.viewer.region_logic import Region
from leap_core.bounds import bounds_rows

if TYPE_CHECKING:
    from app.viewer.panel import ReviewPanel

SESSION_BOUNDS = dict(bounds_rows(SessionConfig))
QUEUE_KINDS = ("lowest confidence", "camera vs final disagreement")
QUEUE_OF: dict[str, QueueKind] = {
    "lowest confidence": "confidence",
    "camera vs final disagreement": "disagreement",
}
STATE_TEXT = {"accepted": "accepted", "skipped": "skipped", None: "not reviewed"}


def progress_text(progress: dict[str, int]) -> str:
    """``"12 / 100 reviewed"`` (and the skipped count when there are any)."""
    text = f"{progress['reviewed']} / {progress['total']} reviewed"
    return f"{text}, {progress['skipped']} skipped" if progress.get("skipped") else text


class ReviewQueuePanel:
    """Widgets of the review queue (call inside the panel's "Review queue" folder)."""

    def __init__(self, panel: ReviewPanel) -> None:
        self.p = panel
        q, gui, g = panel.s.queue, panel.gui, panel.guard
        self.queue_kind = gui.add_dropdown("Order by", QUEUE_KINDS, initial_value=QUEUE_KINDS[0])
        self.next_button = gui.add_button("Next region", hint="Key: N")
        self.prev_button = gui.add_button("Previous region", hint="Key: P")
        self.accept_button = gui.add_button(
            "Accept region", hint="Mark reviewed and go on (key: A)", color="green", disabled=True
        )
        self.skip_button = gui.add_button(
            "Skip region", hint="Mark skipped and go on (key: S)", disabled=True
        )
        self.relabel_class = gui.add_dropdown("Relabel as", ["-"], initial_value="-")
        self.relabel_button = gui.add_button(
            "Relabel region",
            hint="Assign the class to the highlighted voxels (key: R opens the class picker)",
            disabled=True,
        )
        self.leave_button = gui.add_button(
            "Leave review",
            hint="Undim the map and remove the region's box; Next region goes on from here (key: Esc)",
            disabled=True,
        )
        bound = SESSION_BOUNDS["queue_min_count"]
        self.min_count = gui.add_number(
            "Min region size",
            initial_value=q.min_count,
            min=int(bound.low),
            max=int(bound.high),
            step=1,
            hint="Regions need at least this many candidate voxels (smaller specks are left out)",
        )
        self.queue_info = gui.add_markdown("")
        self.progress = gui.add_markdown("")
        self.queue_kind.on_update(g(lambda _: self._in_background(self._build)))
        self.next_button.on_click(g(lambda _: self._in_background(lambda: self.step(1))))
        self.prev_button.on_click(g(lambda _: self._in_background(lambda: self.step(-1))))
        self.accept_button.on_click(g(lambda _: q.mark_region("accepted")))
        self.skip_button.on_click(g(lambda _: q.mark_region("skipped")))
        self.relabel_button.on_click(g(lambda _: q.relabel_region(str(self.relabel_class.value))))
        self.leave_button.on_click(g(lambda _: q.clear_focus()))
        self.min_count.on_update(g(lambda _: q.set_min_count(int(self.min_count.value))))

    def _in_background(self, fn: Any) -> None:
        # Ranking the disagreement queue reads every scan: keep viser's callback thread free meanwhile.
        threading.Thread(target=self.p.guard(fn), name="viewer-queue", daemon=True).start()

    def kind(self) -> QueueKind:
        return QUEUE_OF[str(self.queue_kind.value)]

    def _build(self) -> None:
        q = self.p.s.queue
        q.build_queue(self.kind())
        self.queue_info.content = f"{len(q.regions)} regions; press *Next region* (N)."

    def step(self, step: int) -> Region | None:
        """Show the next / previous region, ranking the chosen queue first when needed."""
        q = self.p.s.queue
        if not q.regions or q.queue_kind != self.kind() or not q.queue_built:
            q.build_queue(self.kind())
        region = q.next_region(step)
        if region is None:
            self.queue_info.content = "Nothing to review."
        return region

    def on_run_loaded(self, names: list[str]) -> None:
        self.relabel_class.options = names
        if self.relabel_class.value not in names:
            self.relabel_class.value = names[0]  # type: ignore[misc]  # viser: split setter (panel.py)
        self.progress.content = ""
        self._region_buttons(False)

    def _region_buttons(self, on: bool) -> None:
        for b in (self.accept_button, self.skip_button, self.relabel_button, self.leave_button):
            b.disabled = not on

    def on_focus_cleared(self) -> None:
        self._region_buttons(False)
        q = self.p.s.queue
        if q.regions:
            self.queue_info.content = "Left the review; press *Next region* (N) to go on."

    def on_queue(self, building: bool) -> None:
        for b in (self.next_button, self.prev_button):
            b.disabled = building
        self.queue_kind.disabled = building
        if building:
            self.queue_info.content = "⏳ Ranking regions…"
        else:
            self.progress.content = progress_text(self.p.s.queue.review_progress())

    def on_region(self, region: Region, pos: int, count: int, kind: str) -> None:
        s = self.p.s
        q = s.queue
        what = "mean confidence" if kind == "confidence" else "disagreement"
        unit = "voxels" if kind == "confidence" else "points"
        state = STATE_TEXT[q.region_state(pos)]
        seen = ""
        if q.focus_frame is not None and s.outputs is not None:
            fid = s.outputs.seq.frame_ids[s.outputs.frame_indices[q.focus_frame]]
            seen = f" Seen best in scan {html.escape(fid)} (boxed in the image)."
        self.queue_info.content = (
            f"Region {pos + 1}/{count}: about **{region.expected_wrong:.0f}** {unit} expected wrong; {what} "
            f"{region.score:.2f}, {region.count} voxels ({state}).{seen}"
        )
        self.progress.content = progress_text(q.review_progress())
        self._region_buttons(True)


def object_text(shown: QueuedObject, class_name: str) -> str:
    """The objects folder's line for the object shown: ``"Object **12** (1 of 5), car: car 48 % vs truck
    41 %"`` (HTML-escaped: class names are the user's)."""
    where = f"{shown.position} of {shown.count}" if shown.position else f"done; {shown.count} left"
    return (
        f"Object **{shown.track}** ({where}), {html.escape(class_name)}: {html.escape(shown.reason)} "
        f"(scan {html.escape(shown.frame_id)})."
    )


class ObjectQueuePanel:
    """Widgets of the "Objects to review" folder (call inside it): Next / Previous object over the session's
    :class:`~app.viewer.object_queue.ObjectQueue`; the shown object is the inspected one, which the Inspect
    section's *Relabel object* relabels."""

    def __init__(self, panel: ReviewPanel) -> None:
        self.p = panel
        gui, g = panel.gui, panel.guard
        self.next_button = gui.add_button(
            "Next object", hint="The next object whose class or track is in doubt"
        )
        self.prev_button = gui.add_button("Previous object")
        self.info = gui.add_markdown("Close class votes, broken and short tracks; press *Next object*.")
        self.next_button.on_click(g(lambda _: self.step(1)))
        self.prev_button.on_click(g(lambda _: self.step(-1)))

    def step(self, step: int) -> QueuedObject | None:
        objects = self.p.s.objects
        shown = objects.step(step)
        if shown is None:
            left = len(objects.pending())
            end = "end" if step > 0 else "start"
            self.info.content = (
                f"No objects to review ({'no tracks in this run' if not objects.ids else 'none queued'})."
                if not left
                else f"At the {end} of the queue ({left} to review)."
            )
            return shown
        self.show(shown)
        return shown

    def show(self, shown: QueuedObject) -> None:
        outputs = self.p.s.outputs
        tracks = None if outputs is None else outputs.tracks()
        names = self.p.s.class_names()
        label = -1 if tracks is None else int(tracks.table.label[shown.track - 1])
        self.info.content = object_text(shown, names[label] if 0 <= label < len(names) else "unlabeled")

    def on_run_loaded(self) -> None:
        self.info.content = "Close class votes, broken and short tracks; press *Next object*."

    def on_object(self, found: ObjectInfo | None) -> None:
        """After *Relabel object* on the object shown, say it is done and how many are left."""
        objects = self.p.s.objects
        if found is None or found.track != objects.current or found.corrected_to is None:
            return
        left = len(objects.pending())
        self.info.content = f"Object **{found.track}** relabelled: done; {left} left. Press *Next object*."


__all__ = [
    "QUEUE_KINDS",
    "QUEUE_OF",
    "ObjectQueuePanel",
    "ReviewQueuePanel",
    "object_text",
    "progress_text",
]
