"""Peak resident memory of ``leap run`` against the bounded-memory target, beside the baseline code.

Target (bounded memory on one machine): the peak RSS of ``leap run`` (3D stages, 3D-CN off)
stays within ``1.5 GB + 64 B × voxels`` at any sequence length; with the 3D-CN on within
``3 GB + 64 B × voxels``.

Each run is a child process (``app.cli``'s ``leap run`` through :data:`_RUN_CHILD`); its RSS is sampled
with psutil every ``--interval`` seconds (child and its descendants summed), and the child writes the
kernel's high-water mark of its own memory (``VmHWM`` of ``/proc/self/status``) when it exits; the larger
of the two is reported. (``wait4``'s ``ru_maxrss`` is not used: Linux carries the forking parent's size
into it across ``exec``.) The stage at the
sampled peak is told from the stage durations in the run's ``stages.json``, counted back from the end.

The baseline is the code of commit ``--baseline`` (default ``c472ae0``, main before this work), checked
out with ``git worktree add --detach`` into a temporary folder and run with ``PYTHONPATH`` set to it, on
the same sequence and the same 2D cache folder (the labeler's masks are computed once and shared, so
both runs do the same work). The ratio is this code's peak / the baseline's peak.

Usage::

    .venv/bin/python benchmarks/bench_memory.py --sequence /work/data/demo/sequences/00 [--3dcn]
        [--voxel-size 0.2 --voxel-size 0.1] [--baseline c472ae0 | --no-baseline] [--work /tmp/bench_memory]

Prints a table and writes ``benchmarks/results/bench_memory[_3dcn]_<sequence name>.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import print_table, write_results

from leap_core.extras import MissingExtra

try:  # the bench extra
    import psutil
except ModuleNotFoundError as exc:
    raise SystemExit(f"error: {MissingExtra('bench', exc.name)}") from None

ROOT = Path(__file__).resolve().parent.parent
GB = 1e9
FIXED_3D = 1.5 * GB
"""Fixed allowance of the target without the 3D-CN (bytes)."""
FIXED_3DCN = 3.0 * GB
"""Fixed allowance with the 3D-CN on (bytes)."""
PER_VOXEL = 64
"""Allowed bytes per voxel of the fused grid."""


@dataclass
class RunMemory:
    """Memory of one ``leap run`` child."""

    peak_sampled: int
    """Largest sum of RSS over the child and its descendants seen by the sampler (bytes)."""
    peak_kernel: int
    """The child's own peak RSS (``VmHWM`` at exit, bytes)."""
    seconds: float
    """Wall time of the run."""
    voxels: int
    """Voxels of the fused grid (``stages.json``, fuse)."""
    peak_stage: str
    """Stage running when the sampled peak was seen."""
    stage_peaks: dict[str, int]
    """Largest sampled RSS while each stage ran (``stages.json``'s start and finish times)."""

    @property
    def peak(self) -> int:
        return max(self.peak_sampled, self.peak_kernel)


def _tree_rss(proc: psutil.Process) -> int:
    total = 0
    try:
        procs = [proc, *proc.children(recursive=True)]
    except psutil.Error:
        return 0
    for p in procs:
        try:
            total += p.memory_info().rss
        except psutil.Error:
            continue
    return total


def _stage_at(state: dict[str, Any], when: float) -> str:
    """Which stage ran at wall time ``when`` (``stages.json``'s ``started`` / ``finished``), else "other"
    (start-up, the runner between stages, exit)."""
    for s, rec in state.items():
        done = isinstance(rec, dict) and "started" in rec and "finished" in rec
        if done and float(rec["started"]) <= when <= float(rec["finished"]):
            return str(s)
    return "other"


def _stage_file(run_dir: Path, sequence: Path) -> Path:
    """The ``stages.json`` of ``sequence`` in a ``leap run`` folder: in ``sequences/<name>/`` (a run of
    this code), or at the top of a baseline run written before every run had that one shape."""
    top = run_dir / "stages.json"
    return (
        top
        if top.is_file()
        else run_dir / "sequences" / os.path.basename(os.path.abspath(sequence)) / top.name
    )


