"""Robustness on a real server (``python -m app.main``, real SQLite, HTTP on 127.0.0.1): a full disk, a second
server on the same work folder, a server that cannot bind, a stray module in the server's current folder
and a deleted camera image."""

from __future__ import annotations

import json
import select
import socket
import sqlite3
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import appfixtures
import httpx
import pytest
from apphelpers import wait_run
from serverproc import SMALL_DEMO, Server, free_port, make_small_street

from app.core.request_head import MAX_HEAD_BYTES

data_root = appfixtures.data_root
tiny_dataset = appfixtures.tiny_dataset

PER_FRAME_STAGES = ("00/labels2d", "00/project", "00/label_points", "00/export")
"""The run's per-frame stages of its one sequence (``00``), as its progress names them."""


def _wait(check: Callable[[], Any], timeout: float, what: str) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = check()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def _project(c: httpx.Client, dataset: Path, name: str) -> dict[str, Any]:
    r = c.post("/projects", json={"name": name, "dataset": {"kind": "folder", "path": str(dataset)}})
    assert r.status_code == 201, r.text
    return dict(r.json())


def _midway(c: httpx.Client, run_id: int) -> bool:
    """True once a per-frame stage of the run is part-way through."""
    progress = c.get(f"/runs/{run_id}/progress").json()
    assert progress["status"] in ("queued", "running"), progress
    return any(
        s["name"] in PER_FRAME_STAGES and s["status"] == "running" and 1 <= s["done"] < s["total"] - 1
        for s in progress["stages"]
    )


def _fill_database(db_path: Path, cap_bytes: int) -> sqlite3.Connection:
    """Grow the database to ``cap_bytes`` with a ballast table (another writer filling the 'disk');
    returns the connection, which later frees the space with ``DROP TABLE``."""
    conn = sqlite3.connect(db_path, timeout=30.0)
    conn.execute("CREATE TABLE ballast (b BLOB)")
    page_size = conn.execute("PRAGMA page_size").fetchone()[0]
    while conn.execute("PRAGMA page_count").fetchone()[0] * page_size < cap_bytes:
        conn.execute("INSERT INTO ballast VALUES (zeroblob(3000))")
        conn.commit()
    return conn


@pytest.mark.slow
def test_a_full_disk_fails_the_run_and_the_job_manager_lives_on(tmp_path: Path) -> None:
    """The database cannot grow (its size cap is reached, as on a full disk) while a run works: the run
    ends failed with the reason, its end is stored once space is back, /health says what is wrong, and
    Resume, Cancel, PATCH and DELETE all work afterwards without a restart."""
    data = tmp_path / "data"
    dataset = make_small_street(data / "street", 12)
    cap_mb = 1.0
    server = Server(data, extra_env={"LEAP_DB_MAX_MB": str(cap_mb)}).start()
    db_path = data / "studio" / "studio.db"
    try:
        with server.client() as c:
            project = _project(c, dataset, "full disk")
            run = c.post(f"/projects/{project['id']}/runs", json={}).json()
            _wait(lambda: _midway(c, run["id"]), 120, "a per-frame stage part-way through")
            ballast = _fill_database(db_path, int(cap_mb * 2**20))

            # The run fails with the reason; the database cannot store that yet, /health says so.
            progress = _wait(
                lambda: (p := c.get(f"/runs/{run['id']}/progress").json())["status"] == "failed" and p,
                60,
                "the run to fail",
            )
            assert "disk holding the database is full" in progress["error"], progress["error"]
            health = c.get("/health").json()
            assert health["status"] == "degraded", health
            assert health["workers_alive"] == health["workers"] == 1
            assert health["unsaved_runs"] == [run["id"]]
            assert any("not stored yet" in p and "full" in p for p in health["problems"]), health
            # The run reads as it will be stored, not as the stale "running" row.
            shown = c.get(f"/runs/{run['id']}").json()
            assert shown["status"] == "failed" and "full" in shown["error"], shown
            listed = c.get(f"/projects/{project['id']}/runs").json()["data"]
            assert [r["status"] for r in listed if r["id"] == run["id"]] == ["failed"], listed
            # Requests that need space are refused with the reason, not a 500.
            r = c.post(f"/projects/{project['id']}/runs", json={})
            assert r.status_code == 507 and "cannot store that yet" in r.json()["detail"], r.text
            r = c.post("/projects", json={"name": "x", "dataset": {"kind": "folder", "path": str(dataset)}})
            assert r.status_code == 507 and "disk holding the database is full" in r.json()["detail"], r.text

            # Space comes back: the run's end is stored without a restart, and everything works again.
            ballast.execute("DROP TABLE ballast")
            ballast.commit()
            ballast.close()
            _wait(lambda: c.get("/health").json()["unsaved_runs"] == [], 30, "the run's end to be stored")
            assert c.get("/health").json()["status"] == "ok"
            stored = c.get(f"/runs/{run['id']}").json()
            assert stored["status"] == "failed" and "full" in stored["error"] and stored["resumable"], stored

            assert c.post(f"/runs/{run['id']}/resume").status_code == 202
            resumed = wait_run(c, run["id"], 180.0, ("done", "failed"), api="")
            assert resumed["status"] == "done", resumed["error"]

            # A project without an earlier run computes every stage, so its run can be caught running.
            other = _project(c, dataset, "cancel me")
            second = c.post(f"/projects/{other['id']}/runs", json={}).json()
            _wait(lambda: _midway(c, second["id"]), 120, "the second run part-way through")
            assert c.post(f"/runs/{second['id']}/cancel").status_code == 200
            assert wait_run(c, second["id"], 60.0, ("cancelled", "done", "failed"), api="")["status"] == (
                "cancelled"
            )
            assert c.patch(f"/projects/{project['id']}", json={"name": "renamed"}).status_code == 200
            assert c.delete(f"/projects/{project['id']}").status_code == 200
    finally:
        server.stop()


