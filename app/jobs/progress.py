"""Live progress of one run: per-stage counters, timings and ETAs (pure bookkeeping, no I/O).

The pipeline reports ``progress(stage, done, total)``. A stage starts at its first report and is done
when ``done == total``. For a stage with ``d`` of ``n`` units done after ``t`` seconds the ETA is
``t · (n − d) / d``.

The run's percent weights each stage by its expected seconds ``E_s``: ``100 · Σ_s E_s · f_s / Σ_s E_s``
(``f_s`` its fraction done), so a run whose 2D labels take most of its time reads most of the way done when
they are (with equal weights, 93 % of ``labels2d`` read 12 %). ``E_s`` is what the stage took (done), its
own rate's projection ``t · n / d`` (running), or for a stage still to come the seconds it took in the
project's previous finished run, else its expected cost: units (the sequence's frames) ×
:func:`~app.jobs.stages.unit_seconds` × the machine's measured speed (seconds taken / expected over the
finished stages other than ``labels2d``, whose cost depends on the labeler and device; 1 before any).
The run's ETA adds the running stages' ``t · (n − d) / d`` and the stages to come's ``E_s``; it is None
until some stage has a rate (a first run then gets one from its stages' own rates, not only a later one
from the previous run's times).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from app.jobs.stages import JOINT, SEPARATOR, split_stage, unit_seconds

TERMINAL_STATUSES = frozenset({"done", "failed", "cancelled", "interrupted"})
MAX_WARNINGS = 20
"""Warnings a run keeps (the first ones; later ones are counted in the last entry)."""


@dataclass
class StageState:
    """Counters of one stage."""

    name: str
    """Stage name (``leap_core.pipeline.STAGES``)."""
    status: str = "pending"
    """pending | running | done | skipped | failed | cancelled."""
    done: int = 0
    """Units finished (frames, iterations)."""
    total: int = 0
    """Units in the stage."""
    started: float | None = None
    """``time.monotonic()`` of the first report."""
    seconds: float | None = None
    """Wall time once done."""
    note: str | None = None
    """Why a skipped stage computed nothing ("no ground truth", "unchanged since the last run")."""

    def fraction(self) -> float:
        if self.status in ("done", "skipped"):
            return 1.0
        if self.total <= 0:
            return 0.0
        return min(1.0, self.done / self.total)

    def eta(self, now: float) -> float | None:
        if self.status != "running" or self.started is None or self.done <= 0 or self.total <= 0:
            return None
        elapsed = now - self.started
        return max(0.0, elapsed * (self.total - self.done) / self.done)

    def public(self, now: float) -> dict[str, Any]:
        seconds = self.seconds
        if seconds is None and self.started is not None and self.status == "running":
            seconds = now - self.started
        eta = self.eta(now)
        return {
            "name": self.name,
            "status": self.status,
            "done": self.done,
            "total": self.total,
            "seconds": None if seconds is None else round(seconds, 3),
            "eta_s": None if eta is None else round(eta, 1),
            "percent": round(100.0 * self.fraction(), 1),
            "note": self.note,
        }


def precedes(earlier: str, later: str) -> bool:
    """Whether the stage listed before ``later`` has ended when ``later`` starts. A run's stages are
    ``<sequence>/<stage>`` (:mod:`app.jobs.stages`) and its sequences may run at the same time (on a Ray
    cluster), so only a stage of the same sequence precedes, or one across the 3D-CN rounds (sequence
    ``*``), which start after every sequence's first stages and end before any of their later ones.
    Stage names without a sequence (runs stored before runs had sequences) always do."""
    seq_e, sep_e, _ = earlier.partition(SEPARATOR)
    seq_l, sep_l, _ = later.partition(SEPARATOR)
    return not (sep_e and sep_l) or JOINT in (seq_e, seq_l) or seq_e == seq_l


@dataclass
class ProgressTracker:
    """Progress of one run, updated from the worker's messages and read by API requests."""

    run_id: int
    project_id: int
    stages: list[StageState]
    status: str = "queued"
    error: str | None = None
    expected_seconds: dict[str, float] = field(default_factory=dict)
    """Seconds each stage took in the project's last finished run (for the run-level ETA)."""
    warnings: list[str] = field(default_factory=list)
    """What the pipeline warned about (e.g. frames without a camera image), shown with the run."""
    labeler_input: str | None = None
    """What the run's 2D labeler reads (``gt2d`` or ``images``): the expected cost of its ``labels2d``."""
    version: int = 0
    """Bumped on every change, so streams send only news."""
    updated_at: str = ""
    on_change: Callable[[int], None] | None = field(default=None, repr=False, compare=False)
    """Called with the run id after every change (wakes the progress streams)."""

    @classmethod
    def create(
        cls,
        run_id: int,
        project_id: int,
        stage_names: Iterable[str],
        *,
        status: str = "queued",
        expected_seconds: Mapping[str, float] | None = None,
        labeler_input: str | None = None,
    ) -> ProgressTracker:
        return cls(
            run_id=run_id,
            project_id=project_id,
            stages=[StageState(n) for n in stage_names],
            status=status,
            expected_seconds=dict(expected_seconds or {}),
            labeler_input=labeler_input,
        )

    def _stage(self, name: str) -> StageState:
        for s in self.stages:
            if s.name == name:
                return s
        # A stage the app did not know about: it runs now, so it goes before every stage not yet started.
        state = StageState(name)
        pending = [i for i, s in enumerate(self.stages) if s.status == "pending"]
        self.stages.insert(pending[0] if pending else len(self.stages), state)
        return state

    def _touch(self, stamp: str) -> None:
        self.version += 1
        self.updated_at = stamp
        if self.on_change is not None:
            self.on_change(self.run_id)

    def clone(self) -> ProgressTracker:
        """An independent copy without the change callback."""
        return dataclasses.replace(
            self,
            stages=[dataclasses.replace(s) for s in self.stages],
            expected_seconds=dict(self.expected_seconds),
            warnings=list(self.warnings),
            on_change=None,
        )

    def set_status(self, status: str, stamp: str, error: str | None = None) -> None:
        self.status = status
        self.error = error
        if status in TERMINAL_STATUSES:
            for s in self.stages:
                if s.status == "running":
                    s.status = {"done": "done", "failed": "failed"}.get(status, "cancelled")
                elif s.status == "pending" and status == "done":
                    s.status = "skipped"
        self._touch(stamp)

    def add_warning(self, text: str, stamp: str) -> None:
        """Record a warning once (a resumed run repeats its first attempt's warnings)."""
        if text in self.warnings:
            return
        if len(self.warnings) < MAX_WARNINGS:
            self.warnings.append(text)
        elif len(self.warnings) == MAX_WARNINGS:
            self.warnings.append("… further warnings are in the run's log")
        else:
            return
        self._touch(stamp)

    def mark_skipped(self, notes: Mapping[str, str | None]) -> None:
        """Show stages the pipeline recorded as skipped (stage → its note) as skipped, with the note."""
        for s in self.stages:
            if s.name in notes and s.status in ("done", "pending", "skipped"):
                s.status = "skipped"
                s.seconds = None
                s.note = s.note or notes[s.name]

    def update(
        self, stage: str, done: int, total: int, now: float, stamp: str, skipped: str | None = None
    ) -> bool:
        """Record a report; returns True when the stage changed state (started or finished).

        Stages run in order, so earlier stages still marked running are closed and earlier stages that
        never reported are marked skipped (only those that precede it: :func:`precedes`). ``skipped`` (the
        reason) marks a stage that reports completion without computing anything as skipped rather than
        done.
        """
        state = self._stage(stage)
        changed = False
        if state.status in ("pending", "cancelled", "failed"):
            index = self.stages.index(state)
            for earlier in self.stages[:index]:
                if not precedes(earlier.name, stage):
                    continue
                if earlier.status == "pending":
                    # The pipeline reports nothing for a stage it skips (3D-CN off, no ground truth).
                    earlier.status = "skipped"
                elif earlier.status == "running":
                    earlier.status = "done"
                    earlier.done = max(earlier.done, earlier.total)
                    if earlier.started is not None and earlier.seconds is None:
                        earlier.seconds = now - earlier.started
            state.status = "running"
            state.started = now
            state.seconds = None
            changed = True
        state.done = int(done)
        state.total = int(total)
        if total > 0 and done >= total and state.status == "running":
            state.status = "done"
            state.seconds = now - (state.started if state.started is not None else now)
            changed = True
        if skipped is not None and state.status in ("running", "done"):
            state.status, state.note, state.seconds = "skipped", skipped, None
            changed = True
        self._touch(stamp)
        return changed

    def current_stage(self) -> str | None:
        for s in self.stages:
            if s.status == "running":
                return s.name
        return None

    # ---------------------------------------------------------------------------- expected seconds
    def _units(self, state: StageState) -> int:
        """Units a stage will count: its reported total, else its sequence's frames (the largest total
        any of its stages reported), else the mean of the other sequences', else 1; a 3D-CN round is
        1000 units (thousandths)."""
        if state.total > 0:
            return state.total
        sequence, _ = split_stage(state.name)
        if sequence == JOINT:
            return 1000
        frames: dict[str | None, int] = {}
        for s in self.stages:
            seq, _ = split_stage(s.name)
            if seq != JOINT and s.total > 0:
                frames[seq] = max(frames.get(seq, 0), s.total)
        if sequence in frames:
            return frames[sequence]
        return round(sum(frames.values()) / len(frames)) if frames else 1

    def _cost(self, state: StageState) -> float:
        """The stage's expected seconds before it measured its own: units × seconds per unit."""
        return self._units(state) * unit_seconds(state.name, self.labeler_input)

    def speed(self) -> float:
        """Seconds the finished stages took per expected second (:meth:`_cost`), ``labels2d`` left out
        (its cost depends on the labeler and the device); 1.0 before any finished."""
        spent = expected = 0.0
        for s in self.stages:
            if s.status != "done" or s.seconds is None or split_stage(s.name)[1] == "labels2d":
                continue
            cost = self._cost(s)
            if cost > 0:
                spent += s.seconds
                expected += cost
        return spent / expected if spent > 0 and expected > 0 else 1.0

    def _planned(self, state: StageState, speed: float) -> float:
        """Expected seconds of a stage not running yet: the previous run's, else its cost × speed."""
        if state.name in self.expected_seconds:
            return self.expected_seconds[state.name]
        return self._cost(state) * speed

    def expected(self, state: StageState, now: float, speed: float) -> float:
        """``E_s``: the stage's expected seconds in all (module docstring)."""
        if state.status == "skipped":
            return 0.0
        if state.status == "done":
            return state.seconds or 0.0
        if state.status == "running" and state.started is not None:
            elapsed = max(0.0, now - state.started)
            eta = state.eta(now)
            return elapsed + eta if eta is not None else max(elapsed, self._planned(state, speed))
        return self._planned(state, speed)

    def percent(self, now: float | None = None) -> float:
        if self.status == "done":
            return 100.0
        if not self.stages:
            return 0.0
        now = time.monotonic() if now is None else now
        speed = self.speed()
        weights = [self.expected(s, now, speed) for s in self.stages]
        total = sum(weights)
        if total <= 0:
            return 100.0 * sum(s.fraction() for s in self.stages) / len(self.stages)
        return 100.0 * sum(w * s.fraction() for w, s in zip(weights, self.stages, strict=True)) / total

    def eta(self, now: float) -> float | None:
        if self.status != "running":
            return None
        measured = any(
            (s.status == "done" and s.seconds is not None) or s.eta(now) is not None for s in self.stages
        )
        if not measured:
            return None
        speed = self.speed()
        eta = 0.0
        for s in self.stages:
            if s.status == "running":
                own = s.eta(now)
                if own is None:
                    started = s.started if s.started is not None else now
                    own = max(0.0, self._planned(s, speed) - (now - started))
                eta += own
            elif s.status in ("pending", "cancelled", "failed"):
                eta += self._planned(s, speed)
        return eta

    def snapshot(self, now: float | None = None) -> dict[str, Any]:
        """The :class:`app.models.RunProgress` payload."""
        now = time.monotonic() if now is None else now
        eta = self.eta(now)
        speed = self.speed()
        return {
            "run_id": self.run_id,
            "project_id": self.project_id,
            "status": self.status,
            "stage": self.current_stage(),
            "percent": round(self.percent(now), 1),
            "eta_s": None if eta is None else round(eta, 1),
            "stages": [
                {**s.public(now), "expected_s": round(self.expected(s, now, speed), 6)} for s in self.stages
            ],
            "error": self.error,
            "warnings": list(self.warnings),
            "updated_at": self.updated_at,
            "version": self.version,
        }

    # ------------------------------------------------------------------------------- persistence
    def stages_record(self) -> dict[str, Any]:
        """What the ``runs.stages`` column keeps: ordered stage states (for history and restarts)."""
        return {
            "order": [s.name for s in self.stages],
            "stages": {
                s.name: {
                    "status": s.status,
                    "done": s.done,
                    "total": s.total,
                    "seconds": s.seconds,
                    **({"note": s.note} if s.note else {}),
                }
                for s in self.stages
            },
            "warnings": list(self.warnings),
        }

    @classmethod
    def from_record(
        cls,
        run_id: int,
        project_id: int,
        status: str,
        record: Mapping[str, Any] | None,
        stage_names: Iterable[str],
        *,
        error: str | None = None,
        stamp: str = "",
    ) -> ProgressTracker:
        """Rebuild a (non-live) tracker from the stored record of a run."""
        record = record or {}
        order = list(record.get("order") or stage_names)
        tracker = cls.create(run_id, project_id, order, status=status)
        stored = record.get("stages") or {}
        for s in tracker.stages:
            entry = stored.get(s.name)
            if entry:
                s.status = entry.get("status", "pending")
                s.done = int(entry.get("done") or 0)
                s.total = int(entry.get("total") or 0)
                s.seconds = entry.get("seconds")
                s.note = entry.get("note")
            if s.status == "running":
                # Stored while running, but no process is working on it now.
                s.status = "cancelled" if status in TERMINAL_STATUSES else "running"
        tracker.error = error
        tracker.warnings = [str(w) for w in record.get("warnings") or []]
        tracker.updated_at = stamp
        return tracker
