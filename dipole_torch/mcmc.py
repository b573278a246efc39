"""Neal's Algorithm 8, and the slice sampler, as Pyro MCMC kernels.

``pyro.infer.MCMC(Neal8Kernel(prior), num_samples=..., warmup_steps=...).run(y)`` runs the
Gibbs sweeps of :func:`dipole_torch.neal8_sweep` with Pyro's progress bar, and keeps
label-switching-invariant summaries of every kept state for ``get_samples()``,
``summary()`` and ``diagnostics()``.

The kernel adds nothing to the chain: with the same generator it makes exactly the sweeps of
:func:`dipole_torch.fit_dp_mixture` (``tests/test_mcmc.py`` checks this). It does add
bookkeeping: on a DIPOLE-sized clustering (50 points, D = 10) a sweep under ``MCMC`` costs
1.2–1.3× the direct one with the per-sample log joint and 1.0–1.2× without it
(``benchmarks/bench_mcmc_kernel.py``). DIPOLE's own clusterings therefore call
:func:`~dipole_torch.fit_dp_mixture` directly.
"""

from __future__ import annotations

import torch
from pyro.infer.mcmc.mcmc_kernel import MCMCKernel
from torch import Tensor

from dipole_torch.dp_mixture import DTYPE, DPMixtureState, neal8_sweep, sequential_labels
from dipole_torch.prior import NormalInverseWishartPrior
from dipole_torch.pyro_model import canonical_state, dp_log_joint
from dipole_torch.slice_sampler import SliceChain, slice_sweep
from dipole_torch.validation import check_finite, check_matrix_shape

__all__ = ["Neal8Kernel", "SliceKernel"]


