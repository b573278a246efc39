"""What one ``tell`` reports, in the row order every ask follows: the policy samples, the
scouts, the probes, the repeated evaluations (``TellBatch``)."""

from __future__ import annotations

from dataclasses import dataclass, field

from torch import Tensor

from dipole_torch.archive import NO_POLICY, PROBE, REPEAT

__all__ = ["TellBatch"]


@dataclass(frozen=True)
class TellBatch:
    """What one ``tell`` reports, as the optimizer's mechanisms see it (float64, on the
    optimizer's device): ``theta [B, D]``, ``rewards [B]``, ``owner [B]`` (see
    ``dipole_torch.archive``: a policy, a scout, a probe) and whether the ask was ``cut``
    to its first B rows.

    An ask lists its rows in groups (``_propose``): the policy samples, one per sampled
    policy; then the scouts (``NO_POLICY``); then the probes (``PROBE``); then the kept
    samples evaluated again (``REPEAT``, with ``best_evaluations``). The mechanisms
    take a group as a slice (``rewards[:batch.policy_rows]``), not through a boolean mask
    (a gather, several times the cost); ``policies`` lists the sampled policies on the
    host. Built from ``owner`` (one ``tolist``); rows out of that order are refused.
    """

    theta: Tensor
    rewards: Tensor
    owner: Tensor
    cut: bool
    policies: tuple[int, ...] = field(init=False)  # owner[:policy_rows]
    sample_rows: int = field(init=False)  # the rows before the probes
    probe_end: int = field(init=False)  # the rows before the repeats

    def __post_init__(self) -> None:
        owners = self.owner.tolist()
        n = len(owners)
        policy_rows = next((i for i, o in enumerate(owners) if o < 0), n)
        sample_rows = next((i for i in range(policy_rows, n) if owners[i] < NO_POLICY), n)
        probe_end = next((i for i in range(sample_rows, n) if owners[i] == REPEAT), n)
        if (
            any(o != NO_POLICY for o in owners[policy_rows:sample_rows])
            or any(o != PROBE for o in owners[sample_rows:probe_end])
            or any(o != REPEAT for o in owners[probe_end:])
        ):
            raise ValueError(
                f"a told batch lists its policy samples, then scouts, then probes, then "
                f"repeated evaluations; got owners {owners}"
            )
        object.__setattr__(self, "policies", tuple(owners[:policy_rows]))
        object.__setattr__(self, "sample_rows", sample_rows)
        object.__setattr__(self, "probe_end", probe_end)

    @property
    def policy_rows(self) -> int:
        """The batch's first rows that are policy samples."""
        return len(self.policies)

    def every_policy(self, num_policies: int) -> bool:
        """Whether the policy samples are one of each of the ``num_policies`` policies, in
        order: rows ``[:num_policies]`` are then per-policy tensors as they stand (no gather
        or scatter by ``owner``)."""
        return self.policies == tuple(range(num_policies))
