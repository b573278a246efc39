"""Retirement, merging and restarts (dipole_torch.mechanisms.retirement): a policy whose
samples straddle two hills restarts from its best one."""

import torch
from test_optimizer import started_dipole, two_optima

F64 = torch.float64


def restart(opt, in_valley):
    """The straddler restart, with ``in_valley [K]`` as the told batch would have set it."""
    opt.retirement._in_valley = tuple(in_valley.tolist())
    opt.retirement.restart_straddlers(opt)


def test_a_policy_whose_samples_straddle_two_hills_restarts_from_its_best():
    # Kept samples on both optima of two_optima, the mean between them (in the valley) and
    # a shrunken exploration: such a policy would retire in the valley. It restarts from
    # its best sample, keeping that sample only, with Σ_start's shape at its samples'
    # spread.
    opt = started_dipole(2, two_optima)
    thetas = torch.tensor([[1.0, 1.0], [1.01, 1.0], [-1.0, -0.98], [-1.02, -1.0]], dtype=F64)
    opt.archive.replace(thetas, two_optima(thetas), torch.zeros(4, dtype=torch.long))
    opt.policy_set.reset(torch.zeros(1, 2, dtype=F64), 1e-6 * torch.eye(2, dtype=F64)[None])
    means, covs = opt.policy_means.clone(), opt.policy_covariances.clone()
    restart(opt, in_valley=torch.zeros(1, dtype=torch.bool))  # latest sample: a tie
    assert torch.equal(opt.policy_means, means) and torch.equal(opt.policy_covariances, covs)
    restart(opt, in_valley=torch.ones(1, dtype=torch.bool))  # latest sample: worse
    assert torch.equal(opt.policy_means[0], thetas[0])
    assert float(opt.policy_covariances[0, 0, 0]) > 0.1
    assert torch.equal(opt.thetas, thetas[:1])


def test_a_straddler_restart_writes_into_no_tensor_a_snapshot_holds():
    # A tell's snapshot (PolicySearch._snapshot) holds the optimizer's tensors themselves:
    # the restart must replace them, not write into them.
    opt = started_dipole(2, two_optima)
    thetas = torch.tensor([[1.0, 1.0], [1.01, 1.0], [-1.0, -0.98], [-1.02, -1.0]], dtype=F64)
    opt.archive.replace(thetas, two_optima(thetas), torch.zeros(4, dtype=torch.long))
    opt.policy_set.reset(torch.zeros(1, 2, dtype=F64), 1e-6 * torch.eye(2, dtype=F64)[None])
    snapshot = opt._snapshot()
    copies = opt.state_dict()
    restart(opt, in_valley=torch.ones(1, dtype=torch.bool))
    assert torch.equal(opt.policy_means[0], thetas[0])  # it did restart
    for key, value in snapshot.items():
        if isinstance(value, torch.Tensor) and key != "generator":
            assert torch.equal(value, copies[key]), key
