"""The run folders and app work folder an earlier version wrote (``tests/data/former-runs.tar.gz``, made by
``tests/data/make_former_runs.py``), unpacked for a test with its recorded absolute paths pointing at the
test's folder."""

from __future__ import annotations

import sqlite3
import tarfile
from pathlib import Path

import pytest

ARCHIVE = Path(__file__).resolve().parent / "data" / "former-runs.tar.gz"


@pytest.fixture
def former(tmp_path: Path) -> Path:
    """The archive unpacked into ``tmp_path/former``, its recorded paths pointing there."""
    with tarfile.open(ARCHIVE) as tar:
        tar.extractall(tmp_path, filter="data")
    root = tmp_path / "former"
    old = (root / "root.txt").read_text().strip()
    for text_file in [*root.glob("cli/**/multi.json"), *root.glob("studio/runs/**/params.json")]:
        text_file.write_text(text_file.read_text().replace(old, str(root)))
    with sqlite3.connect(root / "studio" / "studio.db") as db:
        for table, column in (
            ("projects", "dataset_path"),
            ("project_sequences", "dataset_path"),
            ("runs", "run_dir"),
            ("runs", "params_json"),
        ):
            db.execute(f"UPDATE {table} SET {column} = replace({column}, ?, ?)", [old, str(root)])
    return root
