"""How ``former-runs.tar.gz`` was made: run folders and an app database written by the version of LeAP
Studio before every run had one shape (git 108b224), which kept a run of one sequence's files directly in
its run folder and called a run of several ``multi.json``. tests/test_run_migration.py reads the archive;
this script only runs against that version (from its checkout: ``python tests/data/make_former_runs.py
OUT.tar.gz``), so the archive records what it wrote.

The archive holds, under ``former/`` (``root.txt`` names the absolute folder it was written in, which the
test replaces by its own):

- ``data/street/sequences/{00,01}``: two small synthetic streets (3 and 2 frames, 8,640 rays a scan, with
  ground truth and 2D ground truth);
- ``cli/single``: ``leap run`` of 00 with a 3D-CN round of a small network;
- ``cli/multi``: ``leap run`` of 00 and 01 (a run of several sequences, no 3D-CN);
- ``studio/``: the app's work folder: its database and run folders of a project on 00 (two runs) and a
  project on 00 and 01 (one run), with a correction made on each.
"""

from __future__ import annotations

import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))

CN = """
pipeline:
  consistency:
    enabled: true
    iterations: 1
    device: cpu
    num_threads: 1
    min_steps: 4
    points_per_scan: 1000
    backbone: {channels: 8, layers: 1}
"""


def main(out: Path) -> None:
    from test_pipeline import make_street  # the former version's test data

    from app import crud
    from app.core.config import Settings
    from app.core.db import init_db, open_db
    from app.jobs.manager import JobManager
    from leap_core.config import config_to_dict
    from leap_core.presets import builtin_preset

    base = Path(tempfile.mkdtemp(prefix="leap-former-")) / "former"
    data = base / "data" / "street" / "sequences"
    make_street(data / "00", n_frames=3)
    make_street(data / "01", n_frames=2, step=2.0)
    leap = [sys.executable, "-m", "app.cli"]
    project_file = base / "small-3dcn.yaml"
    project_file.write_text((ROOT / "projects" / "semantickitti.yaml").read_text() + CN)
    subprocess.run(
        [*leap, "run", data / "00", "--project-file", project_file, "--out", base / "cli" / "single"],
        check=True,
    )
    subprocess.run([*leap, "run", data / "00", data / "01", "--out", base / "cli" / "multi"], check=True)

    settings = Settings(work_dir=base / "studio", data_roots=[base / "data"], seed_demo=False)
    init_db(settings.database)
    preset = builtin_preset("semantickitti")
    pipeline = config_to_dict(preset.pipeline)
    with open_db(settings.database) as db:
        one = crud.create_project(
            db,
            name="one street",
            dataset_kind="folder",
            dataset_path=str(data / "00"),
            schema=preset.schema.to_dict(),
            pipeline=pipeline,
        )
        two = crud.create_project(
            db,
            name="two streets",
            dataset_kind="folder",
            dataset_path=str(data / "00"),
            schema=preset.schema.to_dict(),
            pipeline=pipeline,
            sequences=[("00", str(data / "00")), ("01", str(data / "01"))],
        )
    manager = JobManager(settings)
    for project, runs in ((one, 2), (two, 1)):
        for i in range(runs):
            run = manager.start_run(project["id"])
            assert manager.run_now(run["id"]) == "done"
            if i == 0:
                with open_db(settings.database) as db:
                    grid = np.load(
                        Path(run["run_dir"]) / ("grid.npz" if project is one else "sequences/00/grid.npz")
                    )
                    crud.add_correction(
                        db,
                        project_id=project["id"],
                        class_name="vegetation",
                        voxel_size=0.2,
                        keys=grid["keys"][:5],
                        author="api",
                        sequence="00",
                    )
    (base / "root.txt").write_text(str(base))
    with tarfile.open(out, "w:gz") as tar:
        tar.add(base, arcname="former")
    print(f"wrote {out} ({out.stat().st_size} bytes) from {base}")


if __name__ == "__main__":
    main(Path(sys.argv[1]).resolve())
