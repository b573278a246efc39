"""The benchmark scripts' command lines: the ``--help`` text and bad option values."""

import argparse
import ast
import importlib
import re
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))
SCRIPTS = sorted(p for p in BENCHMARKS.glob("*.py") if "argparse.ArgumentParser(" in p.read_text())


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.name)
def test_the_help_describes_a_script_in_whole_sentences(script):
    # ``--help`` shows the docstring's first paragraph, not its first line (cut mid-sentence:
    # "… against the CPU a trial may").
    source = script.read_text()
    assert "__doc__.splitlines()[0]" not in source
    assert 'description=__doc__.split("\\n\\n")[0]' in source
    first = ast.get_docstring(ast.parse(source), clean=False).split("\n\n")[0].rstrip()
    assert re.search(r"[.?!)]$", first), f"{script.name}: {first[-60:]!r}"


PARSE_ARGS = argparse.ArgumentParser.parse_args


def exit_of_parsing(monkeypatch, module, argv: list[str]) -> int:
    """The exit status of ``module.main()`` with ``sys.argv = argv``, stopped right after its
    arguments are parsed: a value the parser takes would start the benchmark, so taking it
    fails the test (AssertionError naming ``argv``)."""
    monkeypatch.setattr(sys, "argv", argv)

    def parse_only(self, *args, **kwargs):
        PARSE_ARGS(self, *args, **kwargs)
        raise AssertionError(f"took {' '.join(map(str, argv))}")

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", parse_only)
    try:
        with pytest.raises(SystemExit) as exit_:
            module.main()
    finally:
        monkeypatch.setattr(argparse.ArgumentParser, "parse_args", PARSE_ARGS)
    return exit_.value.code


# A count of 0 or below used to run nothing and write an empty report over the figure's JSON
# (--seeds 0), or end in a traceback from inside the run (ZeroDivisionError, Pool(-1)).
BAD_VALUES = [
    ("bench_multioptima", "--seeds", "0"),
    ("bench_multioptima", "--budgets", "-5"),
    ("bench_multioptima", "--dims", "0"),
    ("bench_multioptima", "--ks", "-1"),
    ("bench_multioptima", "--ks", "3"),  # make_landscape: k even (was "0/0 (1 err)")
    ("bench_noise", "--ks", "5"),
    ("bench_whole_run", "--ks", "1"),
    ("bench_multioptima", "--workers", "-1"),
    ("bench_niching", "--seeds", "0"),
    ("bench_niching", "--budgets", "0"),
    ("bench_niching", "--workers", "-2"),
    ("bench_noise", "--budget", "0"),
    ("bench_noise", "--noise", "-0.1"),
    ("bench_precision", "--seeds", "0"),
    ("bench_precision", "--dims", "0"),
    ("bench_viapoint_qd", "--budgets", "0"),
    ("bench_trials", "--seeds", "0"),
    ("bench_trials", "--budget", "0"),
    ("bench_whole_run", "--seeds", "0"),
    ("bench_whole_run", "--trials", "0"),
    ("bench_iteration", "--trials", "0"),
    ("bench_iteration", "--seeds", "0"),
    ("bench_sweep", "--batch", "0"),
    ("bench_sweep", "--trials", "0"),
    ("bench_dispatch", "--repeats", "0"),
    ("bench_dispatch", "--ratio", "-1"),
    ("bench_startup", "--repeats", "0"),
    ("bench_gibbs", "--sizes", "0"),
    ("bench_mcmc_kernel", "--sweeps", "0"),
    ("bench_memory", "--n", "0"),
    ("bench_rollout", "--steps", "0"),
    ("bench_launchers", "--workers", "0"),
    ("reproduce_figure1", "--runs", "0"),
    ("reproduce_viapoint", "--workers", "0"),
    ("reproduce_switch", "--grid-step", "0"),
]


@pytest.mark.parametrize(("script", "option", "value"), BAD_VALUES)
def test_a_bad_count_is_an_argparse_error_naming_the_option(
    script, option, value, monkeypatch, capsys
):
    module = importlib.import_module(script)
    assert exit_of_parsing(monkeypatch, module, [f"{script}.py", option, value]) == 2
    assert f"argument {option}: must be" in capsys.readouterr().err