def measure(  # noqa: PLR0917  the code, its inputs and the sampling period
    code_root: Path,
    sequence: Path,
    run_dir: Path,
    cache: Path,
    cn: bool,
    interval: float,
    project: Path | None = None,
) -> RunMemory:
    """Run ``leap run`` from ``code_root`` in a child process and sample its memory."""
    hwm_file = run_dir.with_name(run_dir.name + ".hwm")
    cmd = [
        sys.executable,
        "-c",
        _RUN_CHILD,
        str(hwm_file),
        "run",
        str(sequence),
        "--out",
        str(run_dir),
        "--cache",
        str(cache),
        "--3dcn" if cn else "--no-3dcn",
    ]
    if project is not None:
        cmd += ["--project-file", str(project)]
    env = {**os.environ, "PYTHONPATH": str(code_root)}
    t0 = time.monotonic()
    log_path = run_dir.with_name(run_dir.name + ".log")
    # The log goes to a file: a pipe nobody reads during the run fills up with progress lines and blocks
    # the child.
    log = open(log_path, "wb")  # noqa: SIM115  closed below, after the child exits
    child = subprocess.Popen(cmd, cwd=code_root, env=env, stdout=log, stderr=subprocess.STDOUT)
    proc = psutil.Process(child.pid)
    samples: list[tuple[float, int]] = []
    done = threading.Event()

    def sample() -> None:
        while not done.is_set():
            samples.append((time.time(), _tree_rss(proc)))
            done.wait(interval)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    _, status, _usage = os.wait4(child.pid, 0)
    end = time.monotonic()
    done.set()
    sampler.join()
    log.close()
    err = log_path.read_text(errors="replace")
    log_path.unlink()
    child.returncode = os.waitstatus_to_exitcode(status)
    if child.returncode != 0:
        raise SystemExit(f"leap run from {code_root} failed ({child.returncode}):\n{err[-3000:]}")
    state = json.loads(_stage_file(run_dir, sequence).read_text())
    voxels = int(state.get("fuse", {}).get("voxels", 0))
    stage_peaks: dict[str, int] = {}
    for when, rss in samples:
        s = _stage_at(state, when)
        stage_peaks[s] = max(stage_peaks.get(s, 0), rss)
    when, rss = max(samples, key=lambda x: x[1]) if samples else (0.0, 0)
    hwm = int(hwm_file.read_text()) if hwm_file.is_file() else 0
    hwm_file.unlink(missing_ok=True)
    return RunMemory(
        peak_sampled=rss,
        peak_kernel=hwm,
        seconds=end - t0,
        voxels=voxels,
        peak_stage=_stage_at(state, when),
        stage_peaks=stage_peaks,
    )


def baseline_tree(commit: str, where: Path) -> Path:
    """A detached worktree of ``commit`` under ``where`` (removed by :func:`drop_tree`)."""
    path = where / f"baseline-{commit}"
    if not path.exists():
        subprocess.run(
            ["git", "-C", str(ROOT), "worktree", "add", "--detach", str(path), commit],
            check=True,
            stdout=subprocess.DEVNULL,
        )
    return path


def drop_tree(path: Path) -> None:
    subprocess.run(
        ["git", "-C", str(ROOT), "worktree", "remove", "--force", str(path)],
        check=False,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )


def project_file(work: Path, voxel_size: float | None, cn_steps: int | None) -> Path | None:
    """The semantickitti schema with ``pipeline.fusion.voxel_size`` and / or
    ``pipeline.consistency.min_steps`` set (None: neither is set, no file). Smaller voxels give more of
    them from the same frames, so the per-voxel slope is measured with the per-frame work unchanged; fewer
    3D-CN training steps shorten a run without changing what it holds in memory."""
    if voxel_size is None and cn_steps is None:
        return None
    path = work / f"project-vs{voxel_size}-steps{cn_steps}.yaml"
    text = (ROOT / "projects" / "semantickitti.yaml").read_text() + "\npipeline:\n"
    if voxel_size is not None:
        text += f"  fusion:\n    voxel_size: {voxel_size}\n"
    if cn_steps is not None:
        text += f"  consistency:\n    min_steps: {cn_steps}\n"
    path.write_text(text)
    return path


