"""Steering the project from the viewer: editing its classes and prompts, starting re-runs, and watching a
run until it is done (then the session loads it).

Both act on the project store the web UI edits (:class:`~app.viewer.records.ProjectBackend`), so a class
renamed here shows there, and a run started there is watched here when the viewer opens.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from collections.abc import Callable

from app.viewer.records import ProjectBackend, RunInfo
from app.viewer.render import LodRenderer
from app.viewer.shared import Notifier, SharedState
from leap_core.schema import ClassDef, Schema

log = logging.getLogger(__name__)


class ClassEditor:
    """Rename / recolour / re-prompt, add and remove the project's classes.

    Args:
        shared: the session's shared state (writes ``project_schema`` and the palette).
        backend: the project store the schema is saved to.
        renderer: redraws in the new colours.
        notify: where schema changes are reported (panel ``on_schema``).
    """

    def __init__(
        self, shared: SharedState, backend: ProjectBackend, renderer: LodRenderer, notify: Notifier
    ) -> None:
        self.shared = shared
        self.backend = backend
        self.renderer = renderer
        self.notify = notify

    @property
    def schema(self) -> Schema:
        """The project's schema as last saved or read."""
        return self.shared.project_schema

    def update_class(
        self,
        index: int,
        *,
        name: str | None = None,
        color: tuple[int, int, int] | None = None,
        prompts: list[str] | None = None,
    ) -> Schema:
        """Rename / recolour / re-prompt class ``index`` of the project schema and save it."""
        schema = self.backend.load_schema()
        classes = list(schema.classes)
        old = classes[index]
        classes[index] = dataclasses.replace(
            old,
            name=old.name if name is None else name,
            color=old.color if color is None else color,
            prompts=old.prompts if prompts is None else tuple(prompts),
        )
        return self._save_schema(schema.with_classes(classes))

    def add_class(self, name: str, *, color: tuple[int, int, int] = (200, 200, 200)) -> Schema:
        """Append a class (prompt = its name, next free export id) to the project schema and save it."""
        schema = self.backend.load_schema()
        used = {c.export_id for c in schema.classes}
        export_id = next(i for i in range(max(used, default=0) + 1, 1 << 16) if i not in used)
        new = ClassDef(name=name, color=color, prompts=(name,), export_id=export_id)
        return self._save_schema(schema.with_classes([*schema.classes, new]))

    def remove_class(self, index: int) -> Schema:
        """Remove class ``index`` from the project schema and save it."""
        schema = self.backend.load_schema()
        classes = [c for i, c in enumerate(schema.classes) if i != index]
        return self._save_schema(schema.with_classes(classes))

    def _save_schema(self, schema: Schema) -> Schema:
        self.backend.save_schema(schema)
        sh = self.shared
        with sh.lock:
            sh.project_schema = self.backend.load_schema()
            sh.refresh_palette()
        self.notify.panel.on_schema()
        self.renderer.request_draw()
        return sh.project_schema


class RunWatcher:
    """Starts re-runs and follows the watched run on a thread until it ends; a finished run is loaded.

    Args:
        backend: the project store (starts runs, reports their progress).
        load_run: shows a finished run (the session's :meth:`~app.viewer.session.ReviewSession.load_run`).
        notify: where progress is reported (panel ``on_run_progress`` / ``set_status``; events
            ``run_started`` and ``run_finished``).
        poll_interval_s: how often the watched run's progress is read.
        stop: set when the session closes (ends the watcher).
    """

    def __init__(
        self,
        backend: ProjectBackend,
        load_run: Callable[[RunInfo], None],
        notify: Notifier,
        poll_interval_s: float,
        stop: threading.Event,
    ) -> None:
        self.backend = backend
        self._load_run = load_run
        self.notify = notify
        self._interval = poll_interval_s
        self._stop = stop
        self.watched_run: int | None = None
        """The run being watched (None: none)."""
        self._watcher: threading.Thread | None = None

    def rerun(self) -> int:
        """Start a background run of the project (with its current schema and corrections)."""
        run_id = self.backend.start_run()
        self.notify.emit("run_started")
        self.watch(run_id)
        return run_id

    def watch(self, run_id: int) -> None:
        """Follow run ``run_id`` (instead of the one watched so far) until it ends."""
        self.watched_run = run_id
        if self._watcher is not None and self._watcher.is_alive():
            return  # the running watcher follows ``watched_run``
        self._watcher = threading.Thread(target=self._watch_loop, name="viewer-run-watch", daemon=True)
        self._watcher.start()

    def close(self) -> None:
        """Wait for the watcher to end (``stop`` is set by the session)."""
        if self._watcher is not None:
            self._watcher.join(timeout=5)

    def _watch_loop(self) -> None:
        while not self._stop.is_set():
            run_id = self.watched_run
            if run_id is None:
                return
            try:
                info = self.backend.run_info(run_id)
            except Exception:  # a transient DB error must not kill the watcher
                log.exception("viewer could not read run %s", run_id)
                self._stop.wait(self._interval)
                continue
            self.notify.panel.on_run_progress(info)
            if info.status in ("done", "failed", "cancelled", "interrupted"):
                if self.watched_run == run_id:
                    self.watched_run = None
                if info.status == "done":
                    try:
                        self._load_run(info)
                    except Exception as exc:  # report, keep the old scene
                        log.exception("viewer could not load run %s", run_id)
                        self.notify.panel.set_status(
                            f"Run {info.number} finished but could not be loaded: {exc}"
                        )
                self.notify.emit("run_finished")
                if self.watched_run is None:
                    return
                continue
            self._stop.wait(self._interval)


__all__ = ["ClassEditor", "RunWatcher"]
