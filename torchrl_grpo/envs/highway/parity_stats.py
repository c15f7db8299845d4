"""Two-sample tests for comparing the tensor simulator with highway-env's recorded statistics.

Plain implementations (torch and math only) of the tests the parity ladder's fresh-
reset rung uses: Kolmogorov-Smirnov for continuous samples (returns, gaps, speeds),
chi-square for counts (lanes), and a two-proportion z-test for crash rates.

Example:
    >>> import torch
    >>> g = torch.Generator().manual_seed(0)
    >>> a, b = torch.rand(500, generator=g), torch.rand(500, generator=g)
    >>> ks_2samp(a, b)[1] > 0.01
    True
    >>> ks_2samp(a, b + 0.5)[1] < 1e-6
    True
"""

from __future__ import annotations

import math

import torch

__all__ = ["chi2_counts", "ks_2samp", "proportions_z"]


def _kolmogorov_sf(x: float) -> float:
    """P(K > x) for the Kolmogorov distribution: 2 sum (-1)^(k-1) exp(-2 k^2 x^2)."""
    if x < 0.2:
        return 1.0
    total = sum((-1) ** (k - 1) * math.exp(-2 * k * k * x * x) for k in range(1, 101))
    return min(1.0, max(0.0, 2 * total))


def ks_2samp(a: torch.Tensor, b: torch.Tensor) -> tuple[float, float]:
    """Two-sample Kolmogorov-Smirnov statistic and asymptotic p-value.

    Uses Stephens' small-sample correction of the effective size, as common
    implementations' asymptotic mode does.

    Example:
        >>> ks_2samp(torch.tensor([1.0, 2.0, 3.0]), torch.tensor([1.0, 2.0, 3.0]))[0]
        0.0
    """
    a, b = a.double().flatten().sort().values, b.double().flatten().sort().values
    both = torch.cat([a, b])
    cdf_a = torch.searchsorted(a, both, right=True).double() / a.numel()
    cdf_b = torch.searchsorted(b, both, right=True).double() / b.numel()
    d = float((cdf_a - cdf_b).abs().max())
    n = a.numel() * b.numel() / (a.numel() + b.numel())
    en = math.sqrt(n)
    return d, _kolmogorov_sf((en + 0.12 + 0.11 / en) * d)


def chi2_counts(a: torch.Tensor, b: torch.Tensor, categories: int) -> tuple[float, float]:
    """Chi-square test that two samples of categories ``0..categories-1`` share one distribution.

    Example:
        >>> x = torch.tensor([0, 1, 2] * 100)
        >>> chi2_counts(x, x, 3)
        (0.0, 1.0)
    """
    table = torch.stack(
        [torch.bincount(t.flatten().long(), minlength=categories).double() for t in (a, b)]
    )
    table = table[:, table.sum(0) > 0]
    expected = table.sum(1, keepdim=True) * table.sum(0, keepdim=True) / table.sum()
    stat = float(((table - expected) ** 2 / expected).sum())
    dof = (table.shape[1] - 1) * (table.shape[0] - 1)
    if dof == 0:
        return stat, 1.0
    p = float(
        torch.special.gammaincc(
            torch.tensor(dof / 2, dtype=torch.float64), torch.tensor(stat / 2, dtype=torch.float64)
        )
    )
    return stat, p


def proportions_z(a: torch.Tensor, b: torch.Tensor) -> tuple[float, float]:
    """Two-sided two-proportion z-test of two samples of flags.

    Example:
        >>> a = torch.tensor([True] * 10 + [False] * 90)
        >>> b = torch.tensor([True] * 12 + [False] * 88)
        >>> proportions_z(a, b)[1] > 0.5
        True
    """
    na, nb = a.numel(), b.numel()
    pa, pb = float(a.double().mean()), float(b.double().mean())
    pooled = (pa * na + pb * nb) / (na + nb)
    se = math.sqrt(pooled * (1 - pooled) * (1 / na + 1 / nb))
    if se == 0:
        return 0.0, 1.0 if pa == pb else 0.0
    z = (pa - pb) / se
    return z, math.erfc(abs(z) / math.sqrt(2))
