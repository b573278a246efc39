"""The samples a policy search keeps: θ, their returns, and the policy owning each."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from dipole_torch.gaussian import DTYPE
from dipole_torch.memo import Memo
from dipole_torch.validation import check_finite

__all__ = ["HOST_ROWS", "NO_POLICY", "PROBE", "REPEAT", "SampleArchive"]

# Owner codes of told rows: k >= 0, a sample of policy k; NO_POLICY, a sample that belongs to
# no policy yet (a scout); PROBE, an evaluation that is not a sample of any exploration
# distribution (a hill-valley probe): it never enters the archive; REPEAT, a kept sample
# evaluated again (``best_evaluations``): its return is averaged into that sample's.
NO_POLICY = -1
PROBE = -2
REPEAT = -3

# Up to this many rows the per-sample searches on the CPU (each policy's best row here, the
# importance sets in ``dipole_torch.power``) run in Python numbers on ``host_lists``: at an
# archive's usual sizes (tens of rows) that is a few microseconds where tensor operations
# make a dozen to forty calls, each cold in a run (docs: Speed); from about a thousand rows
# (a large first batch) the tensor path's sorts are the faster.
HOST_ROWS = 512


class SampleArchive:
    """The kept samples: ``thetas [N, D]``, ``rewards [N]`` and ``owner [N]`` (a policy
    index, or ``NO_POLICY``), re-indexed together; ``evaluations [N]``, how many returns
    each row's reward averages, is ``None`` while every row has one (a run that evaluates
    no sample twice never builds it).

    Args:
        dim: D.
        device: where the tensors live (float64).
    """

    def __init__(self, dim: int, device: torch.device):
        self.thetas = torch.empty(0, dim, dtype=DTYPE, device=device)
        self.rewards = torch.empty(0, dtype=DTYPE, device=device)
        self.owner = torch.empty(0, dtype=torch.long, device=device)
        self.evaluations: Tensor | None = None
        self._memo = Memo()

    def __len__(self) -> int:
        return int(self.rewards.shape[0])

    def append(self, thetas: Tensor, rewards: Tensor, owner: Tensor) -> None:
        """Add samples ``thetas [B, D]``, ``rewards [B]``, ``owner [B]``."""
        self.thetas = torch.cat((self.thetas, thetas))
        self.rewards = torch.cat((self.rewards, rewards))
        self.owner = torch.cat((self.owner, owner))
        if self.evaluations is not None:
            self.evaluations = torch.cat((self.evaluations, torch.ones_like(owner)))

    def keep(self, mask: Tensor) -> None:
        """Keep the samples ``mask`` (``[N]`` bool, or indices)."""
        self.thetas, self.rewards, self.owner = (
            self.thetas[mask],
            self.rewards[mask],
            self.owner[mask],
        )
        if self.evaluations is not None:
            self.evaluations = self.evaluations[mask]

    def replace(self, thetas: Tensor, rewards: Tensor, owner: Tensor) -> None:
        """Forget every sample; keep these instead (one evaluation each)."""
        self.thetas, self.rewards, self.owner = thetas, rewards, owner
        self.evaluations = None

    def evaluation_counts(self) -> Tensor:
        """``[N]`` how many returns each row's reward averages."""
        if self.evaluations is None:
            return torch.ones_like(self.owner)
        return self.evaluations

    def average_in(self, rows: Tensor, returns: Tensor) -> tuple[Tensor, Tensor]:
        """Average ``returns [R]``, new evaluations of the kept samples ``rows [R]``
        (distinct row indices), into those samples' rewards. The tensors are replaced, not
        written into (a tell's snapshot holds them). Returns the rows' new ``[R]`` rewards
        and ``[R]`` evaluation counts."""
        counts = self.evaluation_counts()
        n = counts[rows] + 1
        mean = (self.rewards[rows] * (n - 1) + returns) / n
        self.rewards = self.rewards.index_put((rows,), mean)
        self.evaluations = counts.index_put((rows,), n)
        return mean, n

    def best_rows(self, policies: list[int], num_policies: int) -> list[int]:
        """The row of each of ``policies``' best kept sample (``best_row_index``; -1 for a
        policy that keeps none), of ``num_policies`` in all."""
        if self._on_host():
            rows = self._host_best_rows(num_policies)
        else:
            rows = self.best_row_index(num_policies).tolist()
        return [rows[policy] for policy in policies]

    # The per-policy reductions below are memoised (``Memo``): an iteration asks for each
    # policy's best return in several mechanisms, mostly while the archive stands still.
    # They scatter every sample into K + 1 slots, slot 0 taking the samples of no policy, so
    # that no boolean mask (a costly gather) is needed to leave those out.
    def _slots(self) -> Tensor:
        """``[N]`` each sample's slot: its owner + 1 (0: no policy)."""
        return self._memo.get("slots", (self.owner,), lambda: self.owner.clamp_min(-1) + 1)

    def per_policy(self, reduce: str, num_policies: int) -> Tensor:
        """``[K]`` the ``"amax"`` or ``"amin"`` of each policy's kept returns (∓inf: none).
        Memoised: not to be written into."""

        def compute() -> Tensor:
            empty = -math.inf if reduce == "amax" else math.inf
            start = torch.full((num_policies + 1,), empty, dtype=DTYPE, device=self.rewards.device)
            return start.scatter_reduce(0, self._slots(), self.rewards, reduce)[1:]

        return self._memo.get((reduce, num_policies), (self.owner, self.rewards), compute)

    def counts(self, num_policies: int) -> Tensor:
        """``[K]`` the number of kept samples of each policy. Memoised: not to be written
        into."""
        return self._memo.get(
            ("counts", num_policies),
            (self.owner,),
            lambda: torch.bincount(self._slots(), minlength=num_policies + 1)[1:],
        )

    def host_lists(self) -> tuple[tuple[int, ...], tuple[float, ...]]:
        """``owner`` and ``rewards`` as host numbers (the per-sample bookkeeping of an
        iteration on the CPU runs on them). Memoised."""
        return self._memo.get(
            "host",
            (self.owner, self.rewards),
            lambda: (tuple(self.owner.tolist()), tuple(self.rewards.tolist())),
        )

    def mean_rewards(self, num_policies: int) -> Tensor:
        """``[K]`` each policy's mean kept return (0 for a policy with none)."""
        if self.rewards.device.type == "cpu":
            return torch.tensor(self.host_mean_rewards(num_policies), dtype=DTYPE)
        return self._tensor_mean_rewards(num_policies)

    def _tensor_mean_rewards(self, num_policies: int) -> Tensor:
        """``mean_rewards`` in tensor operations, on any device."""
        slots = self._slots()
        total = torch.zeros(num_policies + 1, dtype=DTYPE, device=self.rewards.device)
        # (Each slot's returns are summed in the archive's order, as over the owned ones.)
        total = total.index_add_(0, slots, self.rewards)[1:]
        return total / self.counts(num_policies).clamp_min(1)

    def host_mean_rewards(self, num_policies: int) -> list[float]:
        """``mean_rewards`` as K host numbers: each policy's returns summed in the archive's
        order and divided by their count (at least 1), the tensor path's float64 operations."""
        owner, rewards = self.host_lists()
        total, count = [0.0] * num_policies, [0] * num_policies
        for policy, value in zip(owner, rewards, strict=True):
            if policy >= 0:
                total[policy] += value
                count[policy] += 1
        return [t / max(n, 1) for t, n in zip(total, count, strict=True)]

    def best_row_index(self, num_policies: int) -> Tensor:
        """``[K]`` the row of each policy's best kept sample, the last of its rows of equal
        returns (-1: none kept). Memoised (on the host path, the host numbers it is built
        from): not to be written into."""
        if self._on_host():
            rows = self._host_best_rows(num_policies)
            return torch.tensor(rows, dtype=torch.long, device=self.owner.device)

        def compute() -> Tensor:
            # Found by reductions: an indexed write of every row sorted by return (the last
            # write winning) is undefined where indices repeat, and on CUDA may keep any.
            slots = self._slots()  # (slot 0: the samples of no policy)
            top = self.per_policy("amax", num_policies)
            is_top = self.rewards == torch.cat((top.new_full((1,), math.inf), top))[slots]
            rows = torch.arange(self.rewards.shape[0], device=self.rewards.device)
            last = torch.full((num_policies + 1,), -1, dtype=torch.long, device=rows.device)
            return last.scatter_reduce(0, slots, torch.where(is_top, rows, -1), "amax")[1:]

        sources = (self.owner, self.rewards)
        return self._memo.get(("best_rows", num_policies), sources, compute)

    def _on_host(self) -> bool:
        """Whether the per-sample searches run on ``host_lists`` (the CPU, at most
        ``HOST_ROWS`` rows: a few microseconds of Python where tensor operations make a dozen
        calls)."""
        return self.owner.device.type == "cpu" and self.owner.shape[0] <= HOST_ROWS

    def _host_best_rows(self, num_policies: int) -> tuple[int, ...]:
        """``best_row_index`` as K host numbers, from ``host_lists``. Memoised."""

        def compute() -> tuple[int, ...]:
            owner, rewards = self.host_lists()
            best = [-1] * num_policies
            for row, (policy, value) in enumerate(zip(owner, rewards, strict=True)):
                if policy >= 0 and (best[policy] < 0 or value >= rewards[best[policy]]):
                    best[policy] = row  # (>=: the last of equal returns)
            return tuple(best)

        sources = (self.owner, self.rewards)
        return self._memo.get(("host_best_rows", num_policies), sources, compute)

    def best_samples(self, means: Tensor) -> Tensor:
        """``[K, D]`` each policy's best kept sample (``best_row_index``; its row of ``means
        [K, D]`` where it has none). Memoised: not to be written into."""

        def compute() -> Tensor:
            num_policies = means.shape[0]
            if self._on_host():
                listed = self._host_best_rows(num_policies)
                rows = torch.tensor(listed, dtype=torch.long)  # (on the CPU)
                if -1 not in listed:
                    return self.thetas[rows]  # (every policy keeps a sample: the usual case)
            else:
                rows = self.best_row_index(num_policies)
            if self.rewards.shape[0] == 0:
                return means.clone()
            return torch.where(rows[:, None] >= 0, self.thetas[rows.clamp_min(0)], means)

        sources = (self.owner, self.rewards, self.thetas, means)
        return self._memo.get("best_samples", sources, compute)

    def drop_policies(self, keep: Tensor) -> None:
        """Drop the samples of the policies not in ``keep [K]`` (bool) and renumber the
        owners of the others (samples of no policy stay)."""
        new_index = torch.cumsum(keep.long(), 0) - 1
        self.keep((self.owner < 0) | keep[self.owner.clamp_min(0)])
        self.owner = torch.where(self.owner >= 0, new_index[self.owner.clamp_min(0)], self.owner)

    def state_dict(self, copy: bool = True) -> dict[str, Tensor]:
        """``thetas``, ``rewards``, ``owner`` and (once a sample was evaluated twice)
        ``evaluations``: copies, or (``copy=False``) the tensors themselves, which the
        archive replaces and never writes into."""
        state = {"thetas": self.thetas, "rewards": self.rewards, "owner": self.owner}
        if self.evaluations is not None:
            state["evaluations"] = self.evaluations
        return {key: value.clone() for key, value in state.items()} if copy else state

    def load_state_dict(self, state: dict, device: torch.device) -> None:
        """Load ``thetas [N, D]``, ``rewards [N]``, ``owner [N]`` and, where the state has
        them, ``evaluations [N]`` (≥ 1; absent: one each); raises ``ValueError`` naming the
        key whose shape, type or values do not fit."""
        d = self.thetas.shape[1]
        thetas, rewards, owner = (state[key] for key in ("thetas", "rewards", "owner"))
        _check_tensor(thetas, "thetas", (None, d))
        n = thetas.shape[0]
        _check_tensor(rewards, "rewards", (n,))
        _check_tensor(owner, "owner", (n,), integral=True)
        check_finite(thetas, "state_dict['thetas']")  # every told θ and return was finite
        check_finite(rewards, "state_dict['rewards']")
        self.thetas = thetas.to(device=device, dtype=DTYPE)
        self.rewards = rewards.to(device=device, dtype=DTYPE)
        self.owner = owner.to(device=device, dtype=torch.long)
        evaluations = state.get("evaluations")
        if evaluations is not None:
            _check_tensor(evaluations, "evaluations", (n,), integral=True)
            if bool((evaluations < 1).any()):
                raise ValueError("state_dict['evaluations'] must be >= 1 (returns averaged)")
            evaluations = evaluations.to(device=device, dtype=torch.long)
        self.evaluations = evaluations


def _check_tensor(value, key: str, shape: tuple, integral: bool = False) -> None:
    """Raise ``ValueError`` unless ``value`` is a tensor of ``shape`` (None: any size)."""
    if not isinstance(value, Tensor):
        raise ValueError(f"state_dict[{key!r}] must be a tensor, got {type(value).__name__}")
    fits = value.dim() == len(shape) and all(
        s is None or s == t for s, t in zip(shape, value.shape, strict=False)
    )
    if not fits:
        want = ", ".join("N" if s is None else str(s) for s in shape)
        raise ValueError(f"state_dict[{key!r}] must have shape [{want}], got {list(value.shape)}")
    if integral and value.is_floating_point():
        raise ValueError(f"state_dict[{key!r}] must hold integers, got {value.dtype}")