STAGE_COLUMNS = (
    "other",
    "labels2d",
    "project",
    "fuse",
    "smooth",
    "3dcn",
    "label_points",
    "evaluate",
    "export",
)


_HWM = """
def _hwm():
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    return 0
"""

_RUN_CHILD = (
    _HWM
    + """
import atexit, runpy, sys
out = sys.argv.pop(1)
atexit.register(lambda: open(out, "w").write(str(_hwm())))
sys.argv[0] = "leap"
runpy.run_module("app.cli", run_name="__main__", alter_sys=True)
"""
)
"""``leap run`` (the CLI module as ``python -m app.cli`` runs it) writing its ``VmHWM`` to a file at exit."""

_SMOOTH_CHILD = (
    _HWM
    + """
import sys, time
import numpy as np
from leap_core.fusion import VoxelGrid
import leap_core.smoothing as sm
grid_path, out = sys.argv[1], sys.argv[2]
t = time.perf_counter()
if hasattr(sm, "smooth_grid_blocks"):  # this code: what stage_smooth does
    grid = VoxelGrid.load(grid_path, mmap=True)
    rows = (b.astype(np.float16) for _, b in sm.smooth_grid_blocks(grid))
    sm.SmoothedGrid.save_blocks(out, grid.keys, grid.num_classes, rows, grid.voxel_size)
else:  # the baseline's stage_smooth
    grid = VoxelGrid.load(grid_path)
    probs = sm.knn_smooth(grid.centres(), grid.probs())
    sm.SmoothedGrid(grid.keys, probs.astype(np.float16), grid.voxel_size).save(out)
print(_hwm(), time.perf_counter() - t)
"""
)


def synthetic_grid(path: Path, voxels: int, num_classes: int = 20) -> None:
    """A street-like surface of about ``voxels`` voxels (a 0.2 m lattice in x, y with a noisy height), random
    fused log-posteriors: the smoothing stage's input without running the per-frame stages."""
    sys.path.insert(0, str(ROOT))
    import numpy as np

    from leap_core.fusion import VoxelGrid, voxel_keys

    rng = np.random.default_rng(0)
    side = int(np.ceil(np.sqrt(voxels)))
    x, y = np.meshgrid(np.arange(side), np.arange(side), indexing="ij")
    xyz = np.stack([x.ravel() * 0.2 + 0.1, y.ravel() * 0.2 + 0.1, rng.normal(0, 0.15, side * side)], 1)
    keys = np.unique(voxel_keys(xyz[:voxels], 0.2))
    logp = np.clip(rng.normal(0, 4, size=(len(keys), num_classes)), -20, None)
    logp -= logp.max(axis=1, keepdims=True)
    VoxelGrid(keys, logp.astype(np.float16), 0.2).save(path)


def smooth_peak(code_root: Path, grid: Path, out: Path) -> tuple[int, float]:
    """Peak RSS (bytes, ``VmHWM``) and seconds of the smooth stage's work in a child running
    ``code_root``'s code."""
    env = {**os.environ, "PYTHONPATH": str(code_root)}
    res = subprocess.run(
        [sys.executable, "-c", _SMOOTH_CHILD, str(grid), str(out)],
        cwd=code_root,
        env=env,
        check=True,
        capture_output=True,
        text=True,
    )
    peak, seconds = res.stdout.split()[-2:]
    return int(peak), float(seconds)


