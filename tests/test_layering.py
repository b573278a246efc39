"""The library's dependencies go one way: nothing under dipole_torch but its training
application (dipole_torch.training, and the configs that register its schemas) imports
Hydra, TensorBoard, the tasks or the models; ``import dipole_torch`` leaves its MCMC kernel
, Pyro model and Gaussian mixture (Pyro's) to their first use: an optimizer's iterations do
not import Pyro."""

import json
import subprocess
import sys

CHECK = """
import json, pkgutil, sys
import dipole_torch
app = ("dipole_torch.training", "dipole_torch.configs")
lazy = ("dipole_torch.mcmc", "dipole_torch.pyro_model", "dipole_torch.gaussian_mixture", "pyro")
after_init = sorted(m for m in lazy if m in sys.modules)
core = []

def walk(path, prefix):  # (pkgutil.walk_packages would import the application's packages)
    for module in pkgutil.iter_modules([path]):
        name = prefix + module.name
        if name.startswith(app):
            continue
        __import__(name)
        core.append(name)
        if module.ispkg:
            walk(f"{path}/{module.name}", name + ".")

walk(dipole_torch.__path__[0], "dipole_torch.")
forbidden = ("hydra", "omegaconf", "tensorboard", "torch.utils.tensorboard",
             "dipole_torch.tasks", "dipole_torch.models", *app)
imported = sorted(m for m in sys.modules if m.startswith(forbidden))
print(json.dumps({"core": core, "imported": imported, "pyro_at_import": after_init}))
"""


def test_the_library_core_imports_no_application():
    result = subprocess.run(
        [sys.executable, "-c", CHECK], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout.strip().splitlines()[-1])
    assert {"dipole_torch.dipole", "dipole_torch.dp.sampler", "dipole_torch.mcmc"} <= set(
        report["core"]
    )
    assert report["imported"] == [], report["imported"]
    assert report["pyro_at_import"] == []  # they come with the first of their names used


ITERATIONS = """
import json, sys, torch
import dipole_torch
opt = dipole_torch.Dipole([0.0, 0.0], 0.5, generator=torch.Generator().manual_seed(0))
while not opt.stop(max_trials=200):
    theta = opt.ask()
    opt.tell(theta, -(theta**2).sum(-1))
during = "pyro" in sys.modules
mixture = opt.mixture  # the first use of GaussianMixture imports it, and Pyro
same = type(mixture) is dipole_torch.GaussianMixture
print(json.dumps({"pyro_during": during, "pyro_after": "pyro" in sys.modules,
                  "mixture": type(mixture).__name__, "same": same}))
"""


def test_iterations_do_not_import_pyro_until_a_mixture_is_built():
    result = subprocess.run(
        [sys.executable, "-c", ITERATIONS], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout.strip().splitlines()[-1])
    assert report == {
        "pyro_during": False,
        "pyro_after": True,
        "mixture": "GaussianMixture",
        "same": True,
    }


START = """
import json, sys
from hydra.core.config_store import ConfigStore
from dipole_torch.training.config import register
stores = []
store = ConfigStore.instance()
original = store.store
store.store = lambda **kwargs: (stores.append(kwargs["name"]), original(**kwargs))
register()
first = len(stores)
import dipole_torch.configs  # registers again, as --help does
register()
print(json.dumps({"pyro": "pyro" in sys.modules, "first": first, "again": len(stores) - first}))
"""


def test_the_training_start_imports_no_pyro_and_stores_each_schema_once():
    result = subprocess.run(
        [sys.executable, "-c", START], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout.strip().splitlines()[-1])
    assert report["pyro"] is False  # every task's schema, the viapoint task's model too
    assert report["first"] >= 9  # the config, the task base, 4 tasks, 3 algorithms
    assert report["again"] == 0
