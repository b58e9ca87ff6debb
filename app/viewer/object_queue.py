"""The objects to review of a session: the shown run's tracks that the object review queue holds (close
class votes, broken tracks, short tracks; :mod:`leap_core.object_review`, docs/METHOD.md B.6), stepped
through one at a time.

Showing one moves to the middle one of the scans where it has points, makes it the inspected object (so
the Inspect section's *Relabel object* applies to it), frames the camera on its points and tells the
panel why it is queued. An object an active object correction relabels has been dealt with: it leaves the
queue (stepping skips it and the count drops) as soon as the correction is made.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.viewer import nav_logic as nl
from app.viewer.player import ScanPlayer
from app.viewer.scene import ReviewScene
from app.viewer.selection_tool import SelectionTool
from app.viewer.shared import SharedState
from leap_core.object_review import ObjectQueueConfig, reason_text

OBJECT_VIEW_DISTANCE = 8.0
"""Least camera distance (m) when framing an object: a person's points alone would put the camera a metre
away."""


@dataclass(frozen=True)
class QueuedObject:
    """An object of the queue as shown: its track, why it is queued, where it stands in the queue."""

    track: int
    """Track id."""
    reason: str
    """Why, for a person: ``"car 48 % vs truck 41 %; 3 gaps"``."""
    position: int
    """1-based position among the objects still to review."""
    count: int
    """Objects still to review (those no active object correction relabels)."""
    frame_id: str
    """The scan shown: the middle one of those where it has points."""


class ObjectQueue:
    """The ranked objects of the shown run and the one shown.

    Args:
        shared: the session's shared state (the run, its outputs and its object corrections).
        config: the queue's thresholds (:attr:`app.viewer.records.SessionConfig.objects`).
        player: shows the object's scan.
        tools: makes the object the inspected one.
        scene: frames the camera on it.
    """

    def __init__(
        self,
        shared: SharedState,
        config: ObjectQueueConfig,
        *,
        player: ScanPlayer,
        tools: SelectionTool,
        scene: ReviewScene,
    ) -> None:
        self.shared = shared
        self.config = config
        self.player = player
        self.tools = tools
        self.scene = scene
        self.ids: list[int] = []
        """The ranked track ids, most doubtful first."""
        self.reasons: dict[int, int] = {}
        """Each queued track's reason mask (:mod:`leap_core.object_review`)."""
        self.current: int | None = None
        """The track shown last."""
        self._run: tuple[int, int] | None = None
        """(run id, outputs identity) the ranking is of."""

    def build(self) -> int:
        """Rank the shown run's objects (again when the run changed); returns how many are queued."""
        sh = self.shared
        with sh.lock:
            run, outputs = sh.run, sh.outputs
            schema = sh.run_schema or sh.project_schema
        key = None if run is None or outputs is None else (run.run_id, id(outputs))
        if key is not None and key == self._run:
            return len(self.ids)
        tracks = None if outputs is None else outputs.tracks()
        if tracks is None:
            self.ids, self.reasons = [], {}
        else:
            ids, reasons = tracks.review_queue(schema.things(), self.config)
            self.ids = ids.tolist()
            self.reasons = dict(zip(self.ids, reasons.tolist(), strict=True))
        self._run, self.current = key, None
        return len(self.ids)

    def pending(self) -> list[int]:
        """The queued tracks no active object correction relabels, in queue order."""
        with self.shared.lock:
            done = {t for t, _ in self.shared.object_classes()}
        return [t for t in self.ids if t not in done]

    def step(self, step: int) -> QueuedObject | None:
        """Show the next (``step`` 1) or previous (-1) object still to review after the one shown last;
        None at either end of the queue (nothing changes)."""
        self.build()
        pending = set(self.pending())
        at = self.ids.index(self.current) if self.current in self.ids else (-1 if step > 0 else len(self.ids))
        i = at + step
        while 0 <= i < len(self.ids):
            if self.ids[i] in pending:
                return self.show(self.ids[i])
            i += step
        return None

    def show(self, track: int) -> QueuedObject | None:
        """Show track ``track``: its middle scan, inspected and framed (module docstring). None when the
        run has no such track or it has no points."""
        sh = self.shared
        outputs = sh.outputs
        tracks = None if outputs is None else outputs.tracks()
        if outputs is None or tracks is None or not 1 <= track <= tracks.table.label.size:
            return None
        scans = tracks.scans_of(track)
        if not scans.size:
            return None
        fid = tracks.frame_ids[int(scans[scans.size // 2])]
        index = outputs.seq.frame_ids.index(fid)
        if index not in outputs.frame_indices:
            return None
        view = self.player.show_scan(outputs.frame_indices.index(index), move_camera=False)
        if view is None:
            return None
        self.current = track
        self.tools.inspect_track(track)
        if view.instance is not None:
            framing = nl.fit_view(view.points[view.instance == track], min_distance=OBJECT_VIEW_DISTANCE)
            if framing is not None:
                self.scene.look_at(*framing)
        pending = self.pending()
        return QueuedObject(
            track=track,
            reason=self.reason(track),
            position=pending.index(track) + 1 if track in pending else 0,
            count=len(pending),
            frame_id=fid,
        )

    def reason(self, track: int) -> str:
        """Why ``track`` is queued, for a person (empty when it is not)."""
        outputs = self.shared.outputs
        tracks = None if outputs is None else outputs.tracks()
        mask = self.reasons.get(track, 0)
        if tracks is None or not mask:
            return ""
        names = self.shared.class_names()
        k = track - 1
        ev, life = tracks.table.vote_evidence(), tracks.track_life()
        label, runner = int(tracks.table.label[k]), int(ev.runner_up[k])

        def name(c: int) -> str:
            return names[c] if 0 <= c < len(names) else f"class {c}"

        return reason_text(
            mask,
            name(label),
            share=float(ev.share[k]),
            runner_name=name(runner) if runner >= 0 else None,
            runner_share=float(ev.runner_share[k]),
            present=int(life.present[k]),
            gaps=int(np.asarray(life.gaps)[k]),
        )


__all__ = ["OBJECT_VIEW_DISTANCE", "ObjectQueue", "QueuedObject"]
