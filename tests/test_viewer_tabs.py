"""A viewer session per browser tab over one project's shared state, and reviewers splitting the queue.

Real SQLite, real viser servers (one per tab) on a tiny hand-built run (tests/test_viewer_logic.py's
``review_store``); no browser (tests/browser/test_viewer_tabs_ui.py drives two real tabs).
"""

from __future__ import annotations

import shutil
import time
from datetime import datetime, timedelta, timezone

import numpy as np
import pytest
from test_viewer_logic import review_store

from app import crud, reviewers
from app.core.db import open_db
from app.viewer.manager import ViewerManager
from app.viewer.records import Selection, SessionConfig

__all__ = ["review_store"]  # the fixture, found by name


def _wait(check, timeout: float = 5.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if check():
            return True
        time.sleep(0.02)
    return bool(check())


def _manager(settings) -> ViewerManager:
    return ViewerManager(settings, config=SessionConfig(poll_interval_s=0.1), tab_idle_s=600)


def test_tabs_browse_apart_share_arrays_and_push_corrections(review_store) -> None:
    settings, pid, _, _, _ = review_store
    viewers = _manager(settings)
    try:
        one = viewers.open(pid, reviewer="ana")
        two = viewers.open(pid, reviewer="ben")
        a, b = viewers.get(pid, one.tab), viewers.get(pid, two.tab)
        assert a is not None and b is not None and a is not b and one.port != two.port
        assert viewers.get(pid) is b  # no tab named: the one opened last
        # The big arrays are one copy for both tabs.
        assert a.grid is b.grid and a.outputs is b.outputs
        assert a.label is b.label and a.conf is b.conf
        # Each tab browses on its own.
        a.player.show_scan(0)
        b.player.show_scan(2)
        assert (a.player.frame_pos, b.player.frame_pos) == (0, 2)
        assert a.shared.scan_view is not None and b.shared.scan_view is not None
        assert a.shared.scan_view.frame_id != b.shared.scan_view.frame_id
        # A correction in one tab reaches the other at once, and names its reviewer.
        names = a.class_names()
        rows = np.flatnonzero(a.label != names.index("building"))[:5]
        b.tools._set_selection(np.arange(3, dtype=np.int64), "map", None, False)  # b's own selection
        cid = a.corrections.assign_selection("building", selection=Selection(rows))
        assert cid is not None
        assert _wait(lambda: bool((b.label[rows] == names.index("building")).all()), 2.0)
        assert a.label is b.label  # still one copy after the push
        assert b.shared.selection.rows.tolist() == [0, 1, 2]  # the push leaves b's selection alone
        assert (a.player.frame_pos, b.player.frame_pos) == (0, 2)
        with open_db(settings.database) as db:
            assert crud.get_correction(db, cid).reviewer == "ana"
        # Undo in the other tab's owner is pushed too.
        a.corrections.undo()
        assert _wait(lambda: not bool(b.corrected[rows].any()), 2.0)
    finally:
        viewers.close_all()


def test_tabs_follow_a_run_started_elsewhere_unless_they_stay(review_store) -> None:
    settings, pid, run_id, _, _ = review_store
    viewers = _manager(settings)
    try:
        follow = viewers.get(pid, viewers.open(pid).tab)
        stay = viewers.get(pid, viewers.open(pid).tab)
        assert follow is not None and stay is not None
        stay.set_stay_on_run(True)
        with open_db(settings.database) as db:
            old = crud.require_run(db, run_id)
            new = crud.create_run(db, project_id=pid, params=old.params, runs_dir=settings.runs_dir)
            crud.update_run(db, new.id, status="running")
        # A run queued outside the viewer (the project page, the API) is followed by every tab.
        assert _wait(lambda: follow.runs.watched_run == new.id and stay.runs.watched_run == new.id)
        done = new.sequence_layout("00").folder
        shutil.copytree(old.sequence_layout("00").folder, done, dirs_exist_ok=True)
        with open_db(settings.database) as db:
            crud.update_run(db, new.id, status="done")
        assert _wait(lambda: follow.run is not None and follow.run.run_id == new.id)
        assert stay.run is not None and stay.run.run_id == run_id
        assert _wait(lambda: stay.newer_run is not None and stay.newer_run.run_id == new.id)
        stay.set_stay_on_run(False)  # unticked: the newer run loads, from the copy the other tab read
        assert stay.run is not None and stay.run.run_id == new.id and stay.grid is follow.grid
        # A run whose stages were all reused finishes between two looks of the follower: still loaded.
        with open_db(settings.database) as db:
            quick = crud.create_run(db, project_id=pid, params=old.params, runs_dir=settings.runs_dir)
            shutil.copytree(old.sequence_layout("00").folder, quick.sequence_layout("00").folder)
            crud.update_run(db, quick.id, status="done")
        assert _wait(lambda: follow.run is not None and follow.run.run_id == quick.id)
        assert _wait(lambda: stay.run is not None and stay.run.run_id == quick.id)
    finally:
        viewers.close_all()


def test_an_idle_tab_is_closed(review_store) -> None:
    settings, pid, _, _, _ = review_store
    viewers = ViewerManager(settings, config=SessionConfig(poll_interval_s=0.05), tab_idle_s=0.2)
    try:
        info = viewers.open(pid)
        # No browser ever connects: the tab frees its server once idle.
        assert _wait(lambda: viewers.get(pid, info.tab) is None, 5.0)
    finally:
        viewers.close_all()


def test_an_idle_viewer_reads_its_runs_only_when_one_changes(review_store) -> None:
    """With the app's job manager, the project's follower sleeps until a run changes: no look at the
    database in a window without events (a timer that read it every interval cost each idle tab a steady
    share of a core), and a run the manager reports reaches the tab at once."""
    from app.jobs.manager import JobManager

    settings, pid, run_id, _, _ = review_store
    jobs = JobManager(settings)
    viewers = ViewerManager(settings, jobs, config=SessionConfig(poll_interval_s=0.05), tab_idle_s=600)
    try:
        tab = viewers.get(pid, viewers.open(pid).tab)
        viewer = viewers.viewer(pid)
        assert tab is not None and viewer is not None
        time.sleep(1.0)  # 20 intervals without an event
        assert viewer.looks == 0
        with open_db(settings.database) as db:
            old = crud.require_run(db, run_id)
            new = crud.create_run(db, project_id=pid, params=old.params, runs_dir=settings.runs_dir)
            crud.update_run(db, new.id, status="running")
        jobs.changes.notify(new.id)  # what the manager does when it queues or advances a run
        assert _wait(lambda: tab.runs.watched_run == new.id, 2.0)
        assert viewer.looks == 1
    finally:
        viewers.close_all()


def _queue(settings, pid: int, n: int = 8) -> list[str]:
    regions = [(f"4m:{i},0,0", f"sig{i}") for i in range(n)]
    with open_db(settings.database) as db:
        crud.save_review_queue(db, pid, "confidence", None, regions)
    return [r for r, _ in regions]


def test_reviewers_claim_disjoint_batches_that_expire_or_are_released(review_store) -> None:
    settings, pid, _, _, _ = review_store
    ids = _queue(settings, pid)
    t0 = datetime.now(timezone.utc)
    with open_db(settings.database) as db:
        with pytest.raises(Exception, match="No disagreement review queue"):
            reviewers.claim_regions(db, pid, reviewer="ana", kind="disagreement", count=3)
        crud.set_review_mark(db, pid, region=ids[0], signature="sig0", state="accepted", reviewer="ana")
        ana = reviewers.claim_regions(db, pid, reviewer="ana", kind="confidence", count=3, now=t0)
        ben = reviewers.claim_regions(db, pid, reviewer="ben", kind="confidence", count=3, now=t0)
        assert ana == ids[1:4] and ben == ids[4:7]  # disjoint; the reviewed region is not handed out
        # Claiming again renews and tops up rather than taking more.
        assert reviewers.claim_regions(db, pid, reviewer="ana", kind="confidence", count=3, now=t0) == ana
        later = t0 + timedelta(seconds=reviewers.CLAIM_TTL_S + 1)
        # Expired claims are free for the others.
        carl = reviewers.claim_regions(db, pid, reviewer="carl", kind="confidence", count=4, now=later)
        assert carl == ids[1:5]
        assert reviewers.release_claims(db, pid, reviewer="carl") == 4
        assert reviewers.active_claims(db, pid, now=later) == {}
        reviewers.claim_regions(db, pid, reviewer="ben", kind="confidence", count=2)
        crud.add_correction(
            db, project_id=pid, class_name="car", voxel_size=0.5, keys=[1, 2], author="viewer", reviewer="ben"
        )
        progress = {p.reviewer: p for p in reviewers.reviewer_progress(db, pid)}
    assert progress["ana"].accepted == 1 and progress["ana"].claimed == 0
    assert progress["ben"].corrections == 1 and progress["ben"].claimed == 2


def test_the_viewer_skips_regions_another_reviewer_claimed(review_store) -> None:
    settings, pid, _, _, _ = review_store
    # Every voxel a candidate, in 1 m cells: the tiny run gives a queue of several regions.
    config = SessionConfig(poll_interval_s=0.1, queue_share=1.0, queue_cell=1.0, queue_min_count=1)
    viewers = ViewerManager(settings, config=config, tab_idle_s=600)
    try:
        session = viewers.get(pid, viewers.open(pid, reviewer="ben").tab)
        assert session is not None
        regions = session.queue.build_queue("confidence")
        assert len(regions) >= 2, "the tiny run must give a queue of several regions"
        with open_db(settings.database) as db:
            held = reviewers.claim_regions(db, pid, reviewer="ana", kind="confidence", count=len(regions) - 1)
        seen = {session.queue.next_region().id for _ in range(2 * len(regions))}  # type: ignore[union-attr]
        assert seen == {r.id for r in regions} - set(held)
    finally:
        viewers.close_all()


def test_reviewer_routes_claim_release_and_report(review_store) -> None:
    from fastapi.testclient import TestClient

    from app.main import create_app

    settings, pid, _, _, _ = review_store
    with TestClient(create_app(settings), base_url="http://127.0.0.1") as client:
        api = f"/api/v1/projects/{pid}"
        r = client.post(f"{api}/review/claims", json={"reviewer": "ana", "count": 2})
        assert r.status_code == 409 and "open the 3D viewer" in r.json()["detail"]
        ids = _queue(settings, pid, 4)
        assert client.post(f"{api}/review/claims", json={"reviewer": "", "count": 2}).status_code == 422
        assert client.post(f"{api}/review/claims", json={"reviewer": "ana", "count": 0}).status_code == 422
        r = client.post(f"{api}/review/claims", json={"reviewer": "ana", "count": 2})
        assert r.status_code == 200 and r.json()["regions"] == ids[:2]
        rows = client.get(f"{api}/reviewers").json()["data"]
        assert rows == [{"reviewer": "ana", "accepted": 0, "skipped": 0, "corrections": 0, "claimed": 2}]
        assert client.post(f"{api}/review/claims/release", json={"reviewer": "ana"}).json() == {"released": 2}
        # A viewer route naming a tab that is not one is refused before any lookup.
        assert client.get(f"{api}/viewer/nav?tab=..%2F..").status_code == 422
        opened = client.post(f"{api}/viewer", json={"reviewer": "ana"}).json()
        assert client.get(f"{api}/viewer/nav?tab={opened['tab']}").status_code == 200
        assert client.get(f"{api}/viewer/nav?tab=AAAAAAAAAAAA").status_code == 404
        assert client.get(f"{api}/viewer/tabs/AAAAAAAAAAAA/client/").status_code == 404
        # A link on a tab's page (the scan image) names its tab by the page it is on.
        later = client.post(f"{api}/viewer", json={}).json()
        viewers = client.app.state.viewers
        viewers.get(pid, opened["tab"]).player.show_scan(0)
        viewers.get(pid, later["tab"]).player.show_scan(2)
        page = {"Referer": f"http://127.0.0.1{opened['url']}"}
        assert client.get(f"{api}/viewer/nav", headers=page).json()["pos"] == 0
        assert client.get(f"{api}/viewer/nav").json()["pos"] == 2  # no tab named: the one opened last


def test_migration_9_keeps_existing_corrections_and_marks_unnamed(tmp_path) -> None:
    from app.core import db as dbmod

    path = tmp_path / "old.db"
    with dbmod.open_db(path) as db:
        db.execute(
            "CREATE TABLE schema_version (version INTEGER PRIMARY KEY, description TEXT NOT NULL, "
            "applied_at TEXT NOT NULL)"
        )
        for number, description, apply in dbmod.MIGRATIONS:
            if number <= 8:
                apply(db)
                db.execute("INSERT INTO schema_version VALUES (?, ?, 'then')", [number, description])
        db.execute(
            "INSERT INTO projects (name, created_at, updated_at, dataset_kind, dataset_path, schema_json, "
            "pipeline_json) VALUES ('p', 'then', 'then', 'folder', '/x', '{}', '{}')"
        )
        pid = db.execute("SELECT id FROM projects").fetchone()[0]
        db.execute(
            "INSERT INTO project_sequences (project_id, position, name, dataset_path) "
            "VALUES (?, 0, 'x', '/x')",
            [pid],
        )
        db.execute(
            "INSERT INTO corrections (project_id, created_at, class_name, voxel_size, keys, active, scope, "
            "author, sequence) VALUES (?, 'then', 'car', 0.5, x'', 1, 'map', 'viewer', 'x')",
            [pid],
        )
        db.execute(
            "INSERT INTO review_marks (project_id, region, signature, state, run_id, updated_at) "
            "VALUES (?, 'x/4m:0,0,0', 's', 'accepted', NULL, 'then')",
            [pid],
        )
    assert dbmod.init_db(path) == dbmod.SCHEMA_VERSION >= 9
    with dbmod.open_db(path) as db:
        assert "review_claims" in db.table_names()
        (correction,) = crud.list_corrections(db, pid)
        assert correction.reviewer is None and correction.author == "viewer"
        assert reviewers.reviewer_progress(db, pid) == []  # unnamed work is nobody's
        crud.set_review_mark(db, pid, region="4m:0,0,0", signature="s", state="skipped", reviewer="ana")
        assert [(p.reviewer, p.skipped) for p in reviewers.reviewer_progress(db, pid)] == [("ana", 1)]


def test_a_review_mark_in_one_tab_shows_in_the_others(review_store) -> None:
    settings, pid, _, _, _ = review_store
    config = SessionConfig(poll_interval_s=0.1, queue_share=1.0, queue_cell=1.0, queue_min_count=1)
    viewers = ViewerManager(settings, config=config, tab_idle_s=600)
    try:
        a = viewers.get(pid, viewers.open(pid, reviewer="ana").tab)
        b = viewers.get(pid, viewers.open(pid, reviewer="ben").tab)
        assert a is not None and b is not None
        total = len(a.queue.build_queue("confidence"))
        assert len(b.queue.build_queue("confidence")) == total
        region = a.queue.next_region()
        assert region is not None and b.queue.focus is None  # the focus is tab A's alone
        a.queue.mark_region("accepted")
        assert b.queue.review_progress()["reviewed"] == 1
        assert b.panel.review.progress.content.startswith(f"1 / {total} reviewed")
        with open_db(settings.database) as db:
            assert [(p.reviewer, p.accepted) for p in reviewers.reviewer_progress(db, pid)] == [("ana", 1)]
    finally:
        viewers.close_all()
