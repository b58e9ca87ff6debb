"""The review queue of a session: ranking regions worth a look, showing one, and the verdicts on them.

A region is a cell of the map holding at least :attr:`ReviewQueue.min_count` candidate voxels (the least
confident share, or the share with the most camera-vs-final disagreement; :mod:`app.viewer.region_logic`),
ranked by how many voxels (or camera-labelled points) it is expected to get wrong. Showing one focuses it:
its voxels are drawn filled and larger on top of the map, the rest of the map and the scan's points fade, a
box outlines it, the camera frames it, and the scan that saw it most is shown with the region boxed in its
image (the enlarged image zoomed on it). Accept / skip are stored in the project with the region's
content signature, so a mark counts only while the region's content is unchanged.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from collections.abc import Callable, Collection

import numpy as np

from app.viewer import region_logic as rl
from app.viewer.corrections import Corrections
from app.viewer.player import ScanPlayer
from app.viewer.records import ProjectBackend, QueueKind, ReviewMarkRecord, Selection, SessionConfig
from app.viewer.render import LodRenderer
from app.viewer.scene import ReviewScene
from app.viewer.shared import Notifier, SharedState
from leap_core import review

log = logging.getLogger(__name__)


class ReviewQueue:
    """Ranked regions, the focused one, and the marks on them.

    Args:
        shared: the session's shared state (writes ``focus`` / ``focus_frame``).
        backend: the project store (saves the ranked queue and the marks).
        scene: the viser facade (the region's box, the camera).
        config: the queue's tunables (``queue_share``, ``queue_cell``, ``queue_min_count``, ``queue_scans``).
        renderer: moves the full-resolution area to the region and redraws.
        player: shows the scan that saw the region best.
        corrections: relabels a region.
        notify: where the queue reports (panel ``on_queue`` / ``on_region`` / ``set_status``).
    """

    def __init__(
        self,
        shared: SharedState,
        backend: ProjectBackend,
        scene: ReviewScene,
        config: SessionConfig,
        *,
        renderer: LodRenderer,
        player: ScanPlayer,
        corrections: Corrections,
        notify: Notifier,
    ) -> None:
        self.shared = shared
        self.backend = backend
        self.scene = scene
        self.config = config
        self.renderer = renderer
        self.player = player
        self.corrections = corrections
        self.notify = notify
        self.claimed_by_others: Callable[[], Collection[str]] = tuple
        """Identities of the regions other reviewers claimed (:mod:`app.reviewers`), which stepping skips;
        set by the app's viewer (none by default)."""
        self.regions: list[rl.Region] = []
        """The ranked regions, worst first."""
        self.region_pos = -1
        """Position of the region last shown (-1: none yet)."""
        self.queue_kind: QueueKind = "confidence"
        self.queue_built = False
        """True once a queue was built for the loaded run (a re-run rebuilds it)."""
        self.queue_building = False
        self.signatures: list[str] = []
        """Content signature of each region of :attr:`regions` (same order)."""
        self.marks: dict[str, ReviewMarkRecord] = {}
        """The project's marks by region identity, as last read."""
        self.min_count = config.queue_min_count
        """Minimum region size in candidate voxels (:meth:`set_min_count`)."""

    @property
    def focus(self) -> rl.Region | None:
        """The region shown highlighted."""
        return self.shared.focus

    @property
    def focus_frame(self) -> int | None:
        """Position of the scan the focused region was seen best in."""
        return self.shared.focus_frame

    def reset(self) -> bool:
        """Forget the previous run's queue and focus (caller holds the shared lock); returns whether a queue
        had been built for it (then the new run's is ranked again: :meth:`rebuild_in_background`)."""
        self.regions, self.region_pos, self.signatures = [], -1, []
        self.shared.focus, self.shared.focus_frame = None, None
        rebuild = self.queue_built
        self.queue_built = False
        return rebuild

    def build_queue(self, kind: QueueKind) -> list[rl.Region]:
        """Regions to review, worst first: lowest confidence, or most camera-vs-final disagreement.

        Each region gets its content signature; the queue (identities and signatures) is saved to the
        project so the web UI can count review progress, and the project's marks are read back.
        """
        cfg, sh = self.config, self.shared
        with sh.lock:
            grid, conf, label, run = sh.grid, sh.conf, sh.label, sh.run
            self.queue_building = True
        self.notify.panel.on_queue(True)
        try:
            if grid is None:
                return []
            if kind == "confidence":
                candidates = rl.lowest_share(conf, cfg.queue_share)
                regions = rl.rank_regions(
                    grid.centres,
                    conf,
                    candidates,
                    cfg.queue_cell,
                    wrong=rl.confidence_wrong(conf),
                    min_count=self.min_count,
                    ascending=True,
                )
            else:
                assert sh.outputs is not None
                rate, observed = sh.outputs.disagreement(grid)
                seen = observed > 0
                # lowest_share of -rate (unseen voxels last) is the highest-disagreement share.
                top = rl.lowest_share(np.where(seen, -rate, np.inf), cfg.queue_share)
                candidates = seen & (rate > 0) & top
                regions = rl.rank_regions(
                    grid.centres,
                    rate,
                    candidates,
                    cfg.queue_cell,
                    wrong=rl.disagreement_wrong(rate, observed),
                    min_count=self.min_count,
                    ascending=False,
                )
            signatures = review.region_signatures(
                grid.centres, grid.keys, label, [r.cell for r in regions], cfg.queue_cell
            )
            run_id = None if run is None else run.run_id
            pairs = [(r.id, g) for r, g in zip(regions, signatures, strict=True)]
            self.backend.save_review_queue(kind, run_id, pairs)
            marks = self.backend.review_marks()
            with sh.lock:
                self.queue_kind = kind
                self.regions = regions
                self.signatures = signatures
                self.marks = marks
                self.region_pos = -1
                self.queue_built = True
            return regions
        finally:
            with sh.lock:
                self.queue_building = False
            self.notify.panel.on_queue(False)

    def set_min_count(self, count: int) -> None:
        """Change the minimum region size (within :attr:`SessionConfig.queue_min_count`'s bounds); the
        queue is ranked again on its next use.

        Raises:
            ConfigError: naming ``queue_min_count`` and its range.
        """
        checked = dataclasses.replace(self.config, queue_min_count=int(count)).queue_min_count
        with self.shared.lock:
            if checked != self.min_count:
                self.min_count = checked
                self.queue_built = False

    def rebuild_in_background(self) -> None:
        """Rank the current kind of queue again on a thread (after a re-run: the disagreement queue reads
        every scan); marks of regions whose signature did not change still count."""
        threading.Thread(
            target=self._rebuild_queue, args=(self.queue_kind,), name="viewer-queue", daemon=True
        ).start()

    def _rebuild_queue(self, kind: QueueKind) -> None:
        try:
            self.build_queue(kind)
        except Exception:  # keep the viewer alive; the panel shows the error
            log.exception("rebuilding the review queue failed")
            self.notify.panel.set_status("Ranking the review queue failed; see the server log.")

    def region_state(self, pos: int) -> str | None:
        """``accepted`` / ``skipped`` when region ``pos`` has a mark made on its current content, else
        None."""
        mark = self.marks.get(self.regions[pos].id)
        return mark.state if mark is not None and mark.signature == self.signatures[pos] else None

    def review_progress(self) -> dict[str, int]:
        """``{"total", "reviewed", "skipped"}`` over the current queue (marks on unchanged content only)."""
        with self.shared.lock:
            states = [self.region_state(i) for i in range(len(self.regions))]
        return {
            "total": len(states),
            "reviewed": states.count("accepted"),
            "skipped": states.count("skipped"),
        }

    # ------------------------------------------------------------------------------------- focusing
    def next_region(self, step: int = 1) -> rl.Region | None:
        """Show the next (or previous, ``step=-1``) region of the queue (see :meth:`show_region`)."""
        others = set(self.claimed_by_others())
        with self.shared.lock:
            if not self.regions:
                return None
            n = len(self.regions)
            ahead = [(self.region_pos + step * k) % n for k in range(1, n + 1)]
            pos = next((i for i in ahead if self.regions[i].id not in others), None)
        if pos is None:
            self.notify.panel.set_status("Every region of the queue is claimed by another reviewer.")
            return None
        return self.show_region(pos)

    def show_region(self, pos: int) -> rl.Region | None:
        """Focus region ``pos``: highlight its voxels and dim the rest, outline it, frame the camera on it,
        and show the scan that observed it best with the region boxed in its image."""
        sh = self.shared
        with sh.lock:
            if not 0 <= pos < len(self.regions):
                return None
            self.region_pos = pos
            region = self.regions[pos]
            sh.focus = region
            sh.focus_frame = None
            grid = sh.grid
        assert grid is not None
        lo = grid.centres[region.rows].min(axis=0) - grid.voxel_size / 2
        hi = grid.centres[region.rows].max(axis=0) + grid.voxel_size / 2
        self.scene.set_review_box((lo + hi) / 2, hi - lo, rl.REVIEW_BOX_RGB)
        self.scene.frame_region(region)
        self.renderer.focus_lod(region.centre)
        self.renderer.request_draw()
        best = self._best_scan(region)
        if best is not None:
            with sh.lock:
                sh.focus_frame = best
            keys = grid.keys[region.rows]
            outputs = sh.outputs
            if outputs is not None:
                self.player.camera = outputs.best_camera(outputs.frame_indices[best], keys, grid.voxel_size)
            self.player.show_scan(best, move_camera=False)  # keep the framing of the region
        else:
            self.player.color_scan()  # fade the shown scan's points around the highlight
        self.notify.panel.on_region(region, pos, len(self.regions), self.queue_kind)
        return region

    def clear_focus(self) -> None:
        """Leave the review: no region highlighted (the whole map at full colour, no box in the map or in
        the scan's image). The queue and its position stay, so *Next region* goes on where the user left."""
        with self.shared.lock:
            had_focus = self.shared.focus is not None
            self.shared.focus, self.shared.focus_frame = None, None
        self.scene.set_review_box(None)
        self.renderer.request_draw()
        if had_focus:
            # The shown scan's image still has the region boxed in it: show the scan again without it.
            self.player.show_scan(self.player.frame_pos, move_camera=False)
        self.notify.panel.on_focus_cleared()

    def _best_scan(self, region: rl.Region) -> int | None:
        """Slider position of the scan that observed ``region`` most, among the ``queue_scans`` scans
        nearest it (:func:`leap_core.review.best_observer`)."""
        outputs, grid = self.shared.outputs, self.shared.grid
        if outputs is None or grid is None or not outputs.frame_indices:
            return None
        frames = np.asarray(outputs.frame_indices)
        positions = outputs.seq.poses[frames, :3, 3]
        near = review.nearest_scans(positions, region.centre, self.config.queue_scans)
        keys = grid.keys[region.rows]  # rows ascend, so the keys stay sorted
        # Each scan as its camera that saw the region best: the region is boxed in that camera's image.
        counts = [outputs.region_observers(int(frames[i]), keys, grid.voxel_size, None)[:2] for i in near]
        best = review.best_observer([c[1] for c in counts], [c[0] for c in counts])
        return None if best is None else int(near[best])

    # -------------------------------------------------------------------------------------- verdicts
    def mark_region(self, state: str) -> rl.Region | None:
        """Record ``accepted`` or ``skipped`` for the focused region (in the project's database) and show
        the next region without a mark; returns that region (None when every region has one)."""
        sh = self.shared
        with sh.lock:
            pos = self.region_pos
            if sh.focus is None or not 0 <= pos < len(self.regions):
                raise ValueError("no review region is shown; press Next region first")
            region, signature = self.regions[pos], self.signatures[pos]
        run_id = None if sh.run is None else sh.run.run_id
        self.backend.set_review_mark(region.id, signature, state, run_id)
        others = set(self.claimed_by_others())
        with sh.lock:
            self.marks[region.id] = ReviewMarkRecord(signature, state)
            n = len(self.regions)
            following = [(pos + k) % n for k in range(1, n + 1)]
            nxt = next(
                (i for i in following if self.region_state(i) is None and self.regions[i].id not in others),
                None,
            )
        self.notify.emit("marked")
        if nxt is None:
            self.notify.panel.on_region(region, pos, n, self.queue_kind)
            return None
        return self.show_region(nxt)

    def relabel_region(self, class_name: str) -> int | None:
        """Assign ``class_name`` to the focused region's voxels (a correction, as a box selection would)
        and accept the region on its new content; returns the correction id."""
        sh = self.shared
        with sh.lock:
            pos = self.region_pos
            if sh.focus is None or not 0 <= pos < len(self.regions) or sh.grid is None:
                raise ValueError("no review region is shown; press Next region first")
            region = self.regions[pos]
        cid = self.corrections.assign_selection(class_name, selection=Selection(region.rows))
        grid = sh.grid
        assert grid is not None
        signature = review.region_signatures(
            grid.centres, grid.keys, sh.label, [region.cell], self.config.queue_cell
        )[0]
        with sh.lock:
            self.signatures[pos] = signature
        self.mark_region("accepted")
        return cid


__all__ = ["ReviewQueue"]