@pytest.mark.slow
def test_a_run_refuses_to_start_below_the_free_space_threshold(tmp_path: Path, tiny_dataset: Path) -> None:
    """min_free_disk_mb above the disk's free space: a clear 507 and no run row; /health reports it."""
    data = tiny_dataset.parents[2]
    server = Server(data, extra_env={"LEAP_MIN_FREE_DISK_MB": str(2**40)}).start()
    try:
        with server.client() as c:
            project = _project(c, tiny_dataset, "low disk")
            r = c.post(f"/projects/{project['id']}/runs", json={})
            assert r.status_code == 507, r.text
            assert "MiB free" in r.json()["detail"] and "min_free_disk_mb" in r.json()["detail"]
            assert c.get(f"/projects/{project['id']}/runs").json()["count"] == 0
            health = c.get("/health").json()
            assert health["status"] == "degraded" and health["disk_free_mb"] > 0
            assert any("min_free_disk_mb" in p for p in health["problems"])
    finally:
        server.stop()


@pytest.mark.slow
def test_a_second_server_on_the_same_work_folder_is_refused(tmp_path: Path) -> None:
    """The second server exits with a message naming the first; the first one's run is untouched and its
    Cancel still works (a second server used to mark it interrupted, then Cancel answered 409)."""
    data = tmp_path / "data"
    data.mkdir()
    # The seeded demo project's first run generates a long demo street first: a run that stays active.
    synth = json.dumps({**SMALL_DEMO, "frames": 300})
    first = Server(data, extra_env={"LEAP_SEED_DEMO": "true", "LEAP_DEMO_SYNTH": synth}).start()
    try:
        with first.client() as c:
            run = _wait(lambda: c.get("/projects/1/runs").json()["data"], 30, "the demo run")[0]
            _wait(lambda: c.get(f"/runs/{run['id']}").json()["status"] == "running", 60, "the run to start")
            code, output = Server(data, log=tmp_path / "second.log").refused(timeout=45)
            assert code not in (None, 0), output
            assert "in use by another LeAP Studio server" in output and str(first.port) in output, output

            assert c.get(f"/runs/{run['id']}").json()["status"] == "running"
            assert c.post(f"/runs/{run['id']}/cancel").status_code == 200
            assert wait_run(c, run["id"], 60.0, ("cancelled", "done", "failed"), api="")["status"] == (
                "cancelled"
            )
    finally:
        first.stop()


