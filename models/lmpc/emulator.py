"""The torque emulator (Sec. III-C): an MLP from s = (q, e, qd, e_dot, tau_fb) to the HMPC torque.

ReLU hidden layers, a linear output layer, input and output normalization held as buffers inside the
module (so they are exported inside the ONNX graph), Adam on the MSE of the normalized torque
(Eq. 24), mini-batches, a held-out validation split and early stopping on the validation MSE.
Seeded: the split, the initialization and the batch order all come from ``TrainConfig.seed``.

One emulator per law (the laws' torques differ in kind: a shared net with a one-hot would have to
learn six maps at once, and a per-law bundle is what the runtime loads anyway).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
from torch import nn

from models.errors import ModelInputError


@dataclass(frozen=True)
class TrainConfig:
    hidden: tuple[int, ...] = (128, 128)
    learning_rate: float = 2e-3
    lr_decay_per_epoch: float = 0.97  # exponential schedule; ends the run at a small step
    batch_size: int = 256
    max_epochs: int = 150
    patience: int = 20  # epochs without a validation improvement before stopping
    validation_fraction: float = 0.15
    seed: int = 0
    threads: int = 1
    center_targets: bool = True  # False for a residual target (tau* - tau_fb): out_mean = 0, RMS scale

    def __post_init__(self) -> None:
        if not self.hidden or any(h < 1 for h in self.hidden):
            raise ModelInputError(f"emulator hidden: need >= 1 layer of >= 1 unit, got {self.hidden}")
        if not 0.0 < self.validation_fraction < 0.5:
            raise ModelInputError(f"emulator validation_fraction: must be in (0, 0.5), got {self.validation_fraction}")
        if self.batch_size < 1 or self.max_epochs < 1 or self.patience < 1:
            raise ModelInputError("emulator batch_size, max_epochs, patience: must be >= 1")


class Emulator(nn.Module):
    """tau = out_std * MLP((s - in_mean) / in_std) + out_mean."""

    def __init__(self, n_inputs: int, n_outputs: int, hidden: tuple[int, ...]) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        width = n_inputs
        for size in hidden:
            layers += [nn.Linear(width, size), nn.ReLU()]
            width = size
        layers.append(nn.Linear(width, n_outputs))
        self.net = nn.Sequential(*layers)
        for name, size in (
            ("in_mean", n_inputs),
            ("in_std", n_inputs),
            ("out_mean", n_outputs),
            ("out_std", n_outputs),
        ):
            self.register_buffer(name, torch.zeros(size) if "mean" in name else torch.ones(size))

    def set_normalization(self, features: np.ndarray, targets: np.ndarray, center_targets: bool = True) -> None:
        """Standardize inputs; outputs too, or (``center_targets=False``, for a residual target whose
        zero must stay the feedback law) scale them by their RMS with out_mean = 0."""
        dtype = self.in_mean.dtype
        self.in_mean.copy_(torch.as_tensor(features.mean(0), dtype=dtype))
        self.in_std.copy_(torch.as_tensor(np.maximum(features.std(0), 1e-6), dtype=dtype))
        if center_targets:
            self.out_mean.copy_(torch.as_tensor(targets.mean(0), dtype=dtype))
            self.out_std.copy_(torch.as_tensor(np.maximum(targets.std(0), 1e-6), dtype=dtype))
        else:
            self.out_mean.zero_()
            self.out_std.copy_(torch.as_tensor(np.maximum(np.sqrt(np.mean(targets**2, 0)), 1e-6), dtype=dtype))

    def normalized(self, s: torch.Tensor) -> torch.Tensor:
        return self.net((s - self.in_mean) / self.in_std)

    def forward(self, s: torch.Tensor) -> torch.Tensor:
        return self.normalized(s) * self.out_std + self.out_mean


@dataclass
class TrainResult:
    emulator: Emulator
    config: TrainConfig
    train_mse: list[float] = field(default_factory=list)  # per epoch, normalized torque units
    val_mse: list[float] = field(default_factory=list)
    best_epoch: int = 0
    best_val_mse: float = float("nan")
    val_rmse_nm: list[float] = field(default_factory=list)  # per joint, at the best epoch
    samples_train: int = 0
    samples_val: int = 0
    wall_s: float = 0.0

    def summary(self) -> dict:
        return {
            "config": asdict(self.config),
            "best_epoch": self.best_epoch,
            "epochs_run": len(self.val_mse),
            "best_val_mse_normalized": self.best_val_mse,
            "val_rmse_nm": self.val_rmse_nm,
            "samples_train": self.samples_train,
            "samples_val": self.samples_val,
            "wall_s": round(self.wall_s, 2),
        }


def train_emulator(
    features: np.ndarray,
    targets: np.ndarray,
    config: TrainConfig = TrainConfig(),
    normalization: tuple[np.ndarray, np.ndarray] | None = None,
) -> TrainResult:
    """Fit an Emulator to (features (M, F), targets (M, N)); early stopping keeps the best epoch.

    ``normalization``: (features, targets) to compute the normalization from (default: the training
    split), so that runs being compared can share one normalization and one MSE unit.
    """
    features, targets = np.asarray(features, np.float64), np.asarray(targets, np.float64)
    if features.ndim != 2 or targets.ndim != 2 or features.shape[0] != targets.shape[0] or features.shape[0] < 10:
        raise ModelInputError(
            f"emulator: need (M, F) features and (M, N) targets with M >= 10, got {features.shape} and {targets.shape}"
        )
    if not (np.isfinite(features).all() and np.isfinite(targets).all()):
        raise ModelInputError("emulator: features or targets contain NaN/inf")
    started = time.perf_counter()
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(config.threads)
    rng = np.random.default_rng(config.seed)
    torch.manual_seed(config.seed)
    order = rng.permutation(features.shape[0])
    n_val = max(1, int(round(config.validation_fraction * features.shape[0])))
    val_idx, train_idx = order[:n_val], order[n_val:]
    model = Emulator(features.shape[1], targets.shape[1], config.hidden)
    norm_x, norm_y = normalization if normalization is not None else (features[train_idx], targets[train_idx])
    model.set_normalization(norm_x, norm_y, config.center_targets)
    x = torch.as_tensor(features, dtype=torch.float32)
    y = (torch.as_tensor(targets, dtype=torch.float32) - model.out_mean) / model.out_std
    x_train, y_train, x_val, y_val = x[train_idx], y[train_idx], x[val_idx], y[val_idx]
    optimizer = torch.optim.Adam(model.parameters(), lr=config.learning_rate)
    schedule = torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=config.lr_decay_per_epoch)
    generator = torch.Generator().manual_seed(config.seed)
    result = TrainResult(model, config, samples_train=train_idx.size, samples_val=n_val)
    best_state, waited = None, 0
    try:
        for epoch in range(config.max_epochs):
            model.train()
            total = 0.0
            for batch in torch.randperm(x_train.shape[0], generator=generator).split(config.batch_size):
                loss = torch.mean(torch.sum((model.normalized(x_train[batch]) - y_train[batch]) ** 2, 1)) / y.shape[1]
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
                total += float(loss.detach()) * batch.numel()
            schedule.step()
            model.eval()
            with torch.no_grad():
                val = float(torch.mean((model.normalized(x_val) - y_val) ** 2))
            result.train_mse.append(total / x_train.shape[0])
            result.val_mse.append(val)
            if val < result.best_val_mse or best_state is None:
                result.best_val_mse, result.best_epoch, waited = val, epoch, 0
                best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
            else:
                waited += 1
                if waited >= config.patience:
                    break
        assert best_state is not None
        model.load_state_dict(best_state)
        model.eval()
        with torch.no_grad():
            err = (model(x_val) - torch.as_tensor(targets[val_idx], dtype=torch.float32)).numpy()
        result.val_rmse_nm = np.sqrt(np.mean(err**2, 0)).tolist()
    finally:
        torch.set_num_threads(previous_threads)
    result.wall_s = time.perf_counter() - started
    return result


def evaluate_mse(model: Emulator, features: np.ndarray, targets: np.ndarray) -> float:
    """MSE in the model's normalized torque units on held-out data."""
    with torch.no_grad():
        pred = model.normalized(torch.as_tensor(features, dtype=model.in_mean.dtype))
        y = (torch.as_tensor(targets, dtype=model.in_mean.dtype) - model.out_mean) / model.out_std
        return float(torch.mean((pred - y) ** 2))
