"""What a training run prints: progress, and the summary at the end.

On a terminal, a progress bar (tqdm), with the run's log messages printed above it, never
glued to it. Piped to a file or a cluster's log, one line every ~10 % of the budget instead
(a bar's carriage returns would make one long line of it).
"""

from __future__ import annotations

import contextlib
import logging
import sys

from tqdm import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

__all__ = ["Progress", "summary"]

log = logging.getLogger("train")


def _number(value: float) -> str:
    """A return as a person reads it: ``1000``, ``0.9721``, ``-3.2e-05``."""
    return f"{value:.6g}" if abs(value) >= 1e4 or value == int(value) else f"{value:.4g}"


class Progress:
    """Progress of a run from ``start`` to ``total`` trials.

    Args:
        total: the trial budget.
        start: the trials already done (a resumed run).
        enabled: ``False``: nothing but the log lines every ~10 %.
        stream: where the bar goes (a terminal gets a bar, anything else log lines).
    """

    def __init__(self, total: int, start: int, enabled: bool = True, stream=None):
        self.total = total
        stream = stream if stream is not None else sys.stderr
        self.bar = None
        if enabled and stream.isatty():
            self.bar = tqdm(total=total, initial=start, unit="trial", file=stream)
        self.step = max(1, round(total / 10))
        self.next_line = (start // self.step + 1) * self.step

    def messages(self):
        """A context in which log messages are printed above the bar."""
        return logging_redirect_tqdm() if self.bar is not None else contextlib.nullcontext()

    def update(self, trials: int, added: int, row: dict) -> None:
        """After a batch: ``trials`` done, ``added`` of them in this batch, ``row`` the
        iteration's scalars (``log_iteration``)."""
        best, policies = row["best_so_far"], row["num_policies"]
        if self.bar is not None:
            self.bar.update(added)
            self.bar.set_postfix(best=_number(best), policies=policies, refresh=False)
        elif trials >= self.next_line or trials >= self.total:
            log.info(
                f"{trials} of {self.total} trials ({100 * trials / self.total:.0f} %): best "
                f"return {_number(best)}, {_count(policies, 'policy', 'policies')}"
            )
            self.next_line = (trials // self.step + 1) * self.step

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def summary(name: str, task_name: str, results: dict, out) -> str:
    """The run's last lines: the best return, then each policy (by its id, best first) with
    the task's description of it, or its return where the task has none, and the task's line
    on the policies taken together, where it has one. On noisy returns a policy's return is
    the mean of as many rollouts as the best return's, which orders the policies; a task's
    description, one rollout, is followed by it."""
    policies = results["policies"]
    averaged = results.get("repeats", {}).get("best_reward_evaluations", 1)
    mean = f" (the mean of {averaged})" if averaged > 1 else ""
    lines = [
        f"{name} on {task_name}: best return {_number(results['best_reward'])}{mean} in "
        f"{results['trials']} trials (budget {results['trial_budget']}); "
        f"{_count(len(policies), 'policy', 'policies')} "
        f"({'its mean' if len(policies) == 1 else 'their means'}, without exploration):"
    ]
    for policy in sorted(policies, key=lambda p: -p["return_of_mean"]):
        described = policy["description"] or f"return {_number(policy['return_of_mean'])}"
        if policy["description"] and averaged > 1:  # the task's one rollout, then the order's
            described += (
                f" (one rollout; the mean of {averaged}: {_number(policy['return_of_mean'])})"
            )
        lines.append(f"  policy {policy['id']}: {described}")
    together = results.get("policy_set", {}).get("description")
    if together:  # the task's line on them all (the viapoint task: the routes found)
        lines.append(together)
    repeats = results.get("repeats")
    if repeats is not None:
        lines.append(
            f"returns {repeats['returns']}: "
            + {
                "noisy": f"each policy's best sample evaluated up to "
                f"{repeats['best_evaluations']} times",
                "deterministic": "repeated evaluations returned the same, none since",
                "undecided": "too few repeated evaluations to tell",
            }[repeats["returns"]]
        )
    lines.append(f"outputs in {out}")
    return "\n".join(lines)


def _count(n: int, one: str, many: str) -> str:
    """``"1 policy"``, ``"3 policies"``."""
    return f"{n} {one if n == 1 else many}"