@pytest.mark.slow
def test_a_server_that_cannot_bind_its_port_changes_nothing(tmp_path: Path, tiny_dataset: Path) -> None:
    """A server whose port is taken exits with a message before it opens the database: a run left
    running (by a server that was killed) stays as it is."""
    data = tiny_dataset.parents[2]
    server = Server(data).start()
    try:
        with server.client() as c:
            project = _project(c, tiny_dataset, "bind")
            run = c.post(f"/projects/{project['id']}/runs", json={}).json()
            wait_run(c, run["id"], 120.0, ("done", "failed"), api="")
    finally:
        server.stop()
    db_path = data / "studio" / "studio.db"
    with sqlite3.connect(db_path) as conn:
        conn.execute("UPDATE runs SET status = 'running', finished_at = NULL WHERE id = ?", [run["id"]])
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        code, output = Server(data, port=port, log=tmp_path / "unbound.log").refused(timeout=45)
    assert code not in (None, 0), output
    assert f"127.0.0.1:{port} is already in use" in output, output
    with sqlite3.connect(db_path) as conn:
        status = conn.execute("SELECT status FROM runs WHERE id = ?", [run["id"]]).fetchone()[0]
    assert status == "running"


@pytest.mark.slow
def test_a_stray_module_in_the_server_folder_does_not_reach_the_worker(
    tmp_path: Path, tiny_dataset: Path
) -> None:
    """The server runs in a folder holding a broken ``numbers.py``: the worker used to import it and the
    run failed with 'exit code 1'."""
    data = tiny_dataset.parents[2]
    stray = tmp_path / "cwd"
    stray.mkdir()
    (stray / "numbers.py").write_text('raise ImportError("the stray numbers.py was imported")\n')
    server = Server(data, cwd=stray, port=free_port()).start()
    try:
        with server.client() as c:
            project = _project(c, tiny_dataset, "stray")
            run = c.post(f"/projects/{project['id']}/runs", json={}).json()
            run = wait_run(c, run["id"], 120.0, ("done", "failed"), api="")
            assert run["status"] == "done", run["error"]
    finally:
        server.stop()


@pytest.mark.slow
def test_a_deleted_image_gives_the_run_a_warning(tiny_dataset: Path) -> None:
    """One camera image deleted: the simulated labeler's run still ends done (it reads 2D ground truth),
    but now with a warning naming the frame, in its progress and in its log (both shown by the UI)."""
    data = tiny_dataset.parents[2]
    image = sorted((tiny_dataset / "image_2").iterdir())[1]
    image.unlink()
    server = Server(data).start()
    try:
        with server.client() as c:
            project = _project(c, tiny_dataset, "no image")
            run = c.post(f"/projects/{project['id']}/runs", json={}).json()
            run = wait_run(c, run["id"], 120.0, ("done", "failed"), api="")
            assert run["status"] == "done", run["error"]
            # (The run also names the classes its 2D ground truth lacks: test_runs_api covers those.)
            warnings = [w for w in run["progress"]["warnings"] if "camera image" in w]
            assert len(warnings) == 1 and "1 of 4 frames have no camera image" in warnings[0], warnings
            assert image.stem in warnings[0]
            log = c.get(f"/runs/{run['id']}/logs").json()["text"]
            assert "no camera image" in log and image.stem in log
    finally:
        server.stop()


@pytest.mark.slow
def test_a_second_server_on_the_same_database_is_refused(tmp_path: Path, tiny_dataset: Path) -> None:
    """``LEAP_DB_PATH`` lets a server keep its database outside its work folder. A second server with a
    work folder of its own but the first one's database exits with a message naming the first server and
    the fix, without opening the database: the first one's active runs stay as they are (a second server
    used to mark them interrupted)."""
    data = tiny_dataset.parents[2]
    db_path = data / "studio" / "studio.db"
    first = Server(data).start()
    try:
        with first.client() as c:
            project = _project(c, tiny_dataset, "shared database")
            run = c.post(f"/projects/{project['id']}/runs", json={}).json()
            wait_run(c, run["id"], 120.0, ("done", "failed"), api="")
            # Active as far as the database says: what a second server's start-up would mark interrupted.
            with sqlite3.connect(db_path) as conn:
                conn.execute(
                    "UPDATE runs SET status = 'running', finished_at = NULL WHERE id = ?", [run["id"]]
                )
            second = Server(
                data,
                extra_env={"LEAP_DB_PATH": str(db_path), "LEAP_WORK_DIR": str(tmp_path / "own-work")},
                log=tmp_path / "second.log",
            )
            code, output = second.refused(timeout=45)
            assert code not in (None, 0), output
            assert f"database {db_path} is in use by another LeAP Studio server" in output, output
            assert str(first.port) in output and "LEAP_DB_PATH" in output, output
            with sqlite3.connect(db_path) as conn:
                status = conn.execute("SELECT status FROM runs WHERE id = ?", [run["id"]]).fetchone()[0]
            assert status == "running"
    finally:
        first.stop()


