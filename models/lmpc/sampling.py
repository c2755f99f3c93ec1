"""Theorem 2 (Sec. III-C, App. B): how many of a fixed budget of samples to take from each region.

Regions S_i are time windows of a run, each with an admissible error tolerance delta_i:

    gamma_i = 1 / (delta_i - L Delta_i + eps)^p          (regional difficulty)
    rho_i   = gamma_i A_i                                 (A_i: the region's share of the samples)
    w_i*    = rho_i^(2/3) / sum_j rho_j^(2/3)             (minimizes sum_i rho_i / sqrt(w_i))

``L Delta_i`` (the Lipschitz bound of the expert over the region) is either set (default 0, the
reading under which the paper's numbers are reproduced to 3 decimals) or estimated from the data by
``estimate_lipschitz_delta`` (see its docstring and docs/lmpc.md). Within a region the samples are
drawn uniformly without replacement. ``uniform_sample`` is the baseline at the same budget.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models.errors import ModelInputError


@dataclass(frozen=True)
class Region:
    """A time window [start_s, end_s) of every run, with its admissible error tolerance."""

    name: str
    start_s: float
    end_s: float
    tolerance: float  # delta_i

    def contains(self, t_s: np.ndarray, last: bool = False) -> np.ndarray:
        upper = t_s <= self.end_s if last else t_s < self.end_s
        return (t_s >= self.start_s) & upper


#: The paper's three regions, most demanding first (the order of its w*).
PAPER_REGIONS = (
    Region("disturbance 2-3 s", 2.0, 3.0, 0.05),
    Region("transient 0-2 s", 0.0, 2.0, 0.15),
    Region("steady 3-5 s", 3.0, 5.0, 0.30),
)
PAPER_WEIGHTS = (0.4475, 0.3407, 0.2118)  # as printed in Sec. IV-C


def optimal_weights(
    tolerances: np.ndarray | tuple[float, ...],
    proportions: np.ndarray | tuple[float, ...],
    lipschitz_delta: np.ndarray | tuple[float, ...] | float = 0.0,
    epsilon: float = 1e-9,
    power: float = 1.0,
) -> np.ndarray:
    """w* of Theorem 2 for regions with tolerances delta_i, proportions A_i and margins L Delta_i."""
    delta = np.asarray(tolerances, float)
    area = np.asarray(proportions, float)
    ldelta = np.broadcast_to(np.asarray(lipschitz_delta, float), delta.shape)
    if delta.ndim != 1 or area.shape != delta.shape:
        raise ModelInputError(f"sampling: {delta.size} tolerances but {area.size} proportions")
    if epsilon <= 0 or power <= 0:
        raise ModelInputError(f"sampling: epsilon and p must be > 0, got epsilon={epsilon}, p={power}")
    margin = delta - ldelta + epsilon
    if np.any(margin <= 0):
        raise ModelInputError(f"sampling: delta_i - L Delta_i + eps must be > 0, got {margin.tolist()}")
    if np.any(area < 0) or area.sum() <= 0:
        raise ModelInputError(f"sampling: proportions must be >= 0 and not all 0, got {area.tolist()}")
    rho = area / margin**power
    weights = rho ** (2.0 / 3.0)
    return weights / weights.sum()


def region_index(t_s: np.ndarray, regions: tuple[Region, ...] = PAPER_REGIONS) -> np.ndarray:
    """The region of each time stamp (-1 where none); the latest region is closed at its end."""
    t_s = np.asarray(t_s, float)
    out = np.full(t_s.shape, -1, int)
    end = max(r.end_s for r in regions)
    for i, region in enumerate(regions):
        out[(out < 0) & region.contains(t_s, last=region.end_s == end)] = i
    return out


def time_proportions(t_s: np.ndarray, regions: tuple[Region, ...] = PAPER_REGIONS) -> np.ndarray:
    """A_i: each region's share of the samples (equal to its share of time for uniform logging)."""
    index = region_index(t_s, regions)
    counts = np.array([(index == i).sum() for i in range(len(regions))], float)
    if counts.sum() == 0:
        raise ModelInputError("sampling: no sample falls in any region")
    return counts / counts.sum()


def estimate_lipschitz_delta(
    t_s: np.ndarray,
    run: np.ndarray,
    features: np.ndarray,
    target: np.ndarray,
    regions: tuple[Region, ...] = PAPER_REGIONS,
    quantile: float = 0.5,
) -> np.ndarray:
    """L Delta_i from the data, in the units of the normalized target (the tolerance's units).

    Along each logged run, consecutive samples give |d target| / |d features| (normalized units):
    L is its ``quantile`` over the whole data set (the median, not the max: one impulse sample would
    otherwise dominate). Delta_i is the region's typical sample spacing |d features| (median), i.e.
    the diameter of the neighbourhood one sample stands for. So L Delta_i is how much the expert
    moves between neighbouring samples of the region: large where the state moves fast (the
    disturbance window), which is what the proof's v_i stands for.
    """
    t_s, run = np.asarray(t_s, float), np.asarray(run)
    x = (features - features.mean(0)) / (features.std(0) + 1e-12)
    y = (target - target.mean(0)) / (target.std(0) + 1e-12)
    order = np.lexsort((t_s, run))
    x, y, t_sorted, run_sorted = x[order], y[order], t_s[order], run[order]
    same = run_sorted[1:] == run_sorted[:-1]
    dx = np.linalg.norm(np.diff(x, axis=0), axis=1)[same]
    dy = np.linalg.norm(np.diff(y, axis=0), axis=1)[same] / np.sqrt(y.shape[1])
    t_mid = t_sorted[1:][same]
    moving = dx > 1e-12
    lipschitz = float(np.quantile(dy[moving] / dx[moving], quantile))
    index = region_index(t_mid, regions)
    spacing = np.array([np.median(dx[index == i]) if np.any(index == i) else 0.0 for i in range(len(regions))])
    return lipschitz * spacing


def optimal_sample(
    t_s: np.ndarray,
    budget: int,
    weights: np.ndarray,
    rng: np.random.Generator,
    regions: tuple[Region, ...] = PAPER_REGIONS,
) -> np.ndarray:
    """Indices of ``budget`` samples: round(w_i budget) from region i, uniformly inside it."""
    index = region_index(t_s, regions)
    counts = _allocate(budget, np.asarray(weights, float))
    chosen = []
    for i, count in enumerate(counts):
        members = np.flatnonzero(index == i)
        if count > members.size:
            raise ModelInputError(
                f"sampling: region '{regions[i].name}' has {members.size} samples, "
                f"{count} asked (budget {budget}, w={weights[i]:.4f})"
            )
        chosen.append(rng.choice(members, size=count, replace=False))
    return np.sort(np.concatenate(chosen))


def uniform_sample(count_available: int, budget: int, rng: np.random.Generator) -> np.ndarray:
    """The baseline: ``budget`` indices uniformly without replacement."""
    if budget > count_available:
        raise ModelInputError(f"sampling: budget {budget} exceeds the {count_available} samples available")
    return np.sort(rng.choice(count_available, size=budget, replace=False))


def _allocate(budget: int, weights: np.ndarray) -> np.ndarray:
    """Integer counts summing to ``budget`` (largest remainders)."""
    raw = weights / weights.sum() * budget
    counts = np.floor(raw).astype(int)
    counts[np.argsort(raw - counts)[::-1][: budget - counts.sum()]] += 1
    return counts
