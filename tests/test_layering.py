"""The library's dependencies go one way: nothing under dipole_torch but its training
application (dipole_torch.training, and the configs that register its schemas) imports
Hydra, TensorBoard, the tasks or the models; ``import dipole_torch`` leaves its MCMC kernel
and Pyro model to their first use."""

import json
import subprocess
import sys

CHECK = """
import json, pkgutil, sys
import dipole_torch
app = ("dipole_torch.training", "dipole_torch.configs")
after_init = sorted(m for m in ("dipole_torch.mcmc", "dipole_torch.pyro_model") if m in sys.modules)
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
