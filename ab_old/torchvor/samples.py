"""Point sets of the paper (§1, Fig. 5), shared by tests, benchmarks and the CLI.

Every generator returns an (N, 3) tensor in the unit cube [0, 1]^3 (unless
stated) with the requested dtype and device, drawn from ``torch.Generator``
seeded by ``seed`` so runs are repeatable.
"""
from __future__ import annotations

from typing import Optional

import torch


def _generator(seed: Optional[int], device) -> torch.Generator:
    generator = torch.Generator(device=device)
    if seed is None:
        generator.seed()
    else:
        generator.manual_seed(seed)
    return generator


def white_noise(n: int, *, seed: Optional[int] = 0, dtype=torch.float32, device="cpu") -> torch.Tensor:
    """n points uniform in the unit cube."""
    return torch.rand(n, 3, generator=_generator(seed, device), dtype=dtype, device=device)


def lattice(m: int, *, dtype=torch.float64, device="cpu") -> torch.Tensor:
    """The m^3 cell centres of a regular grid over the unit cube (every cell is a
    cube of volume 1/m^3; all cells are degenerate, cospherical)."""
    axis = (torch.arange(m, dtype=dtype, device=device) + 0.5) / m
    z, y, x = torch.meshgrid(axis, axis, axis, indexing="ij")
    return torch.stack([x.reshape(-1), y.reshape(-1), z.reshape(-1)], 1)


def perturbed_grid(n: int, *, seed: Optional[int] = 0, dtype=torch.float32, device="cpu") -> torch.Tensor:
    """A grid of about n points, each moved uniformly within its grid cell
    (paper's "perturbed grid"; also a cheap stand-in for blue noise)."""
    m = max(1, round(n ** (1.0 / 3.0)))
    cell = lattice(m, dtype=dtype, device=device) - 0.5 / m
    jitter = torch.rand(cell.shape, generator=_generator(seed, device), dtype=dtype, device=device)
    return (cell + jitter / m).clamp_(0, 1)


def jittered_grid(n: int, *, amplitude: float = 0.25, seed: Optional[int] = 0, dtype=torch.float32,
                  device="cpu") -> torch.Tensor:
    """A grid of about n points moved by at most ``amplitude`` cell sizes:
    blue-noise-like spacing without running Lloyd."""
    m = max(1, round(n ** (1.0 / 3.0)))
    centre = lattice(m, dtype=dtype, device=device)
    jitter = torch.rand(centre.shape, generator=_generator(seed, device), dtype=dtype, device=device)
    return (centre + (2 * jitter - 1) * (amplitude / m)).clamp_(0, 1)


def clustered(n: int, *, clusters: int = 20, spread: float = 0.02, seed: Optional[int] = 0,
              dtype=torch.float32, device="cpu") -> torch.Tensor:
    """n points in Gaussian clusters around uniform centres, clamped to the cube."""
    generator = _generator(seed, device)
    centres = torch.rand(clusters, 3, generator=generator, dtype=dtype, device=device)
    label = torch.randint(clusters, (n,), generator=generator, device=device)
    noise = torch.randn(n, 3, generator=generator, dtype=dtype, device=device) * spread
    return (centres[label] + noise).clamp_(0, 1)


def blue_noise(n: int, *, iters: int = 100, seed: Optional[int] = 0, dtype=torch.float32,
               device="cpu") -> torch.Tensor:
    """White noise after ``iters`` Lloyd iterations in the unit cube (the paper's blue noise)."""
    from .lloyd import lloyd

    points = white_noise(n, seed=seed, dtype=dtype, device=device)
    return lloyd(points, ([0.0, 0.0, 0.0], [1.0, 1.0, 1.0]), iters=iters)


__all__ = ["white_noise", "lattice", "perturbed_grid", "jittered_grid", "clustered", "blue_noise"]
