"""What the state-based control tasks (cart-pole, mountain car) share: start states, the
start distribution of the policy search, and rollout helpers."""

from __future__ import annotations

import contextlib

import torch
from dipole_torch.tasks.base import EpisodicTask
from torch import Tensor


class ControlTask(EpisodicTask):
    """An ``EpisodicTask`` simulated from a random start state.

    Subclasses set ``state_dim`` and ``default_seed`` and implement
    ``sample_initial_state(batch_size, generator) -> [batch_size, state_dim]``.
    """

    state_dim: int
    default_seed: int

    engine: str  # "python" or "torch", as resolved by choose_engine

    def sample_initial_state(
        self, batch_size: int, generator: torch.Generator | None = None
    ) -> Tensor:
        raise NotImplementedError

    def _episode(self, gains: list[float], start: list[float]) -> float:
        """The return of one episode of the policy ``gains`` from ``start``, in Python floats
        (the ``"python"`` engine)."""
        raise NotImplementedError

    def _episodes(self, theta: Tensor, state: Tensor) -> Tensor:
        """``[B]`` returns of the ``"python"`` engine: ``_episode`` for each row of
        ``theta: [B, D]`` and ``state: [B, S]``, as a tensor of the task's dtype and device.

        One episode at a time: a result cannot depend on the other rows of the batch, and an
        episode stops as soon as its return is settled."""
        rows = zip(theta.tolist(), state.tolist(), strict=True)
        returns = [self._episode(gains, start) for gains, start in rows]
        return torch.tensor(returns, dtype=self.dtype, device=self.device)

    def _initial_states(
        self, batch_size: int, generator: torch.Generator | None, initial_state: Tensor | None
    ) -> Tensor:
        """``[B, S]`` starts: ``initial_state`` if given; else one per row from ``generator``;
        else one shared start drawn with ``default_seed`` (so ``evaluate`` is deterministic)."""
        if initial_state is not None:
            return check_initial_state(
                initial_state, batch_size, self.state_dim, self.device, self.dtype
            )
        if generator is None:
            default = torch.Generator().manual_seed(self.default_seed)
            return self.sample_initial_state(1, default).expand(batch_size, -1).clone()
        return self.sample_initial_state(batch_size, generator)


ENGINES = ("auto", "python", "torch")


def choose_engine(engine: str, device: torch.device, compile: bool) -> str:
    """Resolve a control task's ``engine``: ``"auto"`` is ``"torch"`` on an accelerator or
    with ``compile``, else ``"python"``; a bad name, or ``compile`` without torch, raises."""
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {', '.join(map(repr, ENGINES))}, got {engine!r}")
    if engine == "auto":
        return "torch" if compile or device.type != "cpu" else "python"
    if engine == "python" and compile:
        raise ValueError("compile=True compiles the torch rollout: it needs engine='torch'")
    return engine


def check_positive_int(**values: int) -> None:
    """Raise ``ValueError`` naming the first argument that is not a positive integer."""
    for name, value in values.items():
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")


_COMPILED: dict = {}


def compiled(function):
    """``torch.compile(function, dynamic=True)``, built once per function."""
    if function not in _COMPILED:
        _COMPILED[function] = torch.compile(function, dynamic=True)
    return _COMPILED[function]


@contextlib.contextmanager
def single_threaded(device: torch.device, batch_size: int, below: int = 200_000):
    """Run a CPU rollout of fewer than ``below`` episodes on one intra-op thread.

    Each step is a few dozen element-wise ops on ``[B]`` tensors: with ``B`` up to ~10⁵,
    OpenMP's fork/join costs more than it saves, and it collapses when another process
    shares the cores. The previous thread count is restored afterwards.
    """
    previous = torch.get_num_threads()
    switch = device.type == "cpu" and batch_size < below and previous != 1
    if switch:
        torch.set_num_threads(1)
    try:
        yield
    finally:
        if switch:
            torch.set_num_threads(previous)


def start_distribution(
    theta0: Tensor | list[float] | None,
    exploration_std: float | list[float] | Tensor,
    dim: int,
    device: torch.device,
    dtype: torch.dtype,
) -> tuple[Tensor, Tensor]:
    """Check ``theta0`` and ``exploration_std``; return ``theta0 [D]``, ``sigma_start [D, D]``."""
    if theta0 is None:
        theta0 = torch.zeros(dim)
    theta0 = torch.as_tensor(theta0, dtype=torch.float64)
    if theta0.shape != (dim,) or not torch.isfinite(theta0).all():
        raise ValueError(f"theta0 must be {dim} finite numbers, got {theta0.tolist()!r}")
    std = torch.as_tensor(exploration_std, dtype=torch.float64)
    std = std.expand(dim) if std.dim() == 0 else std
    if std.shape != (dim,) or not (torch.isfinite(std).all() and (std > 0).all()):
        raise ValueError(
            f"exploration_std must be a positive number or {dim} positive numbers, "
            f"got {std.tolist()!r}"
        )
    return theta0.to(device, dtype), torch.diag(std.square()).to(device, dtype)


def check_initial_state(
    initial_state: Tensor, batch_size: int, dim: int, device: torch.device, dtype: torch.dtype
) -> Tensor:
    """Validate ``initial_state: [S]`` or ``[B, S]`` and return it as ``[B, S]``."""
    initial_state = torch.as_tensor(initial_state)
    if initial_state.dim() == 1:
        initial_state = initial_state.unsqueeze(0).expand(batch_size, -1)
    if initial_state.shape != (batch_size, dim):
        raise ValueError(
            f"initial_state must have shape [{dim}] or [{batch_size}, {dim}], "
            f"got {list(initial_state.shape)}"
        )
    if not torch.isfinite(initial_state).all():
        raise ValueError("initial_state contains non-finite values (NaN or inf)")
    cast = initial_state.to(device=device, dtype=dtype)
    if not torch.isfinite(cast).all():
        raise ValueError(f"initial_state holds values beyond the task's {dtype} range")
    return cast.clone()
