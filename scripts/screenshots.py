"""Refresh the README's viewer screenshots (docs/images/review-inspect.png, review-shortcuts.png).

The browser test tests/browser/test_viewer_nav.py takes them at 1280×720 on the demo project (the viewer
with a clicked voxel's Inspect section open, and the ``?`` shortcut overlay) into test-artifacts/; this
script runs that test and stores the two images, reduced to a 256-colour palette so that each stays well
under 300 KB.

Usage (from the repository root, Chromium at /usr/bin/chromium):

    python scripts/screenshots.py            # run the browser test, then copy
    python scripts/screenshots.py --no-run   # copy what the last test run left in test-artifacts/
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
SHOTS = ("review-inspect.png", "review-shortcuts.png")
MAX_BYTES = 300_000


def copy_shot(name: str, source: Path, target: Path) -> int:
    """Write ``source/name`` as a palette PNG to ``target/name`` (temp file, then rename); returns bytes."""
    src = source / name
    if not src.is_file():
        raise SystemExit(f"{src} is missing: run tests/browser/test_viewer_nav.py first")
    target.mkdir(parents=True, exist_ok=True)
    out = target / name
    tmp = out.with_suffix(".tmp.png")
    with Image.open(src) as im:
        im.convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT).save(tmp, optimize=True)
    tmp.replace(out)
    size = out.stat().st_size
    if size > MAX_BYTES:
        raise SystemExit(f"{out} is {size:,} bytes, over the {MAX_BYTES:,} byte budget")
    return size


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-run", action="store_true", help="only copy the last test run's screenshots")
    args = parser.parse_args(argv)
    if not args.no_run:
        test = "tests/browser/test_viewer_nav.py"
        cmd = [sys.executable, "-m", "pytest", "-q", test, "-k", "clicking or shortcut"]
        if subprocess.run(cmd, cwd=ROOT, check=False).returncode != 0:
            return 1
    for name in SHOTS:
        size = copy_shot(name, ROOT / "test-artifacts", ROOT / "docs" / "images")
        print(f"docs/images/{name}: {size:,} bytes")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
