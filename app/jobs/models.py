"""A project's LiDAR-only models as background jobs: "Train a model" and "Label with a model".

A ``train`` job trains :mod:`leap_core.lidar_model` on the final labels (``points/*.npz``, corrections
applied) of the run it was queued with (the project's latest finished run then), holding apart a sequence
or every few frame blocks for validation, into ``<work_dir>/lidar-models/p<P>/m<J>.pt`` with its card
beside it. A ``label`` job labels one of the project's sequences with a model of the same project into
the run folder ``<work_dir>/lidar-models/p<P>/labels/l<J>/``
(:func:`leap_core.lidar_model.predict.predict_run`), whose export is offered as a zip like a run's.

Jobs run one at a time on one background thread of the server (torch computes in its own threads).
Cancel raises :class:`~leap_core.errors.Cancelled` from the progress callback; the training keeps its last
saved state (``<model>.state.pt``, every ``checkpoint_every`` steps), so resume (after a cancel, a failure
or a server restart, which marks a working job ``interrupted``) continues from that step and ends with the
bytes an uninterrupted training writes. A labeling restarts its sequence (every scan is rewritten).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from pathlib import Path
from typing import Any

from app import crud
from app.core.config import Settings
from app.core.db import open_db, utcnow
from app.core.errors import Conflict
from app.rows import ModelJobRow
from leap_core.errors import Cancelled, LeapError

log = logging.getLogger("leap.models")

ACTIVE = ("queued", "running")
RESUMABLE = ("cancelled", "failed", "interrupted")
PERSIST_EVERY_S = 1.0
"""Shortest time between two progress writes of one job to the database (the UI reads the live value)."""


def models_folder(settings: Settings, project_id: int) -> Path:
    """A project's models and labelings: ``<work_dir>/lidar-models/p<P>`` (removed with the project)."""
    return settings.work_dir / "lidar-models" / f"p{project_id}"


def model_file(settings: Settings, project_id: int, job_id: int) -> Path:
    """The model a ``train`` job writes (``m<J>.pt``; ``m<J>.card.json`` beside it)."""
    return models_folder(settings, project_id) / f"m{job_id}.pt"


def label_folder(settings: Settings, project_id: int, job_id: int) -> Path:
    """The run folder a ``label`` job writes."""
    return models_folder(settings, project_id) / "labels" / f"l{job_id}"


