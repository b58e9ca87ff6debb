"""One server per work folder and per database, and the listening socket bound before anything else happens.

Two servers on one work folder, or on one database (``LEAP_DB_PATH`` lets a server keep its database
outside its work folder), would both own its runs: the second marks the first one's live runs
``interrupted`` at start-up, after which a Cancel answers 409 while the run goes on and ends ``done``.
A server therefore takes an exclusive ``flock`` on ``work_dir/server.lock`` and one on the lock file
beside its database (``studio.db.server-lock``) before it opens the database, and keeps both until it
exits (the kernel drops them even after ``kill -9``). Each lock file records the holder's pid and
address, so the refusal says which server to stop.

The socket is bound next, still before the database is opened: a server whose port is taken exits
without having changed anything (uvicorn would otherwise run the app's start-up, which marks runs
interrupted, before finding out that it cannot listen).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import socket
from pathlib import Path

LOCK_NAME = "server.lock"
"""The work folder's lock file (holds ``pid host:port`` of the server owning the folder)."""

DB_LOCK_SUFFIX = ".server-lock"
"""Suffix of the database's lock file, beside it (``studio.db`` → ``studio.db.server-lock``)."""


class StartupRefused(RuntimeError):
    """The server cannot start; the message says why and what to do."""


def database_lock_path(database: Path) -> Path:
    return database.with_name(database.name + DB_LOCK_SUFFIX)


class _OwnedFile:
    """An exclusive ``flock`` on one file that records ``pid owner`` of the process holding it."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._fd: int | None = None

    def acquire(self, owner: str) -> str | None:
        """Take the lock and record ``owner`` in the file; returns None, or, when another live process
        holds the lock, what its file records (its pid and address).

        Raises:
            StartupRefused: the lock file cannot be created or opened (the message names it).
        """
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as exc:
            raise StartupRefused(
                f"cannot open the lock file {self.path} ({exc.strerror}); check that folder's permissions"
            ) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 200, 0).decode("utf-8", "replace").strip() or "unknown process"
            os.close(fd)
            return holder
        except BaseException:
            os.close(fd)
            raise
        # The record is informational (for the refusal); written in place, the lock is the flock.
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()} {owner}\n".encode(), 0)
        self._fd = fd
        return None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def release(self) -> None:
        if self._fd is not None:
            with contextlib.suppress(OSError):
                os.ftruncate(self._fd, 0)
            os.close(self._fd)
            self._fd = None


class ServerLock:
    """Exclusive ownership of a work folder and of a database for the life of this process (or until
    :meth:`release`)."""

    def __init__(self, work_dir: Path, database: Path) -> None:
        self.work_dir = work_dir
        self.database = database
        self._work = _OwnedFile(work_dir / LOCK_NAME)
        self._db = _OwnedFile(database_lock_path(database))

    def acquire(self, owner: str) -> None:
        """Take both locks and record ``owner`` (e.g. ``"127.0.0.1:8000"``) in them.

        Raises:
            StartupRefused: another live process holds either (its pid and address are named); nothing
                is held then.
        """
        holder = self._work.acquire(owner)
        if holder is not None:
            raise StartupRefused(
                f"work folder {self.work_dir} is in use by another LeAP Studio server "
                f"(pid and address: {holder}); stop it, or give this server another --work-dir"
            )
        try:
            holder = self._db.acquire(owner)
        except BaseException:
            self._work.release()
            raise
        if holder is not None:
            self._work.release()
            raise StartupRefused(
                f"database {self.database} is in use by another LeAP Studio server (pid and address: "
                f"{holder}); stop it, or give this server its own database (unset LEAP_DB_PATH to use "
                "<work folder>/studio.db, or point it at another file)"
            )

    @property
    def held(self) -> bool:
        return self._work.held and self._db.held

    def release(self) -> None:
        self._db.release()
        self._work.release()


def bind_socket(host: str, port: int) -> socket.socket:
    """A listening TCP socket on ``host:port`` (IPv6 when ``host`` contains a colon).

    Raises:
        StartupRefused: the address is taken or cannot be bound (the message names it).
    """
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host.strip("[]"), port))
        sock.listen(2048)
    except OSError as exc:
        sock.close()
        why = "is already in use" if exc.errno == errno.EADDRINUSE else f"cannot be bound ({exc.strerror})"
        raise StartupRefused(
            f"address {host}:{port} {why}; stop the program using it or choose another --port"
        ) from None
    sock.set_inheritable(False)
    return sock
