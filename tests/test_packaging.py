"""The wheel: a regular (not editable) install ships the presets (``projects/``) and the web UI (``web/``)
inside the packages, and the installed ``leap`` works from any folder with the core dependencies alone.

The slow test builds the wheel from a copy of the sources with this venv's setuptools and installs it into a
new venv that sees only the core dependencies' distributions of this venv (linked, not downloaded: no
network), so that it also shows that no extra is needed by ``leap synth``, ``leap run`` and ``leap serve``.
"""

from __future__ import annotations

import email
import json
import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
import zipfile
from collections.abc import Iterator
from importlib import metadata
from pathlib import Path
from typing import Any

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: pytest's own TOML reader
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]


def _setuptools_config() -> dict[str, Any]:
    config: dict[str, Any] = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    return config


def _package_folder(name: str, package_dir: dict[str, str]) -> Path:
    """The folder setuptools takes package ``name`` from (its own package-dir entry, else its parent's)."""
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        mapped = package_dir.get(".".join(parts[:i]))
        if mapped is not None:
            return ROOT / mapped / Path(*parts[i:])
    return ROOT / Path(*parts)


def test_every_package_folder_is_listed_and_every_listed_package_exists() -> None:
    """pyproject.toml lists the packages (setuptools' find cannot map projects/ and web/ into them): a new
    package folder must be added there, or the wheel would leave it out."""
    config = _setuptools_config()
    listed, package_dir = set(config["packages"]), config["package-dir"]
    tops = {name.split(".")[0] for name in listed}
    found = {
        ".".join(init.parent.relative_to(ROOT).parts)
        for top in tops
        for init in (ROOT / top).rglob("__init__.py")
        if "__pycache__" not in init.parts
    }
    assert found <= listed, f"add to [tool.setuptools] packages in pyproject.toml: {sorted(found - listed)}"
    for name in listed:
        folder = _package_folder(name, package_dir)
        assert folder.is_dir(), f"{name}: no folder {folder}"
    for name, folder in package_dir.items():
        # The editable install's finder maps a package onto its folder only through an __init__.py.
        assert (ROOT / folder / "__init__.py").is_file(), f"{folder}/__init__.py is missing ({name})"
        assert name in listed, f"{name} (package-dir) is not in [tool.setuptools] packages"


# ------------------------------------------------------------------------------ the installed wheel
def _build_wheel(tmp: Path) -> Path:
    """The wheel of a copy of the sources setuptools reads (the checkout itself gets no build/ folder)."""
    config = _setuptools_config()
    src = tmp / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    folders = {name.split(".")[0] for name in config["packages"]} | set(config["package-dir"].values())
    for folder in folders:
        shutil.copytree(ROOT / folder, src / folder, ignore=shutil.ignore_patterns("__pycache__"))
    dist = tmp / "dist"
    cmd = [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "--no-index"]
    subprocess.run([*cmd, "-w", str(dist), str(src)], check=True, capture_output=True, timeout=300)
    (wheel,) = dist.glob("leap_studio-*.whl")
    return wheel


def _requires(text: str | None, extras: frozenset[str]) -> Iterator[Requirement]:
    """The requirement ``text`` when its marker holds for the ``extras`` asked of its distribution."""
    if text is None:
        return
    req = Requirement(text)
    if req.marker is None or any(req.marker.evaluate({"extra": e}) for e in extras | {""}):
        yield req


def _core_closure(wheel: Path) -> list[metadata.Distribution]:
    """The installed distributions the wheel's core requirements (no extra) pull in, transitively."""
    with zipfile.ZipFile(wheel) as zf:
        (meta,) = (n for n in zf.namelist() if n.endswith(".dist-info/METADATA"))
        core = email.message_from_bytes(zf.read(meta)).get_all("Requires-Dist") or []
    todo = [req for text in core for req in _requires(text, frozenset())]
    seen: dict[str, tuple[metadata.Distribution, frozenset[str]]] = {}
    while todo:
        req = todo.pop()
        key = canonicalize_name(req.name)
        extras = frozenset(req.extras) | (seen[key][1] if key in seen else frozenset())
        if key in seen and extras == seen[key][1]:
            continue
        dist = metadata.distribution(req.name)
        seen[key] = (dist, extras)
        todo.extend(r for text in dist.requires or [] for r in _requires(text, extras))
    return [dist for dist, _ in seen.values()]


def _link_site(dists: list[metadata.Distribution], site: Path) -> None:
    """Link each distribution's top-level files and folders (its modules, its .dist-info) into ``site``."""
    for dist in dists:
        base = Path(str(dist.locate_file("")))
        for top in {f.parts[0] for f in dist.files or [] if f.parts and f.parts[0] != ".."}:
            if not (site / top).exists() and (base / top).exists():
                (site / top).symlink_to(base / top)


