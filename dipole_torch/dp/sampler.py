"""The Gibbs sampler of the DP Gaussian mixture (IGMM) with its options, as one object."""

from __future__ import annotations

import torch
from torch import Tensor

from dipole_torch.dp.neal8 import neal8_sweep
from dipole_torch.dp.slice import SliceChain, slice_sweep
from dipole_torch.dp.state import DPMixtureState
from dipole_torch.gaussian import DTYPE
from dipole_torch.prior import NormalInverseWishartPrior
from dipole_torch.validation import (
    check_choice,
    check_count,
    check_finite,
    check_matrix_shape,
    check_positive_finite,
)

__all__ = ["Chain", "DPNumericalError", "DPSampler"]

Chain = DPMixtureState | SliceChain  # what a sweep carries over: see DPSampler.sweep

INITS = ("single", "sequential")


class DPNumericalError(torch.linalg.LinAlgError):
    """A sweep of ``DPSampler`` met a matrix that does not factorise in float64. Its message
    compares the data's scale with the prior's: the usual cause is a prior on another scale
    than the data (H's update then adds a tiny Σ0 to a huge scatter, which rounds to a
    singular matrix). A ``torch.linalg.LinAlgError``, so code that already catches numerical
    failures (``Dipole`` skips such a clustering) still does.
    """


