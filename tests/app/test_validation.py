"""Input validation on a real server (``python -m app.main``: real SQLite, real HTTP on 127.0.0.1).

One test per defect of the hardening probe: each sends what made the server
answer 500, take a 200 MB body, echo a 50 MB one, list a folder outside the data roots, or accept a name
that breaks paths and URLs, and checks the answer the API now gives instead.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from conftest import build_tiny_sequence
from serverproc import Server, free_port

from app.core.config import Settings

BIG = 2**63
"""One past SQLite's largest INTEGER."""


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    data = tmp_path_factory.mktemp("validation") / "data"
    data.mkdir()
    srv = Server(data, extra_env={"LEAP_PREWARM_WORKERS": "false"}).start()
    srv.data_root = data  # type: ignore[attr-defined]
    try:
        yield srv
    finally:
        srv.stop()


@pytest.fixture(scope="module")
def api(server: Server) -> Iterator[httpx.Client]:
    with server.client() as client:
        yield client


@pytest.fixture(scope="module")
def project(api: httpx.Client) -> dict[str, Any]:
    r = api.post("/projects", json={"name": "validation", "dataset": {"kind": "demo"}})
    assert r.status_code == 201, r.text
    return dict(r.json())


def raw_post(api: httpx.Client, path: str, text: str, method: str = "POST") -> httpx.Response:
    """Send ``text`` as the JSON body exactly as written (``\\ud800`` escapes, ``1e400``, ``NaN``)."""
    return api.request(method, path, content=text.encode(), headers={"content-type": "application/json"})


def assert_422(r: httpx.Response, loc: list[Any] | None = None) -> list[dict[str, Any]]:
    assert r.status_code == 422, (r.status_code, r.text[:500])
    detail = r.json()["detail"]
    if loc is not None:
        assert detail[0]["loc"] == loc, detail
    return list(detail)


# ------------------------------------------------------------------------------------------------ item 6
def test_ids_beyond_sqlite_integers_are_404_or_422(api: httpx.Client, project: dict[str, Any]) -> None:
    pid = project["id"]
    routes = [
        ("GET", "/projects/{id}"),
        ("PATCH", "/projects/{id}"),
        ("DELETE", "/projects/{id}"),
        ("GET", "/projects/{id}/classes"),
        ("GET", "/projects/{id}/runs"),
        ("POST", "/projects/{id}/runs"),
        ("GET", "/projects/{id}/viewer"),
        ("GET", "/runs/{id}"),
        ("GET", "/runs/{id}/progress"),
        ("GET", "/runs/{id}/events"),
        ("GET", "/runs/{id}/metrics"),
        ("GET", "/runs/{id}/logs"),
        ("POST", "/runs/{id}/cancel"),
        ("POST", "/runs/{id}/resume"),
        ("GET", "/runs/{id}/export.zip"),
        ("POST", "/runs/{id}/export"),
    ]
    for method, template in routes:
        body = {"name": "x"} if method == "PATCH" else ({} if method == "POST" else None)
        for bad in (BIG, 2**64 + 5, 10**30, 0, -1):
            r = api.request(method, template.format(id=bad), json=body)
            assert_422(r)
            assert r.json()["detail"][0]["loc"][0] == "path", (method, template, r.text)
        r = api.request(method, template.format(id=BIG - 1), json=body)
        assert r.status_code == 404, (method, template, r.status_code, r.text)
    # The prompt index of a class, and ids inside bodies.
    assert_422(api.delete(f"/projects/{pid}/classes/car/prompts/{BIG}"), ["path", "index"])
    assert_422(api.post(f"/projects/{pid}/viewer", json={"run_id": BIG}), ["body", "run_id"])
    assert_422(
        api.post(f"/projects/{pid}/runs", json={"frames": {"start": 0, "stop": 2**70}}),
        ["body", "frames", "stop"],
    )