def _closed_after(s: socket.socket, trickle: bytes = b"", timeout: float = 60.0) -> tuple[bytes, bool]:
    """Read from ``s`` until the server closes it, sending one byte of ``trickle`` (cyclically) every
    0.1 s meanwhile: ``(what the server sent, True)``, or ``(..., False)`` when it was still open after
    ``timeout`` seconds. A reset counts as closed."""
    answer, sent = b"", 0
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        readable, _, _ = select.select([s], [], [], 0.1)
        try:
            if readable:
                part = s.recv(65536)
                if not part:
                    return answer, True
                answer += part
            elif trickle:
                s.sendall(trickle[sent % len(trickle) :][:1])
                sent += 1
        except (BrokenPipeError, ConnectionResetError):
            return answer, True
    return answer, False


def _response(s: socket.socket) -> bytes:
    """One whole response (head and ``content-length`` bytes of body) read from ``s``."""
    data = b""
    while b"\r\n\r\n" not in data:
        part = s.recv(65536)
        assert part, data
        data += part
    head, body = data.split(b"\r\n\r\n", 1)
    length = next(
        int(line.split(b":")[1])
        for line in head.split(b"\r\n")
        if line.lower().startswith(b"content-length:")
    )
    while len(body) < length:
        part = s.recv(65536)
        assert part, data
        body += part
    return head + b"\r\n\r\n" + body


@pytest.mark.slow
def test_a_request_head_sent_slowly_or_too_long_is_cut_off(tmp_path: Path) -> None:
    """A client that sends part of a request head and keeps the connection open (a byte now and then, or
    nothing) is disconnected once ``LEAP_REQUEST_HEAD_TIMEOUT_S`` has passed, with 408 when it sent part of
    a head; a head past the size limit gets 431. Requests sent in one go are served as before."""
    data = tmp_path / "data"
    data.mkdir()
    server = Server(data, extra_env={"LEAP_REQUEST_HEAD_TIMEOUT_S": "1", "LEAP_PREWARM_WORKERS": "false"})
    server.start()
    head = b"GET /api/v1/health HTTP/1.1\r\nHost: 127.0.0.1\r\n"
    try:
        with socket.create_connection(("127.0.0.1", server.port), timeout=60) as s:
            s.sendall(head)
            answer, closed = _closed_after(s)
        assert closed and answer.startswith(b"HTTP/1.1 408 Request Timeout\r\n"), answer
        with socket.create_connection(("127.0.0.1", server.port), timeout=60) as s:
            s.sendall(head)
            answer, closed = _closed_after(s, trickle=b"X-Slow: yes\r\n")
        assert closed and (answer == b"" or answer.startswith(b"HTTP/1.1 408 ")), answer
        with socket.create_connection(("127.0.0.1", server.port), timeout=60) as s:
            answer, closed = _closed_after(s)
        assert closed and answer == b""
        with socket.create_connection(("127.0.0.1", server.port), timeout=60) as s:
            # One byte over the limit and nothing after it: the server has read everything when it closes.
            big = head + b"X-Big: "
            s.sendall(big + b"a" * (MAX_HEAD_BYTES + 1 - len(big)))
            answer, closed = _closed_after(s)
        assert closed and answer.startswith(b"HTTP/1.1 431 "), answer

        # A keep-alive connection serves several requests, each head sent in one go.
        with socket.create_connection(("127.0.0.1", server.port), timeout=60) as s:
            for _ in range(3):
                s.sendall(head + b"\r\n")
                assert _response(s).startswith(b"HTTP/1.1 200 OK\r\n")
        with server.client() as c:
            assert c.get("/health").status_code == 200
    finally:
        server.stop()