class DPSampler:
    """Gibbs sampler of the DP Gaussian mixture, with DIPOLE's reward weighting (eq. 6).

    The model: G ~ DP(α, H), (μ_i, Σ_i) ~ G, y_i ~ N(μ_i, Σ_i + R), with H the non-linked
    ``NormalInverseWishartPrior`` and R its regularisation. A sweep draws
    the labels (``method``), then every component's parameters from their conditionals
    (``resample_parameters``), then, with
    ``update_prior``, H's hyperparameters (Algorithm 1's "update priors").

    Args:
        prior: H at the chain's start; it anchors the hyperpriors of H's update.
        alpha: DP concentration α > 0 (paper: 1).
        m: auxiliary components of Algorithm 8 (paper: 10).
        reward_weighted: eq. 6: each component's probability times r_c, the reward the
            mixture predicts at its mean (y's last column holds positive reward weights);
            ``False``: eq. 5.
        update_prior: redraw H's hyperparameters after every sweep; ``False`` keeps H fixed
            at ``prior`` (the chain then samples the DP mixture posterior under that H).
        exact_covariance: the Metropolis-Hastings correction of the Σ step for R;
            ``False`` takes the conjugate draw of the unregularised model, then + R (an
            ablation: a different model).
        inner_steps: alternations of the μ | Σ and Σ | μ draws per sweep.
        auxiliary: ``"fresh"``, Algorithm 8's m draws from H for every point (the paper's);
            ``"reuse"``, one set of m a sweep, a slot redrawn when a point takes it (Favaro
            & Teh 2013, exact too; CPU only).
        method: ``"neal8"``, label by label (``neal8_sweep``);
            ``"slice"``, every label at once (``slice_sweep``;
            exact, for large N and GPUs; eq. 5 only, ``m`` and ``auxiliary`` unused).

    Example:
        >>> g = torch.Generator().manual_seed(2)
        >>> y = torch.randn(100, 2, generator=g, dtype=torch.float64)
        >>> y[:50] -= 4
        >>> y[50:] += 4
        >>> prior = NormalInverseWishartPrior(  # means spread like the data, E[Σ] = 2 I
        ...     mean_loc=y.mean(0), mean_covariance=torch.cov(y.T), df=8.0,
        ...     scale=10.0 * torch.eye(2, dtype=torch.float64),
        ...     regularization=1e-3 * torch.eye(2, dtype=torch.float64))
        >>> sampler = DPSampler(prior, update_prior=False)
        >>> state = sampler.fit(y, num_sweeps=20, generator=g, init="sequential")
        >>> state.counts[state.counts >= 10].tolist()  # (tiny clusters may hold tail points)
        [50, 50]
    """

    def __init__(
        self,
        prior: NormalInverseWishartPrior,
        alpha: float = 1.0,
        m: int = 10,
        reward_weighted: bool = False,
        update_prior: bool = True,
        exact_covariance: bool = True,
        inner_steps: int = 2,
        auxiliary: str = "fresh",
        method: str = "neal8",
    ):
        if not isinstance(prior, NormalInverseWishartPrior):
            raise TypeError(f"prior must be a NormalInverseWishartPrior, got {type(prior)}")
        check_positive_finite(alpha, "alpha")
        check_count(m, "m")
        check_count(inner_steps, "inner_steps")
        check_choice(auxiliary, ("fresh", "reuse"), "auxiliary")
        check_choice(method, ("neal8", "slice"), "method")
        if method == "slice" and (reward_weighted or auxiliary == "reuse"):
            raise ValueError(
                "method='slice' samples the unweighted DP mixture with its own draws: "
                "reward_weighted must be False and auxiliary 'fresh'"
            )
        self.prior = prior
        self.alpha = float(alpha)
        self.m = int(m)
        self.reward_weighted = bool(reward_weighted)
        self.update_prior = bool(update_prior)
        self.exact_covariance = bool(exact_covariance)
        self.inner_steps = int(inner_steps)
        self.auxiliary = auxiliary
        self.method = method

    def __repr__(self) -> str:
        options = ", ".join(
            f"{name}={getattr(self, name)!r}"
            for name in ("alpha", "m", "reward_weighted", "update_prior", "auxiliary", "method")
        )
        return f"DPSampler({options})"

    # ------------------------------------------------------------------ a chain
    def start(
        self, y: Tensor, init: str = "single", generator: torch.Generator | None = None
    ) -> DPMixtureState:
        """A chain's first state on ``y: [N, D]``: ``"single"``, Algorithm 1's one component
        with the data's mean and covariance; ``"sequential"``, labels from one sequential
        Chinese-restaurant pass (``sequential_labels``: for a
        large, fresh data set, where single-site moves split one component too slowly)."""
        check_choice(init, INITS, "init")
        if init == "single":
            return DPMixtureState.single_component(y, self.prior)
        return DPMixtureState.sequential(y, self.prior, self.alpha, generator)

    def to_chain(self, state: DPMixtureState) -> Chain:
        """What ``sweep`` carries from ``state``: the state itself for Algorithm 8, a
        ``SliceChain`` (stick labels) for the slice sampler."""
        return SliceChain.from_state(state) if self.method == "slice" else state

    @staticmethod
    def to_state(chain: Chain) -> DPMixtureState:
        """The ``DPMixtureState`` of a chain (contiguous labels, occupied components)."""
        return chain.state() if isinstance(chain, SliceChain) else chain

    def sweep(self, y: Tensor, chain: Chain, generator: torch.Generator | None = None) -> Chain:
        """One sweep from ``chain`` (``to_chain``) on ``y: [N, D]`` (float64).

        Raises:
            DPNumericalError: a matrix of the sweep did not factorise (see its message).
        """
        try:
            if self.method == "slice":
                return slice_sweep(y, chain, self, generator)
            return neal8_sweep(y, chain, self, generator)
        except torch.linalg.LinAlgError as error:
            raise DPNumericalError(_failure_message(y, self.prior, error)) from error

    def checked_data(self, y: Tensor) -> Tensor:
        """``y: [N, D]`` (N ≥ 1, finite, D the prior's dimension) in float64, or a
        ``ValueError`` naming what is wrong; with ``reward_weighted``, its last column must
        hold positive reward weights (eq. 6 multiplies by them: a non-positive one was
        clamped to a tiny floor, silently weakening eq. 6)."""
        check_matrix_shape(y, (-1, self.prior.dim), "y")
        check_finite(y, "y")
        if y.shape[0] < 1:
            raise ValueError("y must contain at least one point")
        y = y.to(DTYPE)
        if self.reward_weighted and not bool((y[:, -1] > 0).all()):
            raise ValueError(
                f"y's last column must hold positive reward weights with reward_weighted=True "
                f"(eq. 6), got {float(y[:, -1].min()):g} at least: map the returns onto "
                "positive weights first (dipole_torch.RewardScale)"
            )
        return y

    def fit(
        self,
        y: Tensor,
        num_sweeps: int = 50,
        generator: torch.Generator | None = None,
        state: DPMixtureState | None = None,
        init: str = "single",
        settle: int | None = None,
    ) -> DPMixtureState:
        """``num_sweeps`` sweeps on ``y`` from ``state`` (or from ``start`` with
        ``init``); the last state.

        With ``settle``, the chain stops early once ``settle`` sweeps in a row have left
        the partition unchanged (the same groups of points, whatever the labels' numbers).
        Each sweep is still an exact transition of the chain; what changes is how many run.
        Meant for a warm start, where the partition of the last clustering usually stands:
        from Algorithm 1's single component, a first sweep that splits nothing would end a
        chain that has not begun to mix.

        Args:
            y: ``[N, D]`` data, N ≥ 1, finite, D the prior's dimension.
            num_sweeps: sweeps to run (≥ 1).
            generator: source of all randomness.
            state: where the chain starts (``state.labels: [N]``); overrides ``init``.
            init: ``"single"`` or ``"sequential"`` (see ``start``).
            settle: unchanged sweeps in a row that end the chain early (None: never).
        """
        y = self.checked_data(y)
        check_count(num_sweeps, "num_sweeps")
        if state is None:
            state = self.start(y, init, generator)
        else:
            # A component without a point may start a chain (the paper's clustering starts
            # from every policy's component, and a policy may own none of the points).
            state.check(self.prior.dim, y.shape[0], allow_empty=True)
        check_count(settle, "settle", optional=True)
        chain = self.to_chain(state)
        partition = None if settle is None else _partition(state.labels)
        unchanged = 0
        for _ in range(num_sweeps):
            chain = self.sweep(y, chain, generator)
            if settle is None:
                continue
            current = _partition(self.to_state(chain).labels)
            unchanged = unchanged + 1 if current == partition else 0
            partition = current
            if unchanged >= settle:
                break
        return self.to_state(chain)