def test_lone_surrogates_are_refused_with_a_422(api: httpx.Client, project: dict[str, Any]) -> None:
    pid = project["id"]
    cases = [
        ("/projects", '{"name": "\\ud800", "dataset": {"kind": "demo"}}', ["body", "name"]),
        (
            "/projects",
            '{"name": "x", "dataset": {"kind": "folder", "path": "a\\udfffb"}}',
            ["body", "dataset", "path"],
        ),
        (f"/projects/{pid}/classes/car/prompts", '{"prompt": "red \\ud83d car"}', ["body", "prompt"]),
    ]
    for path, text, loc in cases:
        detail = assert_422(raw_post(api, path, text), loc)
        assert "surrogate" in detail[0]["msg"]
    # As a key of the free-form pipeline mapping, and past a field that fails its type (the old 422
    # handler died repeating the input).
    detail = assert_422(raw_post(api, f"/projects/{pid}", '{"pipeline": {"\\udc80x": 1}}', "PATCH"))
    assert detail[0]["loc"][:2] == ["body", "pipeline"]
    assert_422(raw_post(api, "/projects", '{"name": ["\\ud800"], "dataset": 5}'))
    assert api.get(f"/projects/{pid}").json()["name"] == "validation"


def test_non_finite_and_oversized_numbers_are_refused(api: httpx.Client, project: dict[str, Any]) -> None:
    path = f"/projects/{project['id']}"
    for number in ("1e400", "-1e400", "NaN", "Infinity", "1" + "0" * 400):
        for text, loc in (
            (
                f'{{"pipeline": {{"fusion": {{"voxel_size": {number}}}}}}}',
                ["body", "pipeline", "fusion", "voxel_size"],
            ),
            (f'{{"form": {{"voxel_size": {number}}}}}', ["body", "form", "voxel_size"]),
            (
                f'{{"pipeline": {{"correction_strength": {number}}}}}',
                ["body", "pipeline", "correction_strength"],
            ),
        ):
            detail = assert_422(raw_post(api, path, text, "PATCH"), loc)
            assert len(json.dumps(detail)) < 1000
    # Nothing was stored: the project still reads (a stored inf made every later read a 500).
    r = api.get(path)
    assert r.status_code == 200 and 0 < r.json()["pipeline"]["fusion"]["voxel_size"] < 10


def test_nul_and_unusable_dataset_paths_are_422(api: httpx.Client) -> None:
    for path in ("a\u0000b", "seq\u0000/../..", "0" * 4000, "x/" + "y" * 300):
        r = api.post("/projects", json={"name": "x", "dataset": {"kind": "folder", "path": path}})
        assert_422(r, ["body", "dataset", "path"])


def _rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError("no VmRSS")


def _stream_post(
    port: int, path: str, *, declared: int | None, chunks: int, chunk: bytes
) -> tuple[int, bytes]:
    """POST up to ``chunks`` × ``chunk`` bytes over a raw socket, with ``Content-Length: declared`` or,
    when None, ``Transfer-Encoding: chunked``; stop sending as soon as the server answers."""
    framing = f"Content-Length: {declared}" if declared is not None else "Transfer-Encoding: chunked"
    with socket.create_connection(("127.0.0.1", port), timeout=30) as s:
        head = f"POST {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
        s.sendall(f"{head}{framing}\r\n\r\n".encode())
        answer = b""
        for _ in range(chunks):
            s.settimeout(0.0)
            with contextlib.suppress(BlockingIOError, ConnectionResetError):
                answer += s.recv(65536)
            s.settimeout(30)
            if answer:
                break
            data = chunk if declared is not None else f"{len(chunk):x}\r\n".encode() + chunk + b"\r\n"
            try:
                s.sendall(data)
            except (BrokenPipeError, ConnectionResetError):
                break
        while b"\r\n\r\n" not in answer or not answer.split(b"\r\n\r\n", 1)[1]:
            part = s.recv(65536)
            if not part:
                break
            answer += part
    return int(answer.split(b" ", 2)[1]), answer.split(b"\r\n\r\n", 1)[1]