class Neal8Kernel(MCMCKernel):
    """One step = one Gibbs sweep of Neal's (2000) Algorithm 8 on the DP Gaussian mixture.

    Run it with ``pyro.infer.MCMC(kernel, num_samples, warmup_steps).run(y)``, ``y: [N, D]``.
    Each kept sample holds (MCMC stores every site as float64, labels included):

    * ``num_components``: ``[]`` K, the number of occupied components;
    * ``labels``: ``[N]`` component of each point, numbered in order of first appearance
      (so that they do not switch between samples);
    * ``point_means``: ``[N, D]`` μ_{c_i}, the mean of the component of each point;
    * ``log_joint``: ``[]`` log p(labels, μ, Σ, y) under the state's H
      (:func:`dipole_torch.pyro_model.dp_log_joint`; with ``reward_weighted=True`` the chain
      samples a reweighted distribution and this is a diagnostic only).

    ``MCMC(..., save_params=[...])`` keeps a subset. The full current state (a
    :class:`~dipole_torch.DPMixtureState`, e.g. ``kernel.state.mixture()``) is
    :attr:`state`; a ``hook_fn(kernel, params, stage, i)`` passed to ``MCMC`` sees every one.

    Args:
        prior: the base distribution H.
        alpha: DP concentration α > 0.
        m: auxiliary components per point (≥ 1).
        reward_weighted: eq. 6's reward weighting (the last column of y is the weight).
        update_prior: redraw H's hyperparameters after every sweep (DIPOLE's Algorithm 1);
            the default ``False`` samples the DP mixture posterior under a fixed H.
        exact_covariance: the Metropolis-Hastings correction of the Σ step.
        inner_steps: μ | Σ and Σ | μ alternations per sweep.
        init: ``"single"`` (one component, Algorithm 1's start) or ``"sequential"`` (one
            sequential CRP pass); ignored when ``MCMC(initial_params={"labels": ...})`` or
            :attr:`initial_params` gives labels.
        generator: source of all randomness (``None``: the global RNG, e.g.
            ``pyro.set_rng_seed``).

    Example:
        >>> from pyro.infer import MCMC
        >>> from dipole_torch import NormalInverseWishartPrior
        >>> g = torch.Generator().manual_seed(0)
        >>> y = torch.randn(40, 2, generator=g)
        >>> y[:20] -= 3
        >>> y[20:] += 3
        >>> prior = NormalInverseWishartPrior.from_exploration(
        ...     torch.zeros(2, dtype=torch.float64), 9 * torch.eye(2, dtype=torch.float64))
        >>> kernel = Neal8Kernel(prior, m=3, init="sequential", generator=g)
        >>> mcmc = MCMC(kernel, num_samples=10, warmup_steps=5, disable_progbar=True)
        >>> mcmc.run(y)
        >>> labels = mcmc.get_samples()["labels"]  # [10, 40]: the two groups never mix
        >>> labels.shape, bool((labels[:, :20, None] != labels[:, None, 20:]).all())
        (torch.Size([10, 40]), True)
    """

    def __init__(
        self,
        prior: NormalInverseWishartPrior,
        alpha: float = 1.0,
        m: int = 10,
        reward_weighted: bool = False,
        update_prior: bool = False,
        exact_covariance: bool = True,
        inner_steps: int = 2,
        init: str = "single",
        generator: torch.Generator | None = None,
    ):
        if not isinstance(prior, NormalInverseWishartPrior):
            raise TypeError(f"prior must be a NormalInverseWishartPrior, got {type(prior)}")
        if not alpha > 0:
            raise ValueError(f"alpha must be positive, got {alpha}")
        if int(m) != m or m < 1:
            raise ValueError(f"m must be a positive integer, got {m}")
        if int(inner_steps) != inner_steps or inner_steps < 1:
            raise ValueError(f"inner_steps must be a positive integer, got {inner_steps}")
        if init not in ("single", "sequential"):
            raise ValueError(f"init must be 'single' or 'sequential', got {init!r}")
        self.prior = prior
        self.alpha = float(alpha)
        self.m = int(m)
        self.reward_weighted = reward_weighted
        self.update_prior = update_prior
        self.exact_covariance = exact_covariance
        self.inner_steps = int(inner_steps)
        self.init = init
        self.generator = generator
        # MCMC reads these: samples are stored as they are (no unconstraining transforms),
        # and there is no Pyro model to trace.
        self.transforms: dict = {}
        self.model = None
        self._initial_labels: Tensor | None = None
        self._y: Tensor | None = None
        self._state: DPMixtureState | None = None
        self._params: dict[str, Tensor] | None = None
        self._num_sweeps = 0

    # ------------------------------------------------------------------ the MCMCKernel API
    def setup(self, warmup_steps: int, y: Tensor) -> None:
        """Start a chain on ``y: [N, D]`` (called by ``MCMC.run(y)``)."""
        check_matrix_shape(y, (-1, self.prior.dim), "y")
        check_finite(y, "y")
        if y.shape[0] < 1:
            raise ValueError("y must contain at least one point")
        y = y.to(DTYPE)
        self._y = y
        if self._initial_labels is not None:
            if self._initial_labels.shape != (y.shape[0],):
                raise ValueError(
                    f"initial labels must have shape [{y.shape[0]}], "
                    f"got {list(self._initial_labels.shape)}"
                )
            state = DPMixtureState.from_labels(y, self._initial_labels, self.prior)
        elif self.init == "single":
            state = DPMixtureState.single_component(y, self.prior)
        else:
            labels = sequential_labels(y, self.prior, self.alpha, self.generator)
            state = DPMixtureState.from_labels(y, labels, self.prior)
        self._set_state(state)
        self._num_sweeps = 0

    @property
    def initial_params(self) -> dict[str, Tensor]:
        """The summaries of the chain's start (after :meth:`setup`)."""
        if self._params is None:
            raise RuntimeError("initial_params exist after setup(warmup_steps, y)")
        return self._params

    @initial_params.setter
    def initial_params(self, params: dict[str, Tensor]) -> None:
        """Start the next chain from ``params["labels"]: [N]`` (any integer numbering); the
        component parameters start at their conditional posterior means."""
        if "labels" not in params:
            raise ValueError(f"initial_params must contain 'labels', got {sorted(params)}")
        labels = torch.as_tensor(params["labels"])
        if labels.dim() != 1 or (labels != labels.round()).any():
            raise ValueError(f"initial labels must be [N] integers, got {labels}")
        self._initial_labels = labels.long()

    def sample(self, params: dict[str, Tensor]) -> dict[str, Tensor]:
        """One Gibbs sweep from the current state; ``params`` (the previous summaries) only
        mirror it."""
        if self._state is None or self._y is None:
            raise RuntimeError("call setup(warmup_steps, y) before sample()")
        state = self._sweep(self._y)
        self._num_sweeps += 1
        return self._set_state(state)

    def _sweep(self, y: Tensor) -> DPMixtureState:
        """One sweep of Algorithm 8 from the current state; the new state."""
        return neal8_sweep(
            y,
            self.state,
            self.alpha,
            self.m,
            self.reward_weighted,
            self.generator,
            self.inner_steps,
            initial_prior=self.prior,
            update_prior=self.update_prior,
            exact_covariance=self.exact_covariance,
        )

    def logging(self) -> dict[str, int]:
        """Shown next to Pyro's progress bar: the current number of components."""
        return {"K": self._state.num_components if self._state is not None else 0}

    def diagnostics(self) -> dict[str, int]:
        return {"num_sweeps": self._num_sweeps}

    # ------------------------------------------------------------------ helpers
    @property
    def state(self) -> DPMixtureState:
        """The chain's current state (labels, means, covariances Σ + R, H)."""
        if self._state is None:
            raise RuntimeError("the kernel has no state before setup(warmup_steps, y)")
        return self._state

    def _set_state(self, state: DPMixtureState) -> dict[str, Tensor]:
        assert self._y is not None
        self._state = state
        canonical = canonical_state(state)
        k = torch.tensor(float(state.num_components), dtype=DTYPE, device=self._y.device)
        self._params = {
            "num_components": k,
            "labels": canonical.labels.to(DTYPE),
            "point_means": canonical.means[canonical.labels],
        }
        # MCMC(save_params=...) sets save_params: the log joint only when it is kept.
        if "log_joint" in getattr(self, "save_params", ("log_joint",)):
            self._params["log_joint"] = dp_log_joint(self._y, state, self.alpha)
        return self._params


