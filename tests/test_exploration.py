"""Exploration (dipole_torch.mechanisms.exploration): the success rule's constants and
updates, and a new policy's starting covariance."""

import torch
from test_optimizer import two_optima

from dipole_torch import Dipole

F64 = torch.float64


def test_new_policies_explore_with_the_shape_of_sigma_start():
    # The default variant starts each policy at Σ_start's shape, scaled to its component's
    # spread (a few points in 10-D give a badly conditioned posterior covariance); the
    # paper's variant keeps the posterior covariance itself.
    d = 10
    sigma_start = torch.diag(torch.linspace(0.5, 2.0, d, dtype=F64))
    for paper in (False, True):
        build = Dipole.paper if paper else Dipole
        extra = {"reward_range": (-1e4, 0.0)} if paper else {}
        opt = build(
            torch.zeros(d, dtype=F64),
            sigma_start,
            generator=torch.Generator().manual_seed(0),
            **extra,
        )
        theta = opt.ask()
        opt.tell(theta, two_optima(theta))
        ratio = opt.policy_covariances / sigma_start  # elementwise: off-diagonals are 0/0
        diag = ratio.diagonal(dim1=-2, dim2=-1)  # [K, D]
        condition = torch.linalg.cond(opt.policy_covariances)
        if paper:
            assert (condition > 5 * torch.linalg.cond(sigma_start)).all()
        else:
            assert torch.allclose(diag, diag[:, :1].expand_as(diag))
            assert (diag <= 1.0 + 1e-12).all()
            off = opt.policy_covariances - torch.diag_embed(
                opt.policy_covariances.diagonal(dim1=-2, dim2=-1)
            )
            assert off.abs().max() < 1e-12