@pytest.mark.parametrize("script", ["bench_multioptima", "bench_noise", "bench_whole_run"])
def test_optima_that_cannot_fit_on_a_line_are_an_argparse_error(script, monkeypatch, capsys):
    # --dims 1 --ks 8 drew centres 100 000 times, then ended in make_landscape's RuntimeError.
    module = importlib.import_module(script)
    monkeypatch.setattr(sys, "argv", [f"{script}.py", "--dims", "1", "2", "--ks", "2", "6"])
    with pytest.raises(SystemExit) as exit_:
        module.main()  # refused before any work
    assert exit_.value.code == 2
    assert "argument --ks: k = 6 centres 2.0 apart do not fit" in capsys.readouterr().err


def test_the_grid_check_refuses_on_a_line_only_what_cannot_be_drawn():
    from bench_multioptima import grid_error, make_landscape

    assert grid_error([1], [4]) is None and make_landscape(1, 4, seed=0).centres.shape == (4, 1)
    assert grid_error([2, 10], [8]) is None
    assert grid_error([1], [6]) is not None  # 5 gaps of 2.0 fill the width 10 exactly
    with pytest.raises(ValueError, match="D = 1 takes k ≤ 5"):
        make_landscape(1, 8, seed=0)


def test_an_unknown_startup_task_is_an_argparse_error(monkeypatch, capsys):
    # It timed the anchors, then failed in train.py's child with Hydra's error.
    import bench_startup

    argv = ["bench_startup.py", "--task", "nosuch"]
    assert exit_of_parsing(monkeypatch, bench_startup, argv) == 2
    assert "argument --task: invalid choice: 'nosuch'" in capsys.readouterr().err


def test_the_argument_types():
    import argtypes

    assert argtypes.positive_int("3") == 3
    assert argtypes.nonnegative_int("0") == 0
    assert argtypes.positive_even_int("4") == 4
    assert argtypes.positive_float("0.5") == 0.5
    assert argtypes.nonnegative_float("0") == 0.0
    for parse, text in [
        (argtypes.positive_int, "0"),
        (argtypes.positive_int, "x"),
        (argtypes.nonnegative_int, "-1"),
        (argtypes.positive_even_int, "3"),
        (argtypes.positive_even_int, "0"),
        (argtypes.positive_float, "0"),
        (argtypes.positive_float, "inf"),
        (argtypes.nonnegative_float, "nan"),
        (argtypes.nonnegative_float, "-0.1"),
    ]:
        with pytest.raises(argparse.ArgumentTypeError, match="must be"):
            parse(text)


def test_a_viapoint_budget_below_dipoles_first_batch_is_refused(tmp_path, capsys):
    # It ran every peer, then reported DIPOLE's cases as KeyError(20), a "nan ± nan" row.
    import bench_viapoint_qd

    report = tmp_path / "qd.json"
    with pytest.raises(SystemExit) as exit_:
        argv = ["--budgets", "20", "--methods", "DIPOLE", "--workers", "0", "--json", str(report)]
        bench_viapoint_qd.main(argv)
    assert exit_.value.code == 2
    assert "--budgets: 20 is below DIPOLE's first batch of 30 trials" in capsys.readouterr().err
    assert not report.exists()


def test_the_rollout_table_shows_no_nan_without_the_compiled_run():
    import bench_rollout

    assert bench_rollout.ratios(2.0, None, 1.0) == "     2.00x |             -"
    assert bench_rollout.ratios(2.0, 4.0, 1.0) == "     2.00x |         4.00x"


@pytest.mark.parametrize("script", ["bench_gibbs", "bench_rollout"])
def test_a_device_this_machine_lacks_is_an_argparse_error(script, monkeypatch, capsys):
    # "--device cuda" on a CPU-only torch was an AssertionError from the first tensor moved.
    import argtypes
    import torch

    assert argtypes.device("cpu") == "cpu"
    bad = "nosuch" if torch.cuda.is_available() else "cuda"
    module = importlib.import_module(script)
    assert exit_of_parsing(monkeypatch, module, [f"{script}.py", "--device", bad]) == 2
    assert "argument --device: " in capsys.readouterr().err