class SliceKernel(Neal8Kernel):
    """One step = one sweep of the slice sampler (:mod:`dipole_torch.slice_sampler`: every
    label drawn at once; exact, for large N and GPUs), with :class:`Neal8Kernel`'s samples,
    arguments and API. The sweeps are those of
    ``fit_dp_mixture(..., sampler="slice")`` with the same generator. There is no ``m`` and
    no reward weighting; the stick of every point (:attr:`chain`) is kept between steps.

    Example:
        >>> from pyro.infer import MCMC
        >>> from dipole_torch import NormalInverseWishartPrior
        >>> g = torch.Generator().manual_seed(0)
        >>> y = torch.randn(400, 2, generator=g)
        >>> y[:200] -= 3
        >>> y[200:] += 3
        >>> prior = NormalInverseWishartPrior.from_exploration(
        ...     torch.zeros(2, dtype=torch.float64), 9 * torch.eye(2, dtype=torch.float64))
        >>> kernel = SliceKernel(prior, init="sequential", generator=g)
        >>> mcmc = MCMC(kernel, num_samples=10, warmup_steps=5, disable_progbar=True)
        >>> mcmc.run(y)
        >>> samples = mcmc.get_samples()  # labels [10, 400]; never fewer than the 2 groups
        >>> samples["labels"].shape, bool(samples["num_components"].min() >= 2)
        (torch.Size([10, 400]), True)
    """

    def __init__(
        self,
        prior: NormalInverseWishartPrior,
        alpha: float = 1.0,
        update_prior: bool = False,
        exact_covariance: bool = True,
        inner_steps: int = 2,
        init: str = "single",
        generator: torch.Generator | None = None,
    ):
        super().__init__(
            prior,
            alpha,
            update_prior=update_prior,
            exact_covariance=exact_covariance,
            inner_steps=inner_steps,
            init=init,
            generator=generator,
        )
        self._chain: SliceChain | None = None

    def setup(self, warmup_steps: int, y: Tensor) -> None:
        super().setup(warmup_steps, y)
        self._chain = SliceChain.from_state(self.state)

    @property
    def chain(self) -> SliceChain:
        """The slice sampler's current state (stick labels, every stick's atom, H)."""
        if self._chain is None:
            raise RuntimeError("the kernel has no state before setup(warmup_steps, y)")
        return self._chain

    def _sweep(self, y: Tensor) -> DPMixtureState:
        """One slice-sampler sweep from the current chain (kept with its stick labels); the
        new state."""
        self._chain = slice_sweep(
            y,
            self.chain,
            self.alpha,
            self.generator,
            self.inner_steps,
            initial_prior=self.prior,
            update_prior=self.update_prior,
            exact_covariance=self.exact_covariance,
        )
        return self._chain.state()
