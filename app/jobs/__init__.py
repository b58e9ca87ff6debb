"""Background runs of the pipeline: the queue and its worker threads (:mod:`app.jobs.manager`), the worker
process (:mod:`app.jobs.worker`), the messages between them (:mod:`app.jobs.messages`) and live progress
(:mod:`app.jobs.progress`).

This package file imports nothing: the worker process (``python -m app.jobs.worker``) loads it first, and
must not load the server's side before it has set itself up to die with the server.
"""
