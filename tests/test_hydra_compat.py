"""The Hydra and OmegaConf calls spelled for the installed releases: no deprecation warning on
either (``.ci/prerelease-versions`` runs the suite on Hydra 1.4 and omegaconf 2.4)."""

from __future__ import annotations

import warnings

import hydra
import pytest
from dipole_torch.tasks.multimodal import MultimodalTask
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from dipole_torch.training import hydra_compat
from dipole_torch.training.hydra_compat import VERSION_BASE, instantiate, register_resolver


@pytest.mark.parametrize(
    "version, release",
    [("1.3.8", (1, 3)), ("1.4.0rc3", (1, 4)), ("2.4.0.dev15", (2, 4)), ("10.12", (10, 12))],
)
def test_release(version, release):
    assert hydra_compat._release(version) == release


def test_release_of_an_unreadable_version():
    with pytest.raises(ValueError, match="cannot read a version from 'main'"):
        hydra_compat._release("main")


def test_version_base_follows_the_installed_hydra():
    major_minor = tuple(int(part) for part in hydra.__version__.split(".")[:2])
    assert VERSION_BASE == ({} if major_minor >= (1, 4) else {"version_base": None})


def test_compose_and_instantiate_without_warnings():
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with initialize_config_module("dipole_torch.configs", **VERSION_BASE):
            cfg = compose("config", overrides=["task=multimodal", "algo=dipole", "seed=3"])
        task = instantiate(cfg.task.env)
        optimizer = instantiate(
            cfg.algo.optimizer,
            _convert_="all",
            theta0=task.theta0.double(),
            sigma_start=task.sigma_start.double(),
            n0=cfg.task.n0,
        )
    assert isinstance(task, MultimodalTask) and optimizer.dim == task.theta0.numel()
    assert [str(w.message) for w in caught] == []


class Point:
    """A target of the config's own (this module, outside the package)."""

    def __init__(self, x: float, y: float):
        self.x, self.y = x, y


def test_a_config_builds_a_target_of_its_own():
    """The top-level target a config names is trusted (``train.py``'s config is its user's:
    a task of one's own, docs/guide/configs.md)."""
    config = OmegaConf.create({"_target_": f"{__name__}.Point", "x": 1.0, "y": 2.0})
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        built = instantiate(config)
    assert (built.x, built.y) == (1.0, 2.0) and [str(w.message) for w in caught] == []


@pytest.mark.parametrize(
    "target, trusted",
    [
        ("my_task.TwoHills", True),
        ("dipole_torch.Dipole", True),
        ("shutil.rmtree", False),
        ("os.kill", False),
        ("builtins.exit", False),
        ("collections.OrderedDict", False),
        ("", False),
        (None, False),
    ],
)
def test_which_top_level_targets_are_trusted_by_name(target, trusted):
    assert hydra_compat._trusted_by_name(target) is trusted


@pytest.mark.skipif(not hydra_compat.HYDRA_1_4, reason="Hydra 1.4's execution whitelist")
@pytest.mark.parametrize(
    "config",
    [
        {"_target_": f"{__name__}.Point", "x": {"_target_": "os.getcwd"}, "y": 0.0},
        {"_target_": "shutil.rmtree", "path": "/no/such/dipole/dir"},
    ],
    ids=["below the top", "the standard library's at the top"],
)
def test_targets_not_trusted_are_refused(config):
    from hydra.errors import InstantiationException

    with pytest.raises(InstantiationException, match="os.getcwd|shutil.rmtree"):
        instantiate(OmegaConf.create(config))


def test_register_resolver_without_warnings():
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        register_resolver("dipole_test_join", lambda a, b: f"{a}+{b}")
        register_resolver("dipole_test_join", lambda a, b: f"{a}-{b}")  # replaced
    config = OmegaConf.create({"x": 2, "y": "${dipole_test_join:${x},3}"})
    assert config.y == "2-3" and [str(w.message) for w in caught] == []
