"""The Pyro-prior and gymnasium examples of the user guide (docs/guide/pyro.md,
docs/guide/gymnasium.md) run as printed, and print what they claim."""

import os
import re
from pathlib import Path

import torch
from test_docs_examples import DOCS, block

from dipole_torch import GaussianMixture


def _example(page: str, marker: str) -> str:
    return block(DOCS / page, marker).code


def _run(code: str, where: Path) -> None:
    cwd = os.getcwd()
    os.chdir(where)
    try:
        exec(compile(code, "docs example", "exec"), {})
    finally:
        os.chdir(cwd)


def test_pyro_prior_example_keeps_only_the_policies_the_change_allows(tmp_path, capsys):
    # A finished run's policies.pt, as train.py writes it: four policies, two with θ_0 > 0
    # (and its results.json, by which the example finds the newest finished run).
    means = 0.7 * torch.tensor([[1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [1.0, -1.0]])
    policies = GaussianMixture(
        torch.tensor([3.0, 5.0, 4.0, 4.0]), means, 0.01 * torch.eye(2).expand(4, 2, 2)
    ).to(torch.float64)
    run = tmp_path / "outputs" / "multimodal" / "dipole" / "seed0_2026-01-01_00-00-00"
    run.mkdir(parents=True)
    torch.save({"policies": policies.state_dict()}, run / "policies.pt")
    (run / "results.json").write_text("{}")
    _run(_example("guide/pyro.md", "pyro-prior-example"), tmp_path)
    out = capsys.readouterr().out
    share = [float(p) for p in re.search(r"change: \[(.*)\]", out).group(1).split(",")]
    # Policies 1 and 2 sit at θ_0 = -0.7, 14 widths behind the obstacle: no share left.
    assert share[1] == share[2] == 0.0
    # Policies 0 and 3 keep their prior proportions 3 : 4 (of 300 resampled draws).
    assert abs(share[0] - 3 / 7) < 0.1 and abs(share[3] - 4 / 7) < 0.1


def test_gym_example_balances_the_pole_and_reaches_the_goal(tmp_path, capsys):
    _run(_example("guide/gymnasium.md", "gym-example"), tmp_path)
    out = capsys.readouterr().out
    cartpole = float(re.search(r"cart-pole return: (\S+)", out).group(1))
    car = float(re.search(r"mountain-car return: (\S+)", out).group(1))
    assert cartpole == 1000.0  # upright for all 1000 steps
    assert car > 0.0  # reached the goal (101 - t at step t; 0 otherwise)