REPORTS = [
    "bench_multioptima",
    "bench_niching",
    "bench_noise",
    "bench_precision",
    "bench_viapoint_qd",
]


@pytest.mark.parametrize("script", REPORTS)
def test_a_json_path_that_cannot_be_written_is_refused_before_the_run(
    script, tmp_path, monkeypatch, capsys
):
    # A directory given as --json failed with IsADirectoryError after the whole run.
    module = importlib.import_module(script)
    (tmp_path / "file").write_text("")
    for bad, said in [(tmp_path, "is a directory"), (tmp_path / "file" / "x.json", "not a dir")]:
        assert exit_of_parsing(monkeypatch, module, [f"{script}.py", "--json", str(bad)]) == 2
        assert "argument --json: " in (err := capsys.readouterr().err) and said in err


def test_keep_others_without_a_report_says_so(tmp_path):
    # It was a FileNotFoundError traceback.
    import bench_multioptima

    missing = tmp_path / "missing.json"
    argv = ["--dims", "2", "--ks", "2", "--seeds", "1", "--budgets", "50", "--workers", "0"]
    with pytest.raises(SystemExit, match="--keep-others: no report to keep cases from at"):
        bench_multioptima.main([*argv, "--json", str(missing), "--keep-others"])
    assert not missing.exists()


@pytest.mark.parametrize(
    "script", ["reproduce_figure1", "reproduce_viapoint", "reproduce_switch", "aggregate"]
)
def test_an_out_that_is_a_file_is_an_argparse_error(script, tmp_path, monkeypatch, capsys):
    # It was a FileExistsError traceback from out.mkdir().
    module = importlib.import_module(script)
    (tmp_path / "file").write_text("")
    argv = [f"{script}.py", "--out", str(tmp_path / "file")]
    argv += [str(tmp_path)] if script == "aggregate" else []
    assert exit_of_parsing(monkeypatch, module, argv) == 2
    assert "argument --out: " in capsys.readouterr().err


class Parsed(Exception):
    """Raised with the namespace a script parsed, before it runs anything."""


@pytest.mark.parametrize(
    ("script", "argv", "expected"),
    [
        ("bench_precision", ["--peaks", "cone", "cone", "--dims", "2", "2"], {"dims": [2]}),
        ("bench_precision", ["--methods", "CMA-ES", "CMA-ES"], {"methods": ["CMA-ES"]}),
        ("bench_multioptima", ["--dims", "5", "2", "5", "--ks", "2", "2"], {"dims": [5, 2]}),
        ("bench_noise", ["--noise", "0.1", "0", "0.1"], {"noise": [0.1, 0.0]}),
        ("bench_whole_run", ["--methods", "PoWER", "PoWER"], {"methods": ["PoWER"]}),
        ("bench_trials", ["--functions", "7", "7"], {"functions": [7]}),
    ],
)
def test_a_list_option_takes_each_value_once(script, argv, expected, monkeypatch):
    # bench_precision.py --dims 2 2 ran every case twice and reported 1 seed as "(8/8)".
    module = importlib.import_module(script)
    monkeypatch.setattr(sys, "argv", [f"{script}.py", *argv])
    parse_args = argparse.ArgumentParser.parse_args

    def parse_only(self, *args, **kwargs):
        raise Parsed(parse_args(self, *args, **kwargs))

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", parse_only)
    with pytest.raises(Parsed) as parsed:
        module.main()
    namespace = vars(parsed.value.args[0])
    assert {key: namespace[key] for key in expected} == expected