def smooth_table(sizes: list[int], base: Path | None, work: Path) -> list[dict[str, Any]]:
    """The smooth stage alone on synthetic grids: peak RSS of this code and of the baseline, same child
    start-up, outputs compared byte for byte."""
    rows, results = [], []
    for n in sizes:
        grid = work / f"synthetic-{n}.npz"
        synthetic_grid(grid, n)
        peaks = {}
        for label, code in (("baseline", base), ("this", ROOT)):
            if code is not None:
                peaks[label] = smooth_peak(code, grid, work / f"smooth-{label}.npz")
        same = "-"
        if "baseline" in peaks:
            import numpy as np

            with np.load(work / "smooth-this.npz") as a, np.load(work / "smooth-baseline.npz") as b:
                same = "yes" if all(a[k].tobytes() == b[k].tobytes() for k in a.files) else "NO"
        this, old = peaks["this"], peaks.get("baseline")
        rows.append(
            [
                f"{n:,}",
                f"{this[0] / 1e6:,.0f}",
                f"{this[1]:.1f}",
                f"{old[0] / 1e6:,.0f}" if old else "-",
                f"{old[1]:.1f}" if old else "-",
                f"{this[0] / old[0]:.2f}" if old else "-",
                same,
            ]
        )
        results.append(
            {
                "voxels": n,
                "this_peak_bytes": this[0],
                "this_seconds": this[1],
                "baseline_peak_bytes": old[0] if old else None,
                "baseline_seconds": old[1] if old else None,
                "identical_output": same == "yes",
            }
        )
    print_table(
        "Smooth stage alone, synthetic surface grid (20 classes): child peak RSS (MB), seconds",
        ["voxels", "peak", "s", "baseline peak", "baseline s", "ratio", "same bytes"],
        rows,
    )
    if len(results) >= 2:
        a, b = results[0], results[-1]
        dv = b["voxels"] - a["voxels"]
        line = f"smooth slope: {(b['this_peak_bytes'] - a['this_peak_bytes']) / dv:,.0f} B/voxel (this code)"
        if a["baseline_peak_bytes"]:
            line += f", {(b['baseline_peak_bytes'] - a['baseline_peak_bytes']) / dv:,.0f} B/voxel (baseline)"
        sys.stdout.write(line + "\n\n")
    return results


def target(voxels: int, cn: bool) -> float:
    """``1.5 GB + 64 B × voxels`` (``3 GB + ...`` with the 3D-CN)."""
    return (FIXED_3DCN if cn else FIXED_3D) + PER_VOXEL * voxels