def _failure_message(y: Tensor, prior: NormalInverseWishartPrior, error: Exception) -> str:
    """Why a sweep failed, in the data's and the prior's terms (computed only on failure)."""
    prior_std = torch.maximum(
        prior.mean_covariance.diagonal(), prior.expected_covariance.diagonal()
    ).sqrt()
    spread = y.std(0) if y.shape[0] > 1 else torch.zeros_like(y[0])
    offset = (y.mean(0) - prior.mean_loc).abs()
    ratio = float((torch.maximum(spread, offset) / prior_std).max())
    distinct = torch.unique(y, dim=0).shape[0]
    message = (
        f"DPSampler: a sweep met a matrix that does not factorise in float64 "
        f"({str(error).splitlines()[0]}). The data y [{y.shape[0]}, {y.shape[1]}] hold "
        f"{distinct} distinct points; their spread and offset from the prior's mean_loc "
        f"reach {ratio:.3g} times the prior's std (from mean_covariance and E[Σ])."
    )
    if ratio > 1e3:
        return message + (
            " The prior is on another scale than the data: give NormalInverseWishartPrior a "
            "mean_covariance and a scale on the data's scale (or rescale y)."
        )
    return message + (
        " The data may be degenerate (repeated points, or points on a lower-dimensional "
        "set): a larger regularization keeps the components' covariances away from singular."
    )


def _partition(labels: Tensor) -> tuple[int, ...]:
    """``labels [N]`` renumbered by first occurrence: equal for two labellings exactly when
    they group the points alike. (In Python: N is a clustering's few points, where one
    ``tolist`` costs less than the torch calls of a batched renumbering.)"""
    first: dict[int, int] = {}
    return tuple(first.setdefault(label, len(first)) for label in labels.tolist())