class ModelJobs:
    """The model jobs of one database (one per app)."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._queue: list[int] = []
        self._live: dict[int, tuple[int, int]] = {}
        """job → (done, total) of the job working now."""
        self._cancel: set[int] = set()
        self._stopping = False
        self._thread: threading.Thread | None = None

    # ---------------------------------------------------------------------------------------- lifetime
    def start(self) -> None:
        """Mark jobs a stopped server left working as ``interrupted`` (resumable), queue the queued ones
        again, and start the worker thread."""
        with open_db(self.settings.database) as db:
            for job in crud.list_model_jobs(db, statuses=("running",)):
                crud.update_model_job(db, job.id, status="interrupted", error="the server stopped")
            queued = [j.id for j in reversed(crud.list_model_jobs(db, statuses=("queued",)))]
        with self._lock:
            self._stopping = False
            self._queue = queued
            self._thread = threading.Thread(target=self._loop, name="leap-model-jobs", daemon=True)
            self._thread.start()

    def stop(self, timeout: float = 15.0) -> None:
        """Stop the thread; a job working now ends ``interrupted`` (its last saved state kept)."""
        with self._lock:
            self._stopping = True
            self._cancel.update(self._live)
            self._wake.notify_all()
            thread = self._thread
        if thread is not None:
            thread.join(timeout)

    # ---------------------------------------------------------------------------------------- requests
    def submit(self, job: ModelJobRow) -> None:
        with self._lock:
            self._queue.append(job.id)
            self._wake.notify_all()

    def cancel(self, job_id: int) -> None:
        """Cancel a queued job now, a working one at its next step.

        Raises:
            Conflict: the job has ended.
        """
        with open_db(self.settings.database) as db:
            job = crud.require_model_job(db, job_id)
            if job.status not in ACTIVE:
                raise Conflict(f"Model job {job_id} is {job.status}; only queued or working jobs cancel")
            with self._lock:
                if job_id in self._queue:
                    self._queue.remove(job_id)
                    crud.update_model_job(db, job_id, status="cancelled", finished_at=utcnow())
                else:
                    self._cancel.add(job_id)

    def resume(self, job_id: int) -> None:
        """Queue a cancelled, failed or interrupted job again.

        Raises:
            Conflict: the job is queued, working or done.
        """
        with open_db(self.settings.database) as db:
            job = crud.require_model_job(db, job_id)
            if job.status not in RESUMABLE:
                raise Conflict(f"Model job {job_id} is {job.status}; only {', '.join(RESUMABLE)} jobs resume")
            crud.update_model_job(db, job_id, status="queued", error=None, finished_at=None)
        self.submit(job)

    def progress(self, job: ModelJobRow) -> tuple[int, int]:
        """(done, total) of a job: live while it works, else as stored."""
        with self._lock:
            return self._live.get(job.id, (job.done, job.total))

    def wait_idle(self, timeout: float) -> bool:
        """Whether the queue emptied and no job works within ``timeout`` seconds (tests, shutdown)."""
        end = time.monotonic() + timeout
        with self._lock:
            while self._queue or self._live:
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self._wake.wait(left)
        return True

    # ------------------------------------------------------------------------------------------ worker
    def _loop(self) -> None:
        while True:
            with self._lock:
                while not self._queue and not self._stopping:
                    self._wake.wait()
                if self._stopping:
                    return
                job_id = self._queue.pop(0)
                self._live[job_id] = (0, 0)
            try:
                self._run(job_id)
            finally:
                with self._lock:
                    self._live.pop(job_id, None)
                    self._cancel.discard(job_id)
                    self._wake.notify_all()

    def _run(self, job_id: int) -> None:
        with open_db(self.settings.database) as db:
            job = crud.get_model_job(db, job_id)
            if job is None or job.status != "queued":
                return  # deleted with its project, or cancelled while queued
            crud.update_model_job(db, job_id, status="running", started_at=utcnow(), error=None)
        last = [0.0]

        def tick(done: int, total: int) -> None:
            with self._lock:
                self._live[job_id] = (done, total)
                stop = job_id in self._cancel
            now = time.monotonic()
            if now - last[0] >= PERSIST_EVERY_S or done >= total:
                last[0] = now
                with open_db(self.settings.database) as db:
                    crud.update_model_job(db, job_id, done=done, total=total)
            if stop:
                raise Cancelled(f"model job {job_id} cancelled")

        fields: dict[str, Any]
        try:
            extra = self._train(job, tick) if job.kind == "train" else self._label(job, tick)
            fields = {"status": "done", **extra}
        except Cancelled:
            fields = {"status": "interrupted" if self._stopping else "cancelled"}
        except (LeapError, OSError) as exc:
            log.warning("model job %d failed: %s", job_id, exc)
            fields = {"status": "failed", "error": str(exc)}
        except Exception as exc:  # a job's bug must not end the worker thread
            log.exception("model job %d failed", job_id)
            fields = {"status": "failed", "error": f"{type(exc).__name__}: {exc}"}
        with self._lock:
            done, total = self._live.get(job_id, (0, 0))
        with open_db(self.settings.database) as db:
            if crud.get_model_job(db, job_id) is not None:
                crud.update_model_job(db, job_id, done=done, total=total, finished_at=utcnow(), **fields)

    def _train(self, job: ModelJobRow, tick: Any) -> dict[str, Any]:
        # torch and the model code load with the first job, not with the app.
        from leap_core.lidar_model.config import model_config_from_dict  # noqa: PLC0415
        from leap_core.lidar_model.data import run_sequences, split_scans  # noqa: PLC0415
        from leap_core.lidar_model.train import train_lidar_model  # noqa: PLC0415
        from leap_core.schema import Schema  # noqa: PLC0415

        with open_db(self.settings.database) as db:
            run = crud.get_run(db, int(job.params["run_id"]))
        if run is None or run.status != "done":
            raise LeapError(f"run {job.params['run_id']} is gone or no longer finished; train again")
        cfg = model_config_from_dict(job.params["settings"])
        seqs = run_sequences(run.run_dir)
        apart_name = job.params["validation"].get("sequence")
        if job.params["validation"]["by"] == "sequence":
            train = [s for s in seqs if s.layout is not None and s.layout.folder.name != apart_name]
            apart = [s for s in seqs if s.layout is not None and s.layout.folder.name == apart_name]
            block = 0
        else:
            train, apart, block = seqs, [], cfg.val_block
        tr, va = split_scans(train, apart, block, cfg.val_every)
        schema = Schema.from_dict(run.params.schema, source=f"run {run.id} schema")
        out = model_file(self.settings, job.project_id, job.id)
        out.parent.mkdir(parents=True, exist_ok=True)
        result = train_lidar_model(out, tr, va, schema, cfg, progress=tick)
        return {"params_json": _params_json({**job.params, "resumed_from": result.resumed_from})}

    def _label(self, job: ModelJobRow, tick: Any) -> dict[str, Any]:
        from leap_core.lidar_model.model import load_model  # noqa: PLC0415
        from leap_core.lidar_model.predict import predict_run  # noqa: PLC0415

        assert job.model_id is not None
        path = model_file(self.settings, job.project_id, job.model_id)
        model = load_model(path)
        frames = job.params.get("frames")
        out = label_folder(self.settings, job.project_id, job.id)
        out.mkdir(parents=True, exist_ok=True)
        results = predict_run(
            model,
            path,
            [(job.name, Path(job.params["dataset"]), None if frames is None else range(*frames))],
            out,
            progress=lambda _name, done, total: tick(done, total),
        )
        counts: dict[str, int] = {}
        for r in results:
            for raw, n in r.raw_counts.items():
                counts[str(raw)] = counts.get(str(raw), 0) + n
        return {"params_json": _params_json({**job.params, "raw_counts": counts})}


def _params_json(params: dict[str, Any]) -> str:
    return json.dumps(params, sort_keys=True)


__all__ = ["ModelJobs", "label_folder", "model_file", "models_folder"]
