"""The interface every task implements, and its input checks."""

from __future__ import annotations

import abc

import torch
from torch import Tensor


class EpisodicTask(abc.ABC):
    """An episodic reinforcement-learning task seen as a black-box reward of policy parameters.

    Subclasses set, in ``__init__``:

    * ``theta0: [D]`` -- the initial policy parameters (the paper's θ in Algorithm 2),
    * ``sigma_start: [D, D]`` -- the initial exploration covariance Σ_start,
    * ``reward_range: (low, high)`` -- bounds of the return; the optimizers map returns to
      positive weights with it (see ``dipole_torch.RewardScale``),
    * ``device`` and ``dtype`` of the rollouts,

    and implement ``evaluate``, a rollout batched over policies (a loop over time steps
    only). The optimizer never calls the task: ``train.py`` passes ``ask()``'s parameters
    to ``evaluate`` and the returns back to ``tell``.
    """

    theta0: Tensor
    sigma_start: Tensor
    reward_range: tuple[float, float]
    device: torch.device
    dtype: torch.dtype = torch.float32

    @property
    def parameter_dim(self) -> int:
        """D, the number of policy parameters."""
        return int(self.theta0.shape[-1])

    @abc.abstractmethod
    def evaluate(self, theta: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """Run one episode per policy.

        Args:
            theta: ``[B, D]`` policy parameters.
            generator: source of the episode's randomness (initial states); ``None`` uses
                a fixed, task-specific default so that equal ``theta`` give equal returns.

        Returns:
            ``[B]`` returns, on the task's device.
        """

    def describe_policies(self, theta: Tensor) -> list[str]:
        """One line per policy for the end-of-run summary (e.g. the route a viapoint policy
        takes); ``theta: [K, D]``. Empty strings by default."""
        return [""] * theta.shape[0]

    def policy_scalars(self, theta: Tensor) -> dict[str, float]:
        """Figures of merit of the policies ``theta: [K, D]`` taken together (e.g. how many
        of the viapoint task's routes they take), for TensorBoard's ``task/<name>`` tags,
        the HPARAMS tab's metrics and ``results.json``. None by default."""
        return {}

    def describe_policy_set(self, theta: Tensor) -> str:
        """A line on the policies ``theta: [K, D]`` taken together for the end-of-run summary
        (e.g. the routes they take); empty by default."""
        return ""

    def plot_policies(self, theta: Tensor):
        """A matplotlib figure of the policies ``theta: [K, D]`` for TensorBoard, or ``None``
        (the default) when the task has nothing to draw."""
        return None

    def check_theta(self, theta: Tensor) -> Tensor:
        """Validate ``theta: [B, D]`` and move it to the task's device and dtype."""
        if not isinstance(theta, Tensor):
            raise TypeError(f"theta must be a torch.Tensor, got {type(theta).__name__}")
        if theta.dim() != 2 or theta.shape[-1] != self.parameter_dim:
            raise ValueError(
                f"theta must have shape [B, {self.parameter_dim}] for {type(self).__name__}, "
                f"got {list(theta.shape)}"
            )
        if not torch.isfinite(theta).all():
            raise ValueError("theta contains non-finite values (NaN or inf)")
        cast = theta.to(device=self.device, dtype=self.dtype)
        if not torch.isfinite(cast).all():  # finite, but beyond the task's dtype
            raise ValueError(
                f"theta holds values beyond the task's {self.dtype} range (largest "
                f"|θ| {float(theta.abs().max()):.3g}, {self.dtype}'s largest "
                f"{torch.finfo(self.dtype).max:.3g})"
            )
        return cast


def floating_dtype(dtype: torch.dtype | str, half: bool = True) -> torch.dtype:
    """``dtype`` (a ``torch.dtype`` or its name, ``"float64"``) if it is a floating dtype, and
    wide enough when ``half`` is false (float16 and bfloat16 refused); else a ``ValueError``
    naming it (an integer dtype would truncate the starts and the gains)."""
    resolved = getattr(torch, dtype, None) if isinstance(dtype, str) else dtype
    if not isinstance(resolved, torch.dtype) or not resolved.is_floating_point:
        raise ValueError(f"dtype must be a floating torch dtype or its name, got {dtype!r}")
    if not half and resolved in (torch.float16, torch.bfloat16):
        raise ValueError(
            f"dtype {dtype!r} is too narrow for this task (its inverse kinematics and "
            "factorisations need float32 or float64)"
        )
    return resolved
