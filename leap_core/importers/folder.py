"""The output folder of an importer: written whole into a hidden sibling, then renamed into place.

An import takes minutes on a real recording; an interrupted one must not leave a folder that
:class:`~leap_core.datasets.kitti.KittiSequence` opens as a shorter sequence. So every file goes into a fresh
hidden sibling (``.NAME.leap-import-XXXXXXXX``) and the folder appears at its name only when complete.

An existing output folder is replaced only with ``force``, and only when it holds nothing but what an
import writes (:data:`IMPORT_ENTRIES`): ``--force`` re-imports, it never deletes a user's other files (a
``predictions/`` folder, a mistyped ``--out ~``).
"""

from __future__ import annotations

import contextlib
import os
import uuid
from collections.abc import Iterable, Iterator
from pathlib import Path

from leap_core.errors import DatasetError
from leap_core.io_utils import remove_tree

IMPORT_NOTE = "import.json"
"""Written by an importer beside the KITTI files: where the sequence came from (source, options, per-frame
source ids), so a result can be traced back to the recording."""

IMPORT_ENTRIES: frozenset[str] = frozenset(
    {
        "velodyne",
        "image_2",
        "labels",
        "calib.txt",
        "poses.txt",
        "times.txt",
        "poses_estimated.json",
        IMPORT_NOTE,
    }
)
"""What an import writes (and ``leap poses`` adds); ``force`` replaces a folder holding only these."""


def check_output(out: Path, force: bool, allowed: Iterable[str] = IMPORT_ENTRIES) -> None:
    """Refuse an output folder an import must not replace; call before the (long) conversion starts.

    Raises:
        DatasetError: ``out`` is a file; holds files and ``force`` is off; or holds an entry an import does
            not write (even with ``force``), naming it.
    """
    if out.exists() and not out.is_dir():
        raise DatasetError(out, "the output is a file, not a folder")
    entries = sorted(p.name for p in out.iterdir()) if out.is_dir() else []
    if not entries:
        return
    if not force:
        raise DatasetError(
            out,
            f"output folder is not empty ({len(entries)} entries, e.g. {entries[0]!r}); nothing was written "
            "(pass --force to replace a previous import)",
        )
    allowed = frozenset(allowed)
    foreign = [name for name in entries if name not in allowed]
    if foreign:
        raise DatasetError(
            out,
            f"holds {foreign[0]!r}, which an import does not write; even --force will not replace this "
            "folder (move it away, or import elsewhere)",
        )


@contextlib.contextmanager
def staged_output(out: Path, force: bool, allowed: Iterable[str] = IMPORT_ENTRIES) -> Iterator[Path]:
    """Yield a fresh hidden sibling of ``out`` to write into; on success it replaces ``out``.

    ``out`` is checked (:func:`check_output`) on entry and again before the swap (another process may have
    written there meanwhile). On any exception the staged folder is removed and ``out`` is untouched.
    """
    out = Path(out)
    check_output(out, force, allowed)
    out.parent.mkdir(parents=True, exist_ok=True)
    tag = uuid.uuid4().hex[:8]
    fresh = out.parent / f".{out.name}.leap-import-{tag}"
    fresh.mkdir()
    try:
        yield fresh
        check_output(out, force, allowed)
        if out.is_dir():
            stale = out.parent / f".{out.name}.leap-old-{tag}"
            os.rename(out, stale)
            os.rename(fresh, out)
            remove_tree(stale)
        else:
            os.rename(fresh, out)
    except BaseException:
        remove_tree(fresh)
        raise


__all__ = ["IMPORT_ENTRIES", "IMPORT_NOTE", "check_output", "staged_output"]