def test_figure1_jobs_hold_seeds_and_keep_their_generator_seeds():
    import reproduce_figure1

    budgets = {"cartpole": (500, 30)}
    jobs = reproduce_figure1.make_jobs(["cartpole"], 2, 4, budgets, False)
    assert all(job[2] for job in jobs)  # --chunks 4 --runs 2: no job without seeds
    assert [(job[1], job[2], job[5]) for job in jobs if job[1] == "DIPOLE"] == [
        ("DIPOLE", [0], 1000),
        ("DIPOLE", [1], 1001),
    ]
    assert len(reproduce_figure1.make_jobs(["cartpole"], 50, 2, budgets, False)) == 8


def test_figure1_grid_step_above_the_budget_is_refused_before_the_runs(
    tmp_path, monkeypatch, capsys
):
    # It ran every run, then failed with an IndexError on an empty grid.
    import reproduce_figure1

    def no_pool(*args, **kwargs):
        raise AssertionError("the runs started")

    monkeypatch.setattr(reproduce_figure1.multiprocessing, "get_context", no_pool)
    argv = ["reproduce_figure1.py", "--runs", "1", "--tasks", "cartpole", "--grid-step", "501"]
    monkeypatch.setattr(sys, "argv", [*argv, "--out", str(tmp_path)])
    with pytest.raises(SystemExit) as exit_:
        reproduce_figure1.main()
    assert exit_.value.code == 2
    assert "--grid-step 501 leaves no grid point in 500 trials" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("script", "argv", "said"),
    [
        ("bench_gibbs", ["--sizes", "9", "--dims", "2"], "--sizes 9: N must be at least 10"),
        ("bench_gibbs", ["--sizes", "10", "--dims", "10"], "--sizes 10: N must be at least 11"),
        ("bench_mcmc_kernel", ["--points", "2", "--dim", "2"], "--points 2: N must exceed"),
        ("bench_mcmc_kernel", ["--dim", "1"], "argument --dim: must be an integer >= 2"),
        ("bench_memory", ["--n", "2", "--dim", "2"], "--n 2: N must exceed p = 2"),
        ("bench_dispatch", ["--dims", "1"], "argument --dims: must be an integer >= 2"),
    ],
)
def test_sizes_the_data_cannot_have_are_argparse_errors(script, argv, said, monkeypatch, capsys):
    # A covariance of N <= D points (or of one coordinate) failed deep in the prior's checks;
    # bench_dispatch's 8 optima do not fit 2 apart on a 1-D box.
    module = importlib.import_module(script)
    monkeypatch.setattr(sys, "argv", [f"{script}.py", *argv])
    with pytest.raises(SystemExit) as exit_:
        module.main()
    assert exit_.value.code == 2
    assert said in capsys.readouterr().err


def test_gibbs_prior_of_one_dimensional_data():
    # torch.cov of one coordinate is a scalar: "mean_covariance must have shape [1, 1]".
    import bench_gibbs
    import torch

    y, _ = bench_gibbs.make_data(20, 1)
    assert bench_gibbs.prior_for(y).mean_covariance.shape == torch.Size([1, 1])


def test_a_failed_launcher_sweep_shows_train_pys_error(monkeypatch):
    # check=True with captured output showed a CalledProcessError naming the command only.
    import subprocess

    import bench_launchers

    def failed(command, **kwargs):
        return subprocess.CompletedProcess(command, 1, "", "Error: hydra/launcher=joblib ...")

    monkeypatch.setattr(bench_launchers.subprocess, "run", failed)
    with pytest.raises(SystemExit, match=r"(?s)exit status 1.*hydra/launcher=joblib"):
        bench_launchers.launcher(1, 1)


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--methods", "IPOP-CMA-ES"], "drop --methods, --json"),
        (["--json", "/tmp/noise_gap.json"], "drop --methods, --json"),
        (["--noise", "0"], "give a --noise above 0"),
    ],
)
def test_the_best_gap_refuses_options_it_would_ignore(extra, message, capsys):
    # --best-gap runs DIPOLE alone on noisy returns and writes no JSON: --methods and --json
    # were ignored without a word, and noise 0 alone printed an empty table.
    import bench_noise

    with pytest.raises(SystemExit) as exit_:
        bench_noise.main(["--best-gap", *extra])
    assert exit_.value.code == 2
    assert message in capsys.readouterr().err