def test_request_bodies_are_limited(server: Server, api: httpx.Client) -> None:
    assert server.proc is not None
    before = _rss_kib(server.proc.pid)
    chunk = b" " * 65536
    # Declared size over the limit (1 MiB by default): refused before the body is read.
    status, body = _stream_post(
        server.port, "/api/v1/projects", declared=200 * 2**20, chunks=3200, chunk=chunk
    )
    assert status == 413 and b"limit is 1048576 bytes" in body, body
    # No declared size (chunked): refused once 1 MiB has streamed in.
    status, body = _stream_post(server.port, "/api/v1/projects", declared=None, chunks=3200, chunk=chunk)
    assert status == 413 and b"limit is 1048576 bytes" in body, body
    # 400 MB were offered in all; the server held at most about one limit's worth of them.
    assert _rss_kib(server.proc.pid) - before < 60 * 1024
    # Just under the limit is read and validated as usual.
    r = api.post(
        "/projects",
        content=b'{"name": "' + b"x" * (1024 * 1024 - 100) + b'"}',
        headers={"content-type": "application/json"},
    )
    assert r.status_code == 422


def test_422_answers_repeat_only_a_short_prefix(api: httpx.Client, project: dict[str, Any]) -> None:
    big = 900 * 1024
    answers = [
        raw_post(api, "/projects", "[" + "1," * (big // 2)),  # invalid JSON
        api.post("/projects", json={"name": "n" * big, "dataset": {"kind": "demo"}}),  # too long
        api.post("/projects", json={"name": "x", "dataset": {"kind": "demo"}, "extra": ["y" * big]}),
        api.patch(f"/projects/{project['id']}", json={"pipeline": {"k" * big: 1}}),  # unknown setting
        api.patch(f"/projects/{project['id']}", json={"pipeline": {"labeler": "z" * big}}),  # bad value
        api.put(f"/projects/{project['id']}/classes", json={"classes": [{"name": "a" * big}] * 1}),
    ]
    for r in answers:
        assert r.status_code == 422, r.text[:300]
        assert len(r.content) < 3000, (len(r.content), r.text[:300])


def _sequence(folder: Path) -> Path:
    # A real (tiny) sequence: project creation refuses a folder the pipeline cannot run on.
    assert folder.parent.name == "sequences"
    return build_tiny_sequence(folder.parent.parent, n_frames=1, n_points=16).root


def test_links_out_of_the_data_roots_are_neither_listed_nor_accepted(
    server: Server, api: httpx.Client, tmp_path: Path
) -> None:
    root: Path = server.data_root  # type: ignore[attr-defined]
    outside = _sequence(tmp_path / "outside" / "sequences" / "00")
    inside = _sequence(root / "kitti" / "sequences" / "00")
    (root / "linked").symlink_to(tmp_path / "outside", target_is_directory=True)
    sneaky = root / "sneaky" / "sequences" / "00"
    sneaky.mkdir(parents=True)
    (sneaky / "velodyne").symlink_to(outside / "velodyne", target_is_directory=True)
    (root / "in-root-link").symlink_to(root / "kitti", target_is_directory=True)

    listed = {Path(d["path"]).resolve() for d in api.get("/datasets").json()["data"]}
    assert inside.resolve() in listed
    assert outside.resolve() not in listed
    assert sneaky.resolve() not in listed

    r = api.post("/projects", json={"name": "s", "dataset": {"kind": "folder", "path": str(sneaky)}})
    assert r.status_code == 403, r.text
    assert f"velodyne is a symlink to '{outside / 'velodyne'}', which is outside" in r.json()["detail"]
    # The refusal names the link on the way and where it leads, not the typed path as if it were outside.
    link, target = root / "linked", (tmp_path / "outside").resolve()
    for path, says in (
        ("linked/sequences/00", f"goes through '{link}', a symlink to '{target}', which is outside"),
        (str(link), f"'{link}' is a symlink to '{target}', which is outside the allowed data roots"),
    ):
        r = api.post("/projects", json={"name": "o", "dataset": {"kind": "folder", "path": path}})
        assert r.status_code == 403 and says in r.json()["detail"], r.text
    r = api.post("/projects", json={"name": "o", "dataset": {"kind": "folder", "path": str(tmp_path)}})
    assert r.status_code == 403 and "is outside the allowed data roots" in r.json()["detail"], r.text
    r = api.post(
        "/projects", json={"name": "i", "dataset": {"kind": "folder", "path": "in-root-link/sequences/00"}}
    )
    assert r.status_code == 201, r.text


def test_an_entry_relinked_out_of_the_roots_after_creation_stops_the_run(
    server: Server, api: httpx.Client, tmp_path: Path
) -> None:
    """The roots are checked again when a run starts: a sequence whose ``labels/`` became a link out of
    them after the project was created is refused (403 naming the entry and its target), and no run is
    created; restored, the run starts."""
    root: Path = server.data_root  # type: ignore[attr-defined]
    seq = _sequence(root / "relinked" / "sequences" / "00")
    outside = _sequence(tmp_path / "elsewhere" / "sequences" / "00")
    r = api.post("/projects", json={"name": "relinked", "dataset": {"kind": "folder", "path": str(seq)}})
    assert r.status_code == 201, r.text
    pid = r.json()["id"]
    (seq / "labels").rename(seq / "labels.kept")
    (seq / "labels").symlink_to(outside / "labels", target_is_directory=True)
    try:
        r = api.post(f"/projects/{pid}/runs", json={})
        assert r.status_code == 403, r.text
        target = (outside / "labels").resolve()
        says = f"labels is a symlink to '{target}', which is outside the allowed data roots"
        assert says in r.json()["detail"], r.text
        assert api.get(f"/projects/{pid}/runs").json()["data"] == []
    finally:
        (seq / "labels").unlink()
        (seq / "labels.kept").rename(seq / "labels")
    r = api.post(f"/projects/{pid}/runs", json={})
    assert r.status_code == 202, r.text
    assert api.post(f"/runs/{r.json()['id']}/cancel").status_code in (200, 409)


def test_symlink_loops_are_422_naming_the_field(server: Server, api: httpx.Client) -> None:
    """A path through a symbolic link loop (``Path.resolve`` raises RuntimeError for one) is refused with
    the field and the reason, wherever it is given; the dataset list skips such folders."""
    root: Path = server.data_root  # type: ignore[attr-defined]
    loop = root / "loop"
    loop.symlink_to(loop)
    good = _sequence(root / "looped" / "sequences" / "00")
    entry = _sequence(root / "entry-loop" / "sequences" / "00")
    (entry / "times.txt").unlink()
    (entry / "times.txt").symlink_to(entry / "times.txt")
    try:
        for path, says in (
            (str(loop), "is a symlink loop"),
            ("loop", "is a symlink loop"),
            (str(loop / "sequences" / "00"), f"goes through '{loop}', a symlink loop"),
        ):
            r = api.post("/projects", json={"name": "l", "dataset": {"kind": "folder", "path": path}})
            (error,) = assert_422(r, ["body", "dataset", "path"])
            assert f"dataset path '{path}' {says}" in error["msg"], error
        body = {"name": "l", "sequences": [{"path": str(good)}, {"path": str(loop), "name": "b"}]}
        (error,) = assert_422(api.post("/projects", json=body), ["body", "sequences", 1, "path"])
        assert "symlink loop" in error["msg"], error
        r = api.post("/projects", json={"name": "l", "dataset": {"kind": "folder", "path": str(entry)}})
        (error,) = assert_422(r, ["body", "dataset", "path"])
        assert "times.txt is a symlink loop" in error["msg"], error
        r = api.get("/datasets")
        assert r.status_code == 200, r.text
        listed = {d["path"] for d in r.json()["data"]}
        assert str(good) in listed and str(entry) not in listed
    finally:
        loop.unlink()
        (entry / "times.txt").unlink()


def test_values_of_another_json_type_are_refused(api: httpx.Client, project: dict[str, Any]) -> None:
    """No coercion: ``true`` is no integer, ``"2"`` and ``2.0`` no integer, ``1`` no boolean. An integer
    stays a number (the web UI sends ``Number(...)`` for a number field)."""
    pid = project["id"]
    klass = {"name": "strict", "prompts": ["strict thing"], "color": "#102030"}
    correction = {"class_name": "car", "voxel_size": 0.2, "keys": []}
    runs, classes, corrections = (
        f"/projects/{pid}/runs",
        f"/projects/{pid}/classes",
        f"/projects/{pid}/corrections",
    )
    viewer = f"/projects/{pid}/viewer"
    for method, path, body, loc in (
        ("POST", runs, {"frames": {"start": True, "stop": 2}}, ["body", "frames", "start"]),
        ("POST", runs, {"frames": {"start": 0, "stop": "2"}}, ["body", "frames", "stop"]),
        ("POST", runs, {"frames": {"start": 0.0, "stop": 2}}, ["body", "frames", "start"]),
        ("PATCH", f"/projects/{pid}", {"estimate_poses": 1}, ["body", "estimate_poses"]),
        ("PATCH", f"/projects/{pid}", {"name": 5}, ["body", "name"]),
        ("POST", classes, {**klass, "export_id": "900"}, ["body", "export_id"]),
        ("POST", classes, {**klass, "export_id": True}, ["body", "export_id"]),
        ("POST", classes, {**klass, "export_id": 900, "gt_ids": [True]}, ["body", "gt_ids", 0]),
        ("PATCH", f"{classes}/car", {"position": "1"}, ["body", "position"]),
        ("POST", corrections, {**correction, "voxel_size": "0.2"}, ["body", "voxel_size"]),
        ("POST", corrections, {**correction, "keys": [False]}, ["body", "keys", 0]),
        ("PATCH", f"{corrections}/1", {"active": 1}, ["body", "active"]),
        ("POST", "/runs/1/export", {"include_confidence": "true"}, ["body", "include_confidence"]),
        ("POST", f"{viewer}/nav/step", {"step": True}, ["body", "step"]),
        ("POST", f"{viewer}/nav/play", {"on": 0}, ["body", "on"]),
        (
            "POST",
            f"{viewer}/tools/select",
            {"tool": "box", "points": [[True, 0.5], [1, 1]]},
            ["body", "points", 0, 0],
        ),
    ):
        assert_422(api.request(method, path, json=body), loc)
    assert api.patch(f"/projects/{pid}", json={"estimate_poses": False}).status_code == 200
    r = api.post(corrections, json={**correction, "voxel_size": 1})
    assert r.status_code == 201, r.text


def test_a_correction_for_a_class_the_project_lacks_is_refused(
    api: httpx.Client, project: dict[str, Any]
) -> None:
    pid = project["id"]
    before = api.get(f"/projects/{pid}/corrections").json()["corrections"]
    body = {"class_name": "unicorn", "voxel_size": 0.2, "keys": [1, 2]}
    (error,) = assert_422(api.post(f"/projects/{pid}/corrections", json=body), ["body", "class_name"])
    names = [c["name"] for c in api.get(f"/projects/{pid}/classes").json()["data"]]
    assert "'unicorn'" in error["msg"] and ", ".join(names) in error["msg"], error
    assert api.get(f"/projects/{pid}/corrections").json()["corrections"] == before
    assert api.post(f"/projects/{pid}/corrections", json={**body, "class_name": ""}).status_code == 201


def test_control_characters_in_names_are_refused(api: httpx.Client, project: dict[str, Any]) -> None:
    pid = project["id"]
    for bad in ("a\u0000b", "bell\u0007", "two\nlines", "tab\there", "del\u007f"):
        assert_422(api.post("/projects", json={"name": bad, "dataset": {"kind": "demo"}}), ["body", "name"])
        assert_422(api.patch(f"/projects/{pid}", json={"name": bad}), ["body", "name"])
        klass = {"name": bad, "color": "#102030", "prompts": ["thing"], "export_id": 900}
        assert_422(api.post(f"/projects/{pid}/classes", json=klass), ["body", "name"])
        klass = {"name": "thing", "color": "#102030", "prompts": [bad], "export_id": 900}
        assert_422(api.post(f"/projects/{pid}/classes", json=klass), ["body", "prompts", 0])
        assert_422(api.post(f"/projects/{pid}/classes/car/prompts", json={"prompt": bad}), ["body", "prompt"])
    # In a class name given in the URL.
    assert_422(api.delete(f"/projects/{pid}/classes/ca%00r"), ["path", "name"])
    names = [c["name"] for c in api.get(f"/projects/{pid}/classes").json()["data"]]
    assert all(n.isprintable() for n in names)


def test_class_names_made_of_dots_are_refused(api: httpx.Client, project: dict[str, Any]) -> None:
    pid = project["id"]
    for bad in (".", "..", "...", "a/b"):
        klass = {"name": bad, "color": "#102030", "prompts": [f"thing {len(bad)}"], "export_id": 900}
        assert_422(api.post(f"/projects/{pid}/classes", json=klass), ["body", "name"])
        assert_422(api.patch(f"/projects/{pid}/classes/car", json={"name": bad}), ["body", "name"])
    classes = api.get(f"/projects/{pid}/classes").json()["data"]
    replaced = [{k: c[k] for k in ("name", "color", "prompts", "export_id")} for c in classes]
    replaced[0]["name"] = ".."
    assert_422(
        api.put(f"/projects/{pid}/classes", json={"classes": replaced}), ["body", "classes", 0, "name"]
    )
    # A name with dots among other characters is fine, and its URL reaches it.
    klass = {"name": "v1.2", "color": "#102030", "prompts": ["version thing"], "export_id": 901}
    assert api.post(f"/projects/{pid}/classes", json=klass).status_code == 201
    r = api.delete(f"/projects/{pid}/classes/v1.2")
    assert r.status_code == 200 and "v1.2" not in [c["name"] for c in r.json()["data"]]
    assert api.get(f"/projects/{pid}").status_code == 200  # the project itself is untouched


def test_access_tokens_need_entropy(tmp_path: Path) -> None:
    for weak, reason in (
        ("aaaaaaaaaaaa", "at least 16 characters"),
        ("aaaaaaaaaaaaaaaaaaaaaaaa", "different characters"),
        ("1234567890123456", "too easy to guess"),
        ("abc def ghi jkl mno", "without spaces"),
    ):
        with pytest.raises(ValueError, match=reason):
            Settings(host="0.0.0.0", access_token=weak, data_roots=[tmp_path])
    for strong in ("correct-horse-battery-staple", "browser-test-token-123", "Xq7!pL2#vR9$kM4w"):
        assert Settings(host="0.0.0.0", access_token=strong, data_roots=[tmp_path]).token == strong


@pytest.mark.slow
def test_a_weak_token_stops_the_server_and_new_token_makes_a_strong_one(tmp_path: Path) -> None:
    data = tmp_path / "data"
    data.mkdir()
    env = {**os.environ, "LEAP_PREWARM_WORKERS": "false"}
    base = [
        sys.executable,
        "-m",
        "app.cli",
        "serve",
        "--data-root",
        str(data),
        "--work-dir",
        str(data / "studio"),
        "--no-demo",
    ]
    weak = subprocess.run(
        [*base, "--token", "aaaaaaaaaaaa"], env=env, capture_output=True, text=True, timeout=120, check=False
    )
    assert weak.returncode == 2 and "access_token must have at least 16 characters" in weak.stderr

    port = free_port()
    proc = subprocess.Popen(
        [*base, "--new-token", "--port", str(port)],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        token = line.rsplit(": ", 1)[-1].strip()
        assert line.startswith("access token") and len(token) >= 40, line
        url = f"http://127.0.0.1:{port}/api/v1/health"
        deadline = time.monotonic() + 90
        while True:
            try:
                r = httpx.get(url, headers={"X-Leap-Token": token}, timeout=1.0)
                break
            except httpx.HTTPError:
                assert time.monotonic() < deadline and proc.poll() is None, "server did not start"
                time.sleep(0.2)
        assert r.status_code == 200 and r.json()["auth_required"] is True
        assert httpx.get(url, timeout=5).status_code == 403
    finally:
        proc.send_signal(2)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


def test_openapi_declares_every_error_status(api: httpx.Client) -> None:
    schema = api.get("/openapi.json").json()
    assert len(schema["paths"]) >= 20
    for path, operations in schema["paths"].items():
        for method, op in operations.items():
            declared = set(op["responses"])
            assert {"400", "403", "413", "422"} <= declared, (method, path, declared)
            if "{" in path:
                assert "404" in declared, (method, path, declared)
