"""Kept samples evaluated again (``best_evaluations``): for noisy returns.

With noisy returns the best of a policy's samples is mostly the luckiest: kept as told, it is
seldom beaten, the success rule shrinks the exploration around it and the policy converges
where the luck was. Evaluated again and averaged, a lucky return falls back among the others
(the re-evaluation of the elite in noisy evolution strategies).

An ask ends with the repeats (owner ``REPEAT``, see ``dipole_torch.archive``): each sampled
policy's best kept sample while its return averages fewer than ``evaluations`` returns. The
tell averages their returns into those samples (``SampleArchive.average_in``) before anything
judges the batch. Once ``DETERMINISTIC_REPEATS`` repeats have returned the returns they
repeat (to a relative ``REPEAT_RTOL``) and none ever differed, the returns are taken to be
deterministic and nothing is repeated again: the option then costs a deterministic task those
few trials. (Returns of a few discrete values, a success or a failure, can repeat by chance:
there, a run may stop repeating early; noise below ``REPEAT_RTOL`` of the return is taken for
none.)

The repeats also keep the best averaged sample: of the samples whose return came to average
``evaluations`` returns, the one with the best mean (``best``). On noisy returns the best
single return told is the luckiest of thousands, several noise stds above what its θ
returns on average; the search's ``best()`` reports the averaged one instead.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from dipole_torch.archive import REPEAT, SampleArchive

__all__ = ["DETERMINISTIC_REPEATS", "REPEAT_RTOL", "RepeatedEvaluations"]

# Repeated evaluations in a row, each the return it repeats (to REPEAT_RTOL), after which
# the returns are taken to be deterministic and none is evaluated again.
DETERMINISTIC_REPEATS = 3
# Relative difference within which a repeated return counts as the return it repeats: a
# deterministic simulator in float32 whose reductions run in another order at each call (on
# a GPU) returns values that differ in their last bits, about 1e-7 of them.
REPEAT_RTOL = 1e-6


class RepeatedEvaluations:
    """The repeats of a policy search: which kept samples an ask evaluates again, and what
    the repeats told so far say of the returns.

    Args:
        evaluations: returns a sampled policy's best kept sample averages before it is
            trusted (1: every return as told; nothing is repeated).

    Attributes:
        identical: repeats told that returned the return they repeat (while none differed).
        noisy: whether a repeat ever returned another return than the one it repeated.
        pending: ``[R]`` the archive rows of the pending ask's repeats (None: none).
        best: ``([D] θ, its mean return)`` the best sample whose return averages
            ``evaluations`` returns, at the tell that completed it (None: none yet). Kept
            when the sample leaves the archive.
    """

    def __init__(self, evaluations: int = 1):
        self.evaluations = int(evaluations)
        self.identical = 0
        self.noisy = False
        self.pending: Tensor | None = None
        self.best: tuple[Tensor, float] | None = None

    @property
    def returns(self) -> str:
        """What the repeats found the returns to be: ``"noisy"``, ``"deterministic"``, or
        ``"undecided"`` while too few were told."""
        if self.noisy:
            return "noisy"
        return "deterministic" if self.identical >= DETERMINISTIC_REPEATS else "undecided"

    @property
    def best_averaged(self) -> tuple[Tensor, float] | None:
        """``best`` once the returns were found noisy (None otherwise: where no repeat ever
        returned another return, a single return told is as good as their mean)."""
        return self.best if self.noisy else None

    @property
    def reported_evaluations(self) -> int:
        """The returns that ``best()``'s return averages: ``evaluations`` once it reports
        ``best_averaged``, else 1 (a single return told)."""
        return 1 if self.best_averaged is None else self.evaluations

    def rows(self, archive: SampleArchive, policies: list[int], num_policies: int) -> list[int]:
        """The archive rows to evaluate again at an ask sampling ``policies``: each one's best
        kept sample while it averages fewer than ``evaluations`` returns (none once the
        returns are deterministic)."""
        if self.evaluations <= 1 or self.returns == "deterministic":
            return []
        counts = archive.evaluation_counts().tolist()
        rows = [row for row in archive.best_rows(policies, num_policies) if row >= 0]
        return [row for row in rows if counts[row] < self.evaluations]

    def extend(
        self, archive: SampleArchive, theta: Tensor, owner: Tensor, num_policies: int
    ) -> tuple[Tensor, Tensor]:
        """The proposal ``theta [B, D]``, ``owner [B]`` followed by the repeats (owner
        ``REPEAT``), whose rows become ``pending`` (``num_policies``: the search's K)."""
        self.pending = None
        policies = [policy for policy in owner.tolist() if policy >= 0]
        rows = self.rows(archive, policies, num_policies)
        if not rows:
            return theta, owner
        self.pending = torch.tensor(rows, dtype=torch.long, device=owner.device)
        repeat_owner = torch.full((len(rows),), REPEAT, dtype=torch.long, device=owner.device)
        return (
            torch.cat((theta, archive.thetas[self.pending])),
            torch.cat((owner, repeat_owner)),
        )

    def tell(self, archive: SampleArchive, returns: Tensor) -> None:
        """The returns ``[R']`` of the pending ask's first R' repeats (a cut ask may tell
        fewer than it asked): counted as the same as the returns they repeat or not, then
        averaged into their samples; the best of those that now average ``evaluations``
        returns replaces ``best`` if it is better. Clears ``pending``."""
        rows, self.pending = self.pending, None
        if returns.numel() == 0:
            return
        rows = rows[: returns.shape[0]]
        kept = archive.rewards[rows]
        same = torch.isclose(returns.to(kept.dtype), kept, rtol=REPEAT_RTOL, atol=0.0).tolist()
        if all(same):
            self.identical += len(same)
        else:
            self.noisy = True
        means, counts = (values.tolist() for values in archive.average_in(rows, returns))
        done = [i for i, count in enumerate(counts) if count >= self.evaluations]
        if done:
            i = max(done, key=means.__getitem__)  # (the first of equal means)
            if self.best is None or means[i] > self.best[1]:
                self.best = (archive.thetas[rows[i]].clone(), means[i])

    def forget(self) -> None:
        """The world changed: the pending repeats and the best averaged sample are dropped
        (what the repeats found of the noise is kept)."""
        self.pending = None
        self.best = None

    def state_dict(self, copy: bool = True) -> dict:
        return {
            "pending_repeats": self.pending.clone()
            if copy and self.pending is not None
            else self.pending,
            "identical_repeats": self.identical,
            "noisy_returns": self.noisy,
            "best_averaged_theta": None
            if self.best is None
            else self.best[0].clone()
            if copy
            else self.best[0],
            "best_averaged_reward": None if self.best is None else self.best[1],
        }

    def load_state_dict(
        self, state: dict, owner: Tensor | None, rows: int, dim: int, device: torch.device
    ) -> None:
        """Load the counters, the best averaged sample (``[dim]``) and the pending repeats'
        archive rows, checked against the pending ask's ``owner`` and the archive's ``rows``
        (a state from before repeats: none made, none pending, none averaged)."""
        repeats = state.get("pending_repeats")
        asked = 0 if owner is None else int((owner == REPEAT).sum())
        held = 0 if repeats is None else int(repeats.numel())
        if held != asked or (held and not (0 <= int(repeats.min()) and int(repeats.max()) < rows)):
            raise ValueError(
                f"state_dict['pending_repeats'] must list the archive row (0 <= row < {rows}) "
                f"of each of the pending ask's {asked} repeated evaluations, got {held}"
            )
        self.pending = None if repeats is None else repeats.to(device=device, dtype=torch.long)
        self.identical = int(state.get("identical_repeats", 0))
        self.noisy = bool(state.get("noisy_returns", False))
        theta, value = state.get("best_averaged_theta"), state.get("best_averaged_reward")
        if (theta is None) != (value is None) or (
            theta is not None
            and not (
                isinstance(theta, Tensor)
                and tuple(theta.shape) == (dim,)
                and isinstance(value, (int, float))
                and math.isfinite(value)
            )
        ):
            raise ValueError(
                f"state_dict['best_averaged_theta'] must be None or a tensor of shape [{dim}], "
                f"with state_dict['best_averaged_reward'] None or its finite return, got "
                f"{getattr(theta, 'shape', theta)!r} and {value!r}"
            )
        self.best = None if theta is None else (theta.to(device), float(value))
