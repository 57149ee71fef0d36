"""Streaming Fréchet distance: zero on itself, closed form for Gaussians, monotone in a mean shift,
streaming == one shot, and moments merge across 2 gloo processes exactly as in one process."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from gaia_app.eval.frechet import FrechetStatistics, frechet_distance, frechet_distance_gaussians


def stats_of(features: torch.Tensor, batch: int = 64) -> FrechetStatistics:
    stats = FrechetStatistics(features.shape[1])
    for chunk in features.split(batch):
        stats.update(chunk)
    return stats


def correlated(n: int, dim: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    mixing = torch.randn(dim, dim, generator=g) / dim**0.5
    return torch.randn(n, dim, generator=g) @ mixing + torch.randn(dim, generator=g)


def test_a_set_against_itself_is_zero() -> None:
    x = correlated(2000, 16, seed=0)
    assert frechet_distance(stats_of(x), stats_of(x)) == pytest.approx(0.0, abs=1e-8)


def test_closed_form_for_diagonal_gaussians() -> None:
    # d² = |μa − μb|² + Σ (σa − σb)² when both covariances are diagonal
    mean_a, mean_b = torch.tensor([0.0, 1.0, -2.0]), torch.tensor([1.0, 1.0, 0.0])
    sd_a, sd_b = torch.tensor([1.0, 2.0, 0.5]), torch.tensor([3.0, 1.0, 0.5])
    expected = float((mean_a - mean_b).pow(2).sum() + (sd_a - sd_b).pow(2).sum())  # 5 + 5 = 10
    closed_form = frechet_distance_gaussians(mean_a, sd_a.diag() ** 2, mean_b, sd_b.diag() ** 2)
    assert closed_form == pytest.approx(expected, rel=1e-10)
    # and from samples, streamed: 200k draws pin the moments to ≈ 1 %
    g = torch.Generator().manual_seed(1)
    a = torch.randn(200_000, 3, generator=g) * sd_a + mean_a
    b = torch.randn(200_000, 3, generator=g) * sd_b + mean_b
    assert frechet_distance(stats_of(a, 10_000), stats_of(b, 10_000)) == pytest.approx(expected, rel=0.02)


def test_a_general_covariance_matches_the_trace_formula() -> None:
    # commuting case: Σa = A Aᵀ, Σb = 4 Σa → (Σa Σb)^½ = 2 Σa, so d² = |Δμ|² + Tr(Σa + 4Σa − 4Σa) = |Δμ|² + Tr Σa
    g = torch.Generator().manual_seed(2)
    a = torch.randn(5, 5, generator=g, dtype=torch.float64)
    cov = a @ a.T
    shift = torch.randn(5, generator=g, dtype=torch.float64)
    expected = float(shift.pow(2).sum() + cov.trace())
    assert frechet_distance_gaussians(torch.zeros(5), cov, shift, 4 * cov) == pytest.approx(expected, rel=1e-9)


def test_grows_monotonically_with_a_mean_shift() -> None:
    x, y = correlated(3000, 8, seed=3), correlated(3000, 8, seed=3)[torch.randperm(3000)]
    base = stats_of(x)
    distances = [frechet_distance(base, stats_of(y + shift)) for shift in (0.0, 0.25, 0.5, 1.0, 2.0)]
    assert distances[0] == pytest.approx(0.0, abs=1e-8)
    assert all(a < b for a, b in zip(distances, distances[1:]))
    # a shift of s in every one of 8 dims adds 8 s²
    assert distances[-1] == pytest.approx(8 * 2.0**2, rel=1e-6)


def test_streaming_and_merging_equal_one_shot() -> None:
    x = correlated(1000, 6, seed=4)
    one = FrechetStatistics(6).update(x)
    merged = stats_of(x[:300], 7).merge(stats_of(x[300:], 100))
    for a, b in zip(one.mean_cov(), merged.mean_cov()):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_bad_input_is_named() -> None:
    stats = FrechetStatistics(4)
    with pytest.raises(ValueError, match=r"shape \(batch, 4\), got \(2, 3\)"):
        stats.update(torch.zeros(2, 3))
    with pytest.raises(ValueError, match="non-finite"):
        stats.update(torch.tensor([[0.0, float("nan"), 0.0, 0.0]]))
    with pytest.raises(ValueError, match="at least 2 feature vectors"):
        frechet_distance(stats.update(torch.zeros(1, 4)), stats_of(torch.randn(10, 4)))


def _ddp_worker(rank: int, world: int, init_file: str, features: torch.Tensor, out: str) -> None:
    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=world)
    try:
        stats = FrechetStatistics(features.shape[1]).update(features[rank::world]).all_reduce()
        if rank == 0:
            torch.save(stats.mean_cov(), out)
    finally:
        dist.destroy_process_group()


def test_moments_merge_across_two_gloo_ranks(tmp_path: Path) -> None:
    features = correlated(501, 5, seed=5)  # an odd count: the ranks hold 251 and 250 rows
    out = tmp_path / "rank0.pt"
    mp.spawn(_ddp_worker, args=(2, str(tmp_path / "init"), features, str(out)), nprocs=2, join=True)
    mean, cov = torch.load(out)
    expected_mean, expected_cov = FrechetStatistics(5).update(features).mean_cov()
    torch.testing.assert_close(mean, expected_mean, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(cov, expected_cov, rtol=1e-12, atol=1e-12)
