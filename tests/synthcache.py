"""Synthetic sequences rendered once per test run and copied where a test wants them.

Rendering the demo street costs about 0.5 s a frame (mostly the camera image), and the browser and server
fixtures ask for the same few configurations many times over, in both test processes. :func:`synth_copy`
renders a configuration once into a folder that the processes of one run share (``SYNTH_CACHE_ENV``,
set by ``conftest.py``; without it, it renders in place) and copies the files. The generator is
deterministic, so a copy is byte for byte what rendering in place writes (``tests/test_synth*.py`` render
in place and check that).
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import pickle
import shutil
from pathlib import Path

from leap_core.errors import DatasetError
from leap_core.synth import SynthConfig, generate_sequence
from leap_core.synth.generator import SynthStats

SYNTH_CACHE_ENV = "LEAP_TEST_SYNTH_CACHE"
"""Folder shared by the test processes of one run (set per run by ``conftest.py``)."""


def synth_copy(root: Path, cfg: SynthConfig, sequence: str = "00", *, force: bool = False) -> SynthStats:
    """What ``generate_sequence(root, cfg, sequence, force=force)`` returns and writes, rendered at most
    once per test run for each ``cfg``."""
    shared = os.environ.get(SYNTH_CACHE_ENV)
    if not shared:
        return generate_sequence(root, cfg, sequence, force=force)
    key = hashlib.sha256(repr(cfg).encode()).hexdigest()[:24]
    entry = Path(shared) / key
    done = entry / "stats.pickle"
    with (Path(shared) / f"{key}.lock").open("w") as lock:
        # The other process waits here while one renders, instead of rendering the same frames too.
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.is_file():
            stats = generate_sequence(entry, cfg, force=True)
            done.write_bytes(pickle.dumps((stats.points, stats.in_image)))
    seq_dir = Path(root) / "sequences" / sequence
    if seq_dir.exists() and any(seq_dir.iterdir()):
        if not force:
            raise DatasetError(seq_dir, "sequence folder is not empty; refusing to overwrite (use --force)")
        shutil.rmtree(seq_dir)
    shutil.copytree(entry / "sequences" / "00", seq_dir, dirs_exist_ok=True)
    points, in_image = pickle.loads(done.read_bytes())
    return SynthStats(seq_dir, points, in_image)