def main() -> None:  # noqa: PLR0912  one branch per optional part of the report
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sequence", type=Path, action="append", default=[], help="sequence folder (repeatable)")
    ap.add_argument(
        "--smooth-voxels",
        type=int,
        action="append",
        default=[],
        help="also the smooth stage alone on a synthetic grid of this many voxels (repeatable)",
    )
    ap.add_argument("--3dcn", dest="cn", action="store_true", help="run with the 3D-CN on")
    ap.add_argument("--baseline", default="c472ae0", help="commit of the baseline code")
    ap.add_argument("--no-baseline", action="store_true", help="measure this code only")
    ap.add_argument("--work", type=Path, default=None, help="scratch folder (default: a temporary one)")
    ap.add_argument("--interval", type=float, default=0.1, help="RSS sampling period in seconds")
    ap.add_argument(
        "--cn-steps",
        type=int,
        default=None,
        help="consistency.min_steps of the runs (fewer 3D-CN training steps; default: 500)",
    )
    ap.add_argument(
        "--voxel-size",
        type=float,
        action="append",
        default=None,
        help="fusion.voxel_size of the runs (repeatable; default: the schema's default, 0.2 m)",
    )
    args = ap.parse_args()

    work = args.work or Path(tempfile.mkdtemp(prefix="bench_memory-"))
    work.mkdir(parents=True, exist_ok=True)
    base = None if args.no_baseline else baseline_tree(args.baseline, work)
    rows: list[list[Any]] = []
    results: list[dict[str, Any]] = []
    smooth_results: list[dict[str, Any]] = []
    try:
        if args.smooth_voxels:
            smooth_results = smooth_table(args.smooth_voxels, base, work)
        for seq, vs in [(s, v) for s in args.sequence for v in (args.voxel_size or [None])]:
            name = f"{seq.parent.parent.name}-{seq.name}" + ("" if vs is None else f"-vs{vs:g}")
            cache = work / f"cache-{seq.parent.parent.name}-{seq.name}"
            project = project_file(work, vs, args.cn_steps)
            runs: dict[str, RunMemory] = {}
            for label, code in (("baseline", base), ("this", ROOT)):
                if code is None:
                    continue
                run_dir = work / f"run-{name}-{label}{'-3dcn' if args.cn else ''}"
                shutil.rmtree(run_dir, ignore_errors=True)
                runs[label] = measure(code, seq, run_dir, cache, args.cn, args.interval, project)
                shutil.rmtree(run_dir, ignore_errors=True)
            this = runs["this"]
            tgt = target(this.voxels, args.cn)
            old = runs.get("baseline")
            rows.append(
                [
                    f"{name}{' +3D-CN' if args.cn else ''}",
                    f"{this.voxels:,}",
                    f"{tgt / 1e6:,.0f}",
                    f"{this.peak / 1e6:,.0f}",
                    this.peak_stage,
                    f"{old.peak / 1e6:,.0f}" if old else "-",
                    old.peak_stage if old else "-",
                    f"{this.peak / old.peak:.2f}" if old else "-",
                    "yes" if this.peak <= tgt else "NO",
                ]
            )
            results.append(
                {
                    "sequence": str(seq),
                    "voxel_size": vs,
                    "3dcn": args.cn,
                    "voxels": this.voxels,
                    "target_bytes": tgt,
                    "runs": {
                        k: {
                            "peak_bytes": r.peak,
                            "peak_sampled_bytes": r.peak_sampled,
                            "peak_kernel_bytes": r.peak_kernel,
                            "seconds": r.seconds,
                            "voxels": r.voxels,
                            "peak_stage": r.peak_stage,
                            "stage_peaks_bytes": r.stage_peaks,
                        }
                        for k, r in runs.items()
                    },
                }
            )
    finally:
        if base is not None:
            drop_tree(base)
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)
    stage_rows = []
    for r in results:
        for label, run in r["runs"].items():
            peaks = run["stage_peaks_bytes"]
            stage_rows.append(
                [
                    f"{Path(r['sequence']).parent.parent.name} vs={r['voxel_size']} {label}",
                    *(f"{peaks.get(s, 0) / 1e6:,.0f}" for s in STAGE_COLUMNS),
                ]
            )
    print_table("Peak RSS per stage (MB, sampled)", ["run", *STAGE_COLUMNS], stage_rows)
    print_table(
        f"Peak RSS of `leap run` (MB), target {'3' if args.cn else '1.5'} GB + {PER_VOXEL} B × voxels; "
        f"baseline = {args.baseline}",
        ["sequence", "voxels", "target", "peak", "at stage", "baseline", "at stage", "ratio", "within"],
        rows,
    )
    if len(results) >= 2:
        pts = sorted((r["voxels"], r["runs"]["this"]["peak_bytes"]) for r in results)
        (v0, p0), (v1, p1) = pts[0], pts[-1]
        if v1 > v0:
            slope = (p1 - p0) / (v1 - v0)
            line = f"slope between the smallest and largest run: {slope:,.0f} B/voxel (this code)"
            if all("baseline" in r["runs"] for r in results):
                b = sorted((r["voxels"], r["runs"]["baseline"]["peak_bytes"]) for r in results)
                line += f", {(b[-1][1] - b[0][1]) / (v1 - v0):,.0f} B/voxel (baseline)"
            sys.stdout.write(line + "\n")
    suffix = "_3dcn" if args.cn else ""
    names = "_".join(f"{s.parent.parent.name}{s.name}" for s in args.sequence)
    if args.voxel_size:
        names += "_vs" + "-".join(f"{v:g}" for v in args.voxel_size)
    if smooth_results:
        names += "_smooth" + "-".join(str(n) for n in args.smooth_voxels)
    write_results(f"bench_memory{suffix}_{names}", {"results": results, "smooth_stage": smooth_results})


if __name__ == "__main__":
    main()
