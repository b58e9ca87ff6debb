"""The GPU code paths, on a machine with a CUDA GPU (skipped elsewhere, so CI, which has none, skips them;
docs/MUTATION.md says when they last ran on a GPU and what they caught).

What runs on the GPU in a pipeline run: the 3D-CN's training and inference (``consistency.device``; its
inputs' features and grid cells, and bfloat16 mixed precision with ``consistency.precision``) and the
2D labeler's Grounding DINO + SAM (``Runtime.device``, in float16 with ``half_precision``). Each test runs
one of them on CUDA and compares it with the same computation on the CPU, which the rest of the suite checks
exactly, or float16 on CUDA with float32 there."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from test_consistency import TINY, _predictions, _scans, _tiny_stage_inputs, synthetic_scan
from test_grounded_sam import half_precision_agreement, images, small_schema

from leap_core.consistency.stage import checkpoint_path, fuse_back, run_3dcn_iteration
from leap_core.consistency.train import _training_batch, load_checkpoint, predict_log_probs, train_model
from leap_core.fusion import FusionConfig, VoxelGrid
from leap_core.labelers.cache import LabelCache, image_digest
from leap_core.labelers.grounded_sam import GroundedSamConfig, GroundedSamLabeler
from leap_core.labelers.tiny_models import TinyModelsConfig, make_tiny_models
from leap_core.runtime import Runtime

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")


def test_3dcn_round_trains_and_predicts_on_the_gpu(tmp_path: Path, make_tiny_sequence) -> None:
    seq, grid, c = _tiny_stage_inputs(tmp_path, make_tiny_sequence)
    fused = VoxelGrid(grid.keys, np.roll(grid.logp, 1, axis=1), grid.voxel_size)
    cfg = replace(TINY, epochs=2, temperature=1.0, new_voxel_margin=0.0, device="cuda")
    work = tmp_path / "work"
    out = run_3dcn_iteration(seq, fused, grid, c, cfg, FusionConfig(), work, 1)
    ck = load_checkpoint(checkpoint_path(work, 1))  # loaded onto the CPU
    losses = ck.meta["losses"]
    assert losses[-1] < losses[0], losses  # trained on the GPU
    frames = range(len(seq))
    # The same weights on the CPU and on the GPU give the same log-probabilities (float32 both; the GPU's
    # kernels sum in another order).
    gpu_model = load_checkpoint(checkpoint_path(work, 1), device="cuda").model
    worst = 0.0
    for i in frames:
        pts = seq.frame(i).points
        cpu = predict_log_probs(ck.model, pts)
        gpu = predict_log_probs(gpu_model, pts, device="cuda")
        worst = max(worst, float(np.abs(cpu - gpu).max()))
        assert (cpu.argmax(1) == gpu.argmax(1)).mean() > 0.99
    print(f"largest CPU/GPU log-probability difference: {worst:.2e}")
    assert worst < 1e-3
    # The round's grid is the fusion of those predictions (up to the grid's float16 rounding).
    expected = fuse_back(
        fused,
        _predictions(seq, frames, ck.model),
        c,
        cfg.temperature,
        FusionConfig(),
        cfg.network_evidence,
        new_voxel_margin=0.0,
    )
    assert np.array_equal(out.keys, expected.keys)
    np.testing.assert_allclose(out.logp.astype(np.float32), expected.logp.astype(np.float32), atol=1e-2)

    # A second call reuses the checkpoint, which loads onto the CPU: the round moves it to the GPU for its
    # inference (the GPU allocates), and gives the first call's grid.
    mtime = checkpoint_path(work, 1).stat().st_mtime_ns
    torch.cuda.synchronize()
    torch.cuda.empty_cache()
    torch.cuda.reset_peak_memory_stats()
    before = torch.cuda.memory_allocated()
    again = run_3dcn_iteration(seq, fused, grid, c, cfg, FusionConfig(), work, 1)
    assert checkpoint_path(work, 1).stat().st_mtime_ns == mtime
    assert torch.cuda.max_memory_allocated() > before
    assert np.array_equal(again.keys, out.keys)
    np.testing.assert_allclose(again.logp.astype(np.float32), out.logp.astype(np.float32), atol=1e-2)


def test_3dcn_inputs_prepared_on_the_gpu_and_bfloat16_training() -> None:
    scans = _scans()
    cfg = replace(TINY, points_per_scan=200, augment=True, scans_per_step=2)
    on_cpu = _training_batch(scans.__getitem__, [0, 1], cfg, np.random.default_rng(4), 1)
    on_gpu = _training_batch(
        scans.__getitem__, [0, 1], cfg, np.random.default_rng(4), 1, torch.device("cuda")
    )
    assert on_cpu is not None and on_gpu is not None and on_gpu[0].feats.is_cuda
    torch.testing.assert_close(on_gpu[0].feats.cpu(), on_cpu[0].feats, atol=2e-5, rtol=0)
    torch.testing.assert_close(on_gpu[0].local.cpu(), on_cpu[0].local, atol=2e-5, rtol=0)
    # Mixed precision on the GPU learns as float32 does (test_consistency's bfloat16 test, on CUDA).
    model, stats = train_model(
        scans.__getitem__, list(scans), 3, replace(TINY, epochs=8, device="cuda", precision="bfloat16")
    )
    assert np.mean(stats.losses[-4:]) < 0.5 * np.mean(stats.losses[:4])
    pts, lab = synthetic_scan(99)
    logp = predict_log_probs(model.cuda(), pts, device="cuda", precision=torch.bfloat16)
    assert (logp.argmax(axis=1) == lab).mean() > 0.9


def test_grounded_sam_on_the_gpu_matches_the_cpu(tmp_path: Path) -> None:
    models = make_tiny_models(tmp_path / "models", TinyModelsConfig(num_queries=12)).models_dir
    imgs = images(2)
    schema = small_schema()
    # Threshold 0.01: every region the tiny random detector finds is kept on both devices, so a score that
    # differs in its last bits cannot drop a region on one of them.
    cfg = GroundedSamConfig(box_threshold=0.01, batch_size=2)
    cpu = GroundedSamLabeler(cfg, Runtime(models_dir=models, device="cpu")).label_images(imgs, schema)
    lab = GroundedSamLabeler(cfg, Runtime(models_dir=models, device="cuda"))
    gpu = lab.label_images(imgs, schema)
    assert lab.models.device == "cuda"
    assert next(lab.models.detector.parameters()).is_cuda and next(lab.models.segmenter.parameters()).is_cuda
    for a, b in zip(cpu, gpu, strict=True):
        assert a.num_masks == b.num_masks > 0
        np.testing.assert_allclose(a.probs, b.probs, atol=1e-3)
        np.testing.assert_allclose(a.confidence, b.confidence, atol=1e-3)
        agree = (np.unpackbits(a.bits, axis=1) == np.unpackbits(b.bits, axis=1)).mean()
        print(f"mask pixels the same on both devices: {agree:.5f}")
        assert agree > 0.99


def test_grounded_sam_in_half_precision_on_the_gpu_follows_float32(tmp_path: Path) -> None:
    models = make_tiny_models(tmp_path / "models", TinyModelsConfig(num_queries=12)).models_dir
    imgs = images(2)
    schema = small_schema()
    # A threshold just above zero: every query is kept in both precisions, whatever its rounding.
    cfg = GroundedSamConfig(box_threshold=1e-6, batch_size=2)
    results = []
    for half in (False, True):
        lab = GroundedSamLabeler(
            replace(cfg, half_precision=half),
            Runtime(models_dir=models, device="cuda"),
            cache=LabelCache(tmp_path / f"cache-{half}"),
        )
        out = lab.label_images(imgs, schema)
        want = torch.float16 if half else torch.float32
        assert lab.models.dtype == want
        assert next(lab.models.detector.parameters()).dtype == want
        assert next(lab.models.segmenter.parameters()).dtype == want
        assert all(sm.num_masks > 0 and sm.probs.dtype == np.float32 for sm in out)
        (plan,) = lab.plan(schema)
        assert lab.cache is not None
        got = [lab.cache.get(lab.pass_key(image_digest(im), plan)) for im in imgs]
        assert all(r is not None and r.scores.dtype == np.float32 for r in got)
        results.append([r for r in got if r is not None])
    # The tolerances of float16 on the CPU (test_grounded_sam), where these tiny random models reach 0.92
    # and 0.985; not yet run on a GPU.
    found, agree = half_precision_agreement(results[0], results[1])
    print(f"float32 regions found again in float16: {found:.3f}; mask pixels the same: {agree:.4f}")
    assert found >= 0.75 and agree >= 0.9
