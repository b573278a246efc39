"""The wheel: one top-level package (dipole_torch: nothing in Hydra's plugin namespace), the
configs and train.py inside it, a ``dipole-train`` command that trains from a project holding
its own ``models/`` and ``tasks/`` packages, and no side effect on another Hydra app.

The wheel is built offline from a copy of the sources (a stale ``build/`` or egg-info of the
checkout cannot leak into it) and installed with ``pip install --target``; the check runs in
``python -S``, so the editable install's finder (a ``.pth`` file of site-packages) is not
loaded and only the wheel provides ``dipole_torch``.
"""

import json
import os
import shlex
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest
import torch
from test_train import train

ROOT = Path(__file__).resolve().parents[1]
# Not part of a build: environments, outputs, earlier builds, and folders no wheel ships.
SKIP = {".git", ".venv", ".ci-venv", "build", "dist", "outputs", "multirun", "docs"}
SKIP |= {"tests", "benchmarks", "__pycache__", ".pytest_cache", ".ruff_cache"}


def _pip(*args, cwd):
    result = subprocess.run(
        [sys.executable, "-m", "pip", *args, "--no-deps", "--no-index", "--quiet"],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stdout + result.stderr


def _build_wheel(tmp_path: Path) -> Path:
    source = tmp_path / "source"
    shutil.copytree(
        ROOT,
        source,
        ignore=lambda folder, names: [
            n for n in names if n in SKIP or n.endswith(".egg-info") or n.endswith(".pyc")
        ],
    )
    _pip("wheel", "--no-build-isolation", "-w", str(tmp_path / "wheel"), str(source), cwd=tmp_path)
    (wheel,) = (tmp_path / "wheel").glob("dipole_torch-*.whl")
    return wheel


# Run with python -S from a project of the user's: '' (its directory) first on sys.path, then
# the wheel's install target, then site-packages for the dependencies.
CHECK = """
import json, sys
target, site_packages, run_dir = sys.argv[1:4]
sys.path[1:1] = [target, site_packages]

import models, tasks  # the user's own packages
assert models.OWNER == tasks.OWNER == "user", (models.__file__, tasks.__file__)

import gymnasium as gym
import dipole_torch
import dipole_torch.tasks.viapoint
from dipole_torch.tasks.viapoint import ViapointTask

assert dipole_torch.__path__ == [target + "/dipole_torch"], dipole_torch.__path__
assert dipole_torch.tasks.viapoint.__file__.startswith(target), dipole_torch.tasks.__file__
for name in ("dipole/CartPole-v1", "dipole/MountainCar-v0"):
    env = gym.make(name)
    env.reset(seed=0)
    env.step(env.action_space.sample())
assert ViapointTask().theta0.shape == (9,)  # the bundled URDF, found inside the package

from importlib.metadata import entry_points
(command,) = entry_points(group="console_scripts", name="dipole-train")
main = command.load()
sys.argv = ["dipole-train", "task=viapoint", "trials=30", "progress=false", "figure_every=0",
            "hydra.run.dir=" + run_dir]
main()
assert models.OWNER == tasks.OWNER == "user"
assert not [m for m in sys.modules if m.startswith(("models.", "tasks."))]
print(json.dumps({"command": command.value, "train": sys.modules[main.__module__].__file__}))
"""


def test_wheel_installs_one_package_and_its_command_trains(tmp_path):
    wheel = _build_wheel(tmp_path)
    names = zipfile.ZipFile(wheel).namelist()
    top_level = {
        name.split("/")[0] for name in names if not name.split("/")[0].endswith(".dist-info")
    }
    assert top_level == {"dipole_torch"}, sorted(top_level)
    assert "dipole_torch/train.py" in names
    for package in ("dp", "mechanisms", "training", "configs"):
        assert f"dipole_torch/{package}/__init__.py" in names, package
    assert "dipole_torch/models/wam/wam7.urdf" in names
    configs = sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "configs").rglob("*.yaml"))
    assert configs and all(f"dipole_torch/{c}" in names for c in configs), configs
    for package in ("models", "models/wam", "tasks"):
        sources = {p.name for p in (ROOT / package).glob("*.py")}
        assert all(f"dipole_torch/{package}/{s}" in names for s in sources), package
    (entry_points,) = [n for n in names if n.endswith(".dist-info/entry_points.txt")]
    text = zipfile.ZipFile(wheel).read(entry_points).decode()
    assert "dipole-train = dipole_torch.train:main" in text, text

    target = tmp_path / "installed"
    _pip("install", "--target", str(target), str(wheel), cwd=tmp_path)
    project = tmp_path / "project"  # a user's project with its own models/ and tasks/
    for package in ("models", "tasks"):
        (project / package).mkdir(parents=True)
        (project / package / "__init__.py").write_text('OWNER = "user"\n')
    run_dir = tmp_path / "run"
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    site_packages = sysconfig.get_paths()["purelib"]
    result = subprocess.run(
        [sys.executable, "-S", "-c", CHECK, str(target), site_packages, str(run_dir)],
        cwd=project,
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    checked = json.loads(result.stdout.strip().splitlines()[-1])
    assert checked == {
        "command": "dipole_torch.train:main",
        "train": str(target / "dipole_torch" / "train.py"),
    }
    results = json.loads((run_dir / "results.json").read_text())
    assert results["task"] == "viapoint" and results["trials"] == 30 and results["policies"]
    assert (run_dir / "train.log").read_text()  # Hydra's job logging, named after train.py

    # Installing it changes no other Hydra app: nothing of ours is imported when one starts,
    # and its config groups are its own.
    app = tmp_path / "other_app"
    (app / "conf" / "db").mkdir(parents=True)
    (app / "conf" / "config.yaml").write_text("defaults:\n  - db: mysql\n  - _self_\nx: 1\n")
    (app / "conf" / "db" / "mysql.yaml").write_text("host: localhost\n")
    (app / "app.py").write_text(OTHER_APP)
    for args in ([], ["--help"]):
        result = subprocess.run(
            [sys.executable, "-S", str(app / "app.py"), str(target), site_packages, *args],
            cwd=app,
            capture_output=True,
            text=True,
            env=env,
            timeout=120,
        )
        assert result.returncode == 0, result.stdout + result.stderr
        assert "imported: []" in result.stdout or args, result.stdout
        assert "task" not in result.stdout.split("== Config ==")[0], result.stdout
        assert "dipole" not in result.stdout, result.stdout


# A Hydra app of someone else's, run with the wheel on sys.path.
OTHER_APP = """
import sys
target, site_packages = sys.argv[1:3]
del sys.argv[1:3]
sys.path[1:1] = [target, site_packages]
import hydra

@hydra.main(version_base=None, config_path="conf", config_name="config")
def main(cfg):
    ours = sorted(m for m in sys.modules if m.split(".")[0] in ("dipole_torch", "torch", "pyro"))
    print("imported:", ours)

main()
"""


def test_a_checkpoint_naming_the_old_task_module_resumes(tmp_path):
    """Checkpoints written before tasks/ became dipole_torch.tasks name ``tasks.<module>``."""
    run = tmp_path / "run"
    common = ("task=multimodal", "algo=power", "figure_every=0")
    train(*common, "trials=20", f"hydra.run.dir={run}")
    checkpoint = torch.load(run / "checkpoint.pt", weights_only=True)
    assert "_target_: dipole_torch.tasks.multimodal.MultimodalTask" in checkpoint["config"]
    checkpoint["config"] = checkpoint["config"].replace("dipole_torch.tasks.", "tasks.")
    torch.save(checkpoint, run / "checkpoint.pt")
    train(*common, "trials=40", f"resume={run / 'checkpoint.pt'}")
    assert json.loads((run / "results.json").read_text())["trials"] == 40


def resumes_without(
    tmp_path, common: tuple[str, ...], lines_removed: tuple[str, ...], resume: tuple = ()
) -> None:
    """Train 20 trials, remove ``lines_removed`` (each present once) from the checkpoint's
    config, as a checkpoint from before those keys existed, and resume to 40 trials (with
    the overrides ``resume``). The optimizer's state loses its settings too: checkpoints
    from before those keys are from before the state kept them."""
    run = tmp_path / "run"
    train(*common, "trials=20", f"hydra.run.dir={run}")
    checkpoint = torch.load(run / "checkpoint.pt", weights_only=True)
    lines = checkpoint["config"].splitlines()
    old = [x for x in lines if x.strip() not in lines_removed]
    assert len(old) == len(lines) - len(lines_removed)
    checkpoint["config"] = "\n".join(old) + "\n"
    del checkpoint["optimizer"]["settings"]
    torch.save(checkpoint, run / "checkpoint.pt")
    train(*common, "trials=40", *resume, f"resume={run / 'checkpoint.pt'}")
    assert json.loads((run / "results.json").read_text())["trials"] == 40


def test_a_checkpoint_from_before_pair_points_bounds_and_auxiliary_resumes(tmp_path):
    """Checkpoints written before algo.optimizer.pair_points, .bounds and .auxiliary existed
    lack them: they resume with their defaults (the midpoint test, no box, auto draws)."""
    common = ("task=multimodal", "algo=dipole", "figure_every=0")
    resumes_without(tmp_path, common, ("pair_points: 1", "bounds: null", "auxiliary: auto"))


def test_a_checkpoint_from_before_max_sampled_resumes_as_it_ran(tmp_path):
    """A checkpoint from before algo.optimizer.max_sampled sampled every active policy: the
    default (4) would change its run, so resuming refuses and names the override that
    resumes it as it ran (null), which then works."""
    common = ("task=multimodal", "algo=dipole", "figure_every=0")
    with pytest.raises(AssertionError, match=r"algo\.optimizer\.max_sampled=null"):
        resumes_without(tmp_path / "plain", common, ("max_sampled: 4",))
    resumes_without(
        tmp_path / "null", common, ("max_sampled: 4",), ("algo.optimizer.max_sampled=null",)
    )


def test_a_checkpoint_from_before_waking_resumes_as_it_ran(tmp_path):
    """A checkpoint from before algo.optimizer.refine never woke retired policies: resuming
    refuses and names the override that resumes it as it ran (refine=0), which then works;
    refine_share (a share of the wakes' trials) has no effect without them."""
    common = ("task=multimodal", "algo=dipole", "figure_every=0")
    removed = ("refine: 0.1", "refine_share: 0.2")
    with pytest.raises(AssertionError, match=r"algo\.optimizer\.refine=0\.0"):
        resumes_without(tmp_path / "plain", common, removed)
    resumes_without(tmp_path / "zero", common, removed, ("algo.optimizer.refine=0.0",))


def test_a_paper_checkpoint_with_the_options_its_schema_dropped_resumes(tmp_path):
    """algo=dipole_paper's schema listed options its algorithm leaves inert (restarts,
    refine_share, pair_points, the unjudged ones) until they were dropped: its checkpoints
    from before have them, and resume without them."""
    run = tmp_path / "run"
    common = ("task=multimodal", "algo=dipole_paper", "figure_every=0")
    train(*common, "trials=20", f"hydra.run.dir={run}")
    checkpoint = torch.load(run / "checkpoint.pt", weights_only=True)
    lines = checkpoint["config"].splitlines()
    at = lines.index("    alpha: 1.0") + 1
    dropped = [
        "    restarts: box",
        "    pair_points: 1",
        "    accept_unjudged: false",
        "    unjudged_share: null",
        "    coverage_from: null",
        "    refine_share: 0.2",
    ]
    checkpoint["config"] = "\n".join([*lines[:at], *dropped, *lines[at:]]) + "\n"
    torch.save(checkpoint, run / "checkpoint.pt")
    train(*common, "trials=40", f"resume={run / 'checkpoint.pt'}")
    assert json.loads((run / "results.json").read_text())["trials"] == 40


def test_a_cartpole_checkpoint_from_before_the_engines_resumes(tmp_path):
    """Checkpoints written before task.env.engine existed lack it: they resume with "auto"."""
    common = ("task=cartpole", "algo=power", "figure_every=0", "task.env.steps=50")
    resumes_without(tmp_path, common, ("engine: auto",))


def test_the_resume_command_names_the_command_that_ran(monkeypatch):
    from dipole_torch.training.resume import resume_command

    monkeypatch.setattr(sys, "argv", ["/env/bin/dipole-train", "task=viapoint"])
    assert resume_command(["task=viapoint"], "/r/checkpoint.pt") == (
        "dipole-train task=viapoint resume=/r/checkpoint.pt"
    )
    monkeypatch.setattr(sys, "argv", ["train.py", "task=viapoint"])
    assert resume_command(["task=viapoint"], "/r/checkpoint.pt") == (
        "python train.py task=viapoint resume=/r/checkpoint.pt"
    )


@pytest.mark.parametrize(
    "path",
    [
        "/m/viapoint_dipole_seed0_algo.optimizer.alpha=2/checkpoint.pt",  # a sweep's directory
        "/m/runs [1,2]/a 'b' \"c\"/checkpoint.pt",
    ],
)
def test_the_resume_command_quotes_a_path_that_hydra_would_parse(monkeypatch, path):
    """A sweep run's directory holds "=" (``_algo.optimizer.alpha=2``): the printed command,
    pasted, ended in Hydra's "mismatched input '=' expecting <EOF>". The shell's words of the
    command are overrides that Hydra parses back to the path."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from dipole_torch.training.resume import resume_command

    monkeypatch.setattr(sys, "argv", ["train.py", "task=viapoint"])
    words = shlex.split(resume_command(["task=viapoint"], path))
    parsed = OverridesParser.create().parse_overrides(words[2:])
    assert [(o.key_or_group, o.value()) for o in parsed] == [
        ("task", "viapoint"),
        ("resume", path),
    ]