def _core_venv(tmp: Path, wheel: Path) -> Path:
    """A venv holding the wheel, its core dependencies and pip (linked from this venv); its ``bin``."""
    venv = tmp / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    py = venv / "bin" / "python"
    site = Path(
        subprocess.run(
            [py, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
            check=True,
            capture_output=True,
            text=True,
        ).stdout.strip()
    )
    _link_site([*_core_closure(wheel), metadata.distribution("pip")], site)
    pip = [py, "-m", "pip", "--disable-pip-version-check", "-q"]
    subprocess.run([*pip, "install", "--no-deps", "--no-index", str(wheel)], check=True, timeout=300)
    # Every requirement of every distribution there is met: the core dependencies are all present.
    subprocess.run([*pip, "check"], check=True, timeout=120)
    return venv / "bin"


def _answers(url: str) -> bool:
    try:
        return _get(url)[0] == 200
    except urllib.error.URLError:  # not listening yet
        return False


def _get(url: str) -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=30) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()


def _post(url: str, body: dict[str, Any]) -> tuple[int, Any]:
    data = json.dumps(body).encode()
    req = urllib.request.Request(url, data=data, headers={"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read())


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.slow
def test_a_regular_install_runs_from_another_folder_without_any_extra(tmp_path: Path) -> None:
    wheel = _build_wheel(tmp_path)
    with zipfile.ZipFile(wheel) as zf:
        shipped = set(zf.namelist())
    for folder, package in (("projects", "leap_core/projects"), ("web", "app/web")):
        files = [p for p in (ROOT / folder).rglob("*") if p.is_file() and "__pycache__" not in p.parts]
        missing = {f"{package}/{p.relative_to(ROOT / folder).as_posix()}" for p in files} - shipped
        assert not missing, f"the wheel leaves out {sorted(missing)} (pyproject.toml's package-data)"

    bin_dir = _core_venv(tmp_path, wheel)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["PATH"] = f"{bin_dir}{os.pathsep}{env.get('PATH', '')}"

    def leap(*args: str) -> subprocess.CompletedProcess[str]:
        cmd = [str(bin_dir / "leap"), *args]
        return subprocess.run(
            cmd, check=False, cwd=elsewhere, env=env, capture_output=True, text=True, timeout=300
        )

    probe = (
        "import app.main, leap_core.schema as s\nprint(s.projects_dir())\nprint(app.main.WEB_DIR)\nimport ray"
    )
    where = subprocess.run(
        [bin_dir / "python", "-c", probe],
        check=False,
        cwd=elsewhere,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert len(where.stdout.split()) == 2, where.stderr
    site = bin_dir.parent / "lib"
    presets, web = (Path(line) for line in where.stdout.split())
    assert presets.is_relative_to(site) and presets.name == "projects", where.stdout  # the installed copy
    assert web.is_relative_to(site) and web.name == "web", where.stdout
    assert "No module named 'ray'" in where.stderr  # no extra is installed

    assert leap("--help").returncode == 0
    demo = tmp_path / "demo"
    synth = leap("synth", str(demo), "--frames", "3")
    assert synth.returncode == 0, synth.stderr
    run = leap("run", str(demo / "sequences" / "00"), "--out", str(tmp_path / "run"))
    assert run.returncode == 0, run.stderr
    assert len(list((tmp_path / "run" / "sequences" / "00" / "export").glob("*.label"))) == 3
    ray = leap("run", str(demo / "sequences" / "00"), "--out", str(tmp_path / "ray"), "--ray", "auto")
    assert ray.returncode == 2 and "Ray is not installed: pip install 'leap-studio[ray]'" in ray.stderr

    port = _free_port()
    serve = [str(bin_dir / "leap"), "serve", "--port", str(port), "--no-demo", "--data-root", str(tmp_path)]
    serve += ["--work-dir", str(tmp_path / "studio")]
    with open(tmp_path / "serve.log", "wb") as log:
        server = subprocess.Popen(serve, cwd=elsewhere, env=env, stdout=log, stderr=log)
    try:
        base = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 60
        while not _answers(f"{base}/api/v1/health"):
            assert server.poll() is None and time.monotonic() < deadline, (tmp_path / "serve.log").read_text()
            time.sleep(0.2)
        assert _get(f"{base}/") == (200, (ROOT / "web" / "index.html").read_bytes())
        assert _get(f"{base}/viewer/overlay.js") == (
            200,
            (ROOT / "web" / "viewer" / "overlay.js").read_bytes(),
        )
        assert _get(f"{base}/api/docs") == (200, (ROOT / "web" / "api-docs.html").read_bytes())
        dataset = {"kind": "folder", "path": str(demo / "sequences" / "00")}
        status, project = _post(
            f"{base}/api/v1/projects", {"name": "p", "dataset": dataset, "schema_name": "agri_uav"}
        )
        assert status == 201 and project["num_classes"] == 7, project
        status, error = _post(
            f"{base}/api/v1/projects", {"name": "q", "dataset": dataset, "schema_name": "x"}
        )
        assert status == 422 and "available: agri_uav, demo, nuscenes, semantickitti" in json.dumps(error)
    finally:
        server.terminate()
        server.wait(30)
