"""Every code block of the README and of the documentation (docs/, the pages of mkdocs.yml's
nav) runs, in the order a reader meets it.

Each page runs in one fresh temporary directory as the working directory: its Python blocks in
one namespace, its bash blocks in a subprocess (``python train.py`` and ``python
benchmarks/...`` resolved to this repository's scripts, the environment's ``bin/`` first on
``PATH``). A block whose first line is ``# file: <path>`` (``<!-- file: <path> -->`` in XML)
is written to that path instead, for the blocks after it. A block that cannot run here (it
installs packages, needs a GPU, a cluster or a server, or is a benchmark) carries
``<!-- no-test: <reason> -->`` right before it in the Markdown source; any other block must
run. A Python block that ends with ``# Prints:`` and comment lines must print exactly those.

Also checked here: the pages' tables show the numbers of ``docs/figures/*.json``, every
benchmark command names a script and options it has, every test a page names exists, and the
layout lists folders that exist.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import subprocess
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch
import yaml

from tasks.multimodal import MultimodalTask

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
FIGURES = DOCS / "figures"

FENCE = re.compile(r"^```([\w+-]*)[^\n]*\n(.*?)^```[ \t]*$", re.M | re.S)
NO_TEST = re.compile(r"<!--\s*no-test:\s*(?P<reason>[^>]*?)\s*-->\s*$")
MARKER = re.compile(r"<!--\s*(?P<name>[\w-]+)\s*-->\s*$")
FILE_LINE = re.compile(r"^(?:#|<!--)\s*file:\s*(?P<path>\S+?)\s*(?:-->)?$")


def nav_pages() -> list[Path]:
    """The documentation pages in the order of mkdocs.yml's nav."""
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text())

    def walk(entries) -> list[str]:
        pages = []
        for entry in entries:
            value = next(iter(entry.values())) if isinstance(entry, dict) else entry
            pages += walk(value) if isinstance(value, list) else [value]
        return pages

    return [DOCS / page for page in walk(config["nav"])]


PAGES = [ROOT / "README.md", *nav_pages()]


@dataclass
class Block:
    page: Path
    line: int  # 1-based line of the opening fence
    language: str
    code: str
    skip: str | None  # the no-test reason
    marker: str | None  # the <!-- name --> right before it, if any

    @property
    def where(self) -> str:
        return f"{self.page.relative_to(ROOT)}:{self.line}"


def blocks(page: Path) -> list[Block]:
    """The page's fenced code blocks, in order, with the marker right before each."""
    text = page.read_text()
    indented = re.search(r"^[ \t]+```", text, re.M)
    assert not indented, f"{page}: an indented fence (not run here): move it to the margin"
    found, previous_end = [], 0
    for match in FENCE.finditer(text):
        before = text[previous_end : match.start()].rstrip()
        skip = NO_TEST.search(before)
        marker = MARKER.search(before)
        found.append(
            Block(
                page=page,
                line=text.count("\n", 0, match.start()) + 1,
                language=match.group(1),
                code=match.group(2),
                skip=skip.group("reason") if skip else None,
                marker=marker.group("name") if marker else None,
            )
        )
        previous_end = match.end()
    return found


def block(page: Path, marker: str) -> Block:
    """The block of ``page`` marked ``<!-- marker -->``."""
    marked = [b for b in blocks(page) if b.marker == marker]
    assert len(marked) == 1, f"{page.relative_to(ROOT)} lost its {marker} block"
    return marked[0]


def bash_environment() -> dict[str, str]:
    bin_dir = str(Path(sys.executable).parent)
    return dict(os.environ, PATH=bin_dir + os.pathsep + os.environ.get("PATH", ""))


def resolve_scripts(command: str) -> str:
    """``python train.py`` and ``python benchmarks/x.py`` as this repository's scripts."""
    command = re.sub(r"\bpython (train\.py)\b", rf"{sys.executable} {ROOT}/\1", command)
    return re.sub(r"\bpython (benchmarks/)", rf"{sys.executable} {ROOT}/\1", command)


def run_bash(code: str, where: str, cwd: Path) -> str:
    result = subprocess.run(
        ["bash", "-e", "-o", "pipefail", "-c", resolve_scripts(code)],
        cwd=cwd,
        env=bash_environment(),
        capture_output=True,
        text=True,
        timeout=600,
    )
    if result.returncode != 0:
        raise AssertionError(
            f"{where}: the bash block failed (status {result.returncode}):\n{code}\n"
            f"--- stdout\n{result.stdout[-3000:]}\n--- stderr\n{result.stderr[-5000:]}"
        )
    return result.stdout


def run_python(code: str, where: str, namespace: dict) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(code, where, "exec"), namespace)
    return out.getvalue()


def expected_output(code: str) -> list[str] | None:
    """The lines after a final ``# Prints:`` comment, if the block ends with one."""
    match = re.search(r"^# Prints:\n((?:#.*\n?)+)\Z", code, re.M)
    if not match:
        return None
    return [line[2:] if line.startswith("# ") else line[1:] for line in match.group(1).splitlines()]


def write_file(block: Block, cwd: Path) -> bool:
    first, _, rest = block.code.partition("\n")
    match = FILE_LINE.match(first.strip())
    if not match:
        return False
    path = cwd / match.group("path")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(rest)
    return True


# What a marked block's output must show, beyond running.
def _check_reuse(out: str) -> None:
    # What it prints is true: the place it names returns (nearly) the return it conditioned on.
    match = re.search(r"policies that return (\S+) live around \[([^\]]*)\]", out)
    said = float(match.group(1))
    where = torch.tensor([[float(x) for x in match.group(2).split(",")]])
    returns = float(MultimodalTask().evaluate(where))
    assert said >= 0.9 and returns == pytest.approx(said, abs=0.05), (said, returns)


def _check_switch(out: str) -> None:
    # The comment in the block says what it prints: the return of the policy it switches to.
    page = (ROOT / "docs" / "guide" / "switching.md").read_text()
    said = float(re.search(r"return \{ret:\.3f\}\"\)\s*# (\S+)", page).group(1))
    switched = float(re.search(r"switched to a policy with return (\S+)", out).group(1))
    assert switched == pytest.approx(said, abs=5e-4) and switched >= 0.9


CHECKS = {"reuse-example": _check_reuse, "switch-example": _check_switch}


def run_page(page: Path, cwd: Path) -> dict[int, str]:
    """Runs every block of ``page`` in ``cwd``; returns each run block's output by line."""
    namespace: dict = {"__name__": "__docs__"}
    outputs = {}
    for b in blocks(page):
        if b.skip is not None:
            assert b.skip, f"{b.where}: a no-test marker must say why"
            continue
        if write_file(b, cwd):
            continue
        if b.language == "python":
            out = run_python(b.code, b.where, namespace)
            expected = expected_output(b.code)
            if expected is not None:
                assert out.splitlines() == expected, f"{b.where} printed:\n{out}"
        elif b.language in ("bash", "sh", "console"):
            out = run_bash(b.code, b.where, cwd)
        else:
            raise AssertionError(
                f"{b.where}: a {b.language or 'plain'} block that neither runs nor is a file "
                "(# file: <path>): mark it <!-- no-test: <reason> -->"
            )
        if b.marker in CHECKS:
            CHECKS[b.marker](out)
        outputs[b.line] = out
    return outputs


# Pages whose blocks run Hydra launcher plugins (the sweep extra), as tests/test_launchers.py.
NEEDS_PLUGINS = {"docs/guide/sweeps.md": ("hydra_joblib_launcher", "hydra_submitit_launcher")}


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_code_block_of_the_page_runs(page, tmp_path, monkeypatch):
    from test_launchers import plugin_installed

    missing = [
        m for m in NEEDS_PLUGINS.get(str(page.relative_to(ROOT)), ()) if not plugin_installed(m)
    ]
    if missing:
        pytest.skip(f"{', '.join(missing)} not installed (pip install -e '.[sweep]')")
    monkeypatch.chdir(tmp_path)
    run_page(page, tmp_path)


def test_every_page_is_in_the_nav():
    pages = {p.relative_to(DOCS) for p in DOCS.rglob("*.md")}
    in_nav = {p.relative_to(DOCS) for p in nav_pages()}
    assert pages == in_nav, f"pages not in mkdocs.yml's nav: {sorted(map(str, pages - in_nav))}"


def test_the_marked_blocks_say_why_and_are_the_fewer():
    marked = [b for page in PAGES for b in blocks(page) if b.skip is not None]
    runs = [b for page in PAGES for b in blocks(page) if b.skip is None]
    assert all(len(b.skip) > 10 for b in marked), [b.where for b in marked if len(b.skip) <= 10]
    assert len(runs) > len(marked)


# ------------------------------------------------------------------ commands the tests do not run
BENCHMARK = re.compile(r"python benchmarks/(?P<script>\w+)\.py(?P<args>[^`|\n#]*)")


def test_every_benchmark_command_names_a_script_and_options_it_has():
    for page in PAGES:
        for match in BENCHMARK.finditer(page.read_text()):
            script = ROOT / "benchmarks" / f"{match.group('script')}.py"
            assert script.is_file(), f"{page.name}: {match.group(0)}: no such script"
            source = script.read_text()
            for option in re.findall(r"(?<!\S)--[\w-]+", match.group("args")):
                assert f'"{option}"' in source, f"{page.name}: {script.name} has no {option}"


def test_every_test_a_page_names_exists():
    sources = "\n".join(p.read_text() for p in (ROOT / "tests").glob("test_*.py"))
    files = {p.name for p in (ROOT / "tests").glob("test_*.py")}
    for page in PAGES:
        text = page.read_text()
        for name in re.findall(r"`(test_\w+)`", text):
            assert f"def {name}(" in sources, f"{page.name} names {name}, which is no test"
        for name in re.findall(r"tests/(test_\w+\.py)", text):
            assert name in files, f"{page.name} names tests/{name}, which does not exist"


def test_the_layout_lists_folders_and_files_that_exist():
    listing = next(b for b in blocks(DOCS / "layout.md") if b.language == "text")
    for line in listing.code.splitlines():
        path = line.split()[0]
        assert (ROOT / path).exists(), f"docs/layout.md lists {path}, which does not exist"
        if path.endswith("/"):  # the files it names in that folder
            for name in re.findall(r"\b[\w/]+\.(?:py|yaml)\b", line):
                matches = list((ROOT / path).glob(name)) + list((ROOT / path).glob(f"*/{name}"))
                assert matches, f"docs/layout.md lists {path}{name}, which does not exist"


# ------------------------------------------------------------------ the numbers of docs/figures
def _mean_std(pair, digits: int, scale: float = 1.0) -> str:
    mean, std = (float(x) * scale for x in (pair.values() if isinstance(pair, dict) else pair))
    return f"{mean:.{digits}f} ± {std:.{digits}f}"


def figure1_rows() -> list[str]:
    """Figure 1's table, from docs/figures/figure1.json."""
    data = json.loads((FIGURES / "figure1.json").read_text())
    tasks = {"cartpole": "cart-pole", "mountain_car": "mountain car"}
    algorithms = {
        "DIPOLE": "DIPOLE (default)",
        "DIPOLE (paper)": "DIPOLE (paper)",
        "PoWER": "PoWER, fixed Σ_start",
        "PoWER, decaying exploration": "PoWER, exploration × 0.98 per iteration",
    }
    return [
        f"| {label} | {name} | {_mean_std(data[task][algo]['final_best'], 1)} | "
        f"{_mean_std(data[task][algo]['final_average'], 1)} |"
        for task, label in tasks.items()
        for algo, name in algorithms.items()
    ]


def viapoint_rows() -> list[str]:
    """Figures 2-3's table, from docs/figures/viapoint.json."""
    data = json.loads((FIGURES / "viapoint.json").read_text())
    algos = [data[a] for a in ("DIPOLE", "DIPOLE (paper)", "PoWER")]
    total = data["num_routes_in_layout"]

    def row(label, cell):
        return f"| {label} | " + " | ".join(cell(a) for a in algos) + " |"

    return [
        row("final best sample return (mean ± std)", lambda a: _mean_std(a["final_best"], 3)),
        row("final average sample return", lambda a: _mean_std(a["final_average"], 3)),
        row(
            "return of the best final policy mean (no exploration noise)",
            lambda a: _mean_std(a["final_best_policy_mean_reward"], 3),
        ),
        row(
            f"distinct routes per run (policy mean return ≥ {data['threshold']})",
            lambda a: _mean_std(a["routes_per_run"], 1),
        ),
        row(
            f"routes of the layout found over the {data['runs']} runs",
            lambda a: f"{len(a['routes_covered'])} / {total}",
        ),
        row(
            "end-point error of the final policy means",
            lambda a: _mean_std(a["end_point_error_m"], 2, scale=100) + " cm",
        ),
    ]


def switch_rows() -> list[str]:
    """The route switch's table, from docs/figures/switch.json."""
    data = json.loads((FIGURES / "switch.json").read_text())
    dipole, power, scratch = data["DIPOLE"], data["PoWER"], data["DIPOLE scratch"]
    runs, after = data["runs"], data["trials_after_block"]
    k = data["dipole_num_policies_reevaluated"]

    def fraction(text: str) -> str:
        return text.replace("/", " / ")

    def within_k(algo, policies: list[int]) -> int:
        reached = algo["trials_to_threshold"]
        return sum(t is not None and t <= n for t, n in zip(reached, policies, strict=True))

    def trials(algo, key: str, dipole_like: bool) -> str:
        mean, std, median = algo[f"{key}_mean_std_median"]
        if dipole_like:
            return f"{mean:.1f} ± {std:.1f}, median {median:g} (all {runs})"
        reached = fraction(algo[f"{key}_reached"])
        limit = f" within {after}" if not reached.startswith(f"{runs} ") else ""
        return f"{round(mean)} ± {round(std)}, median {round(median)} ({reached}{limit})"

    def returns(algo) -> str:
        return f"{algo['final_executed'][0]:.3f} / {algo['final_best_policy_mean'][0]:.3f}"

    # The claim: every run that knew ≥ 2 routes before the block is back within its K trials.
    known = data["dipole_runs_with_two_or_more_routes"]
    assert fraction(data["dipole_switch_success"]) == f"{known} / {known}"
    assert within_k(dipole, k) >= known
    return [
        f"| runs with ≥ 2 routes before the block | "
        f"{data['dipole_runs_with_two_or_more_routes']} / {runs} | — (one policy) | — |",
        f"| back at return ≥ {data['threshold']} within K trials (no relearning) | "
        f"{within_k(dipole, k)} / {runs} (K = {min(k)}–{max(k)}) | "
        f"{within_k(power, [1] * runs)} / {runs} | — |",
        f"| trials to {data['threshold']}, executed policy (`best()`) | "
        + " | ".join(
            [
                trials(dipole, "trials_to_threshold", True),
                trials(power, "trials_to_threshold", False),
                trials(scratch, "trials_to_threshold", False),
            ]
        )
        + " |",
        f"| trials to {data['threshold']}, best policy mean (evaluation rollouts) | "
        + " | ".join(
            [
                trials(dipole, "trials_to_threshold_policy_mean", True),
                trials(power, "trials_to_threshold_policy_mean", False),
                trials(scratch, "trials_to_threshold_policy_mean", False),
            ]
        )
        + " |",
        f"| return after {after} trials: executed / best policy mean | "
        f"{returns(dipole)} | {returns(power)} | {returns(scratch)} |",
    ]


def multioptima_rows() -> list[str]:
    """The multi-optima table, from docs/figures/multioptima.json."""
    data = json.loads((FIGURES / "multioptima.json").read_text())
    names = {
        "DIPOLE": "DIPOLE (default)",
        "DIPOLE (paper)": "DIPOLE (paper)",
        "DIPOLE (coverage)": "DIPOLE (coverage: `algo=dipole_coverage`)",
        "PoWER": "PoWER (decaying exploration)",
        "IPOP-CMA-ES": "IPOP-CMA-ES (`cma`)",
        "NMMSO": "NMMSO (`pynmmso`)",
        "random search": "random search",
    }
    config = data["config"]
    rows = []
    for method, name in names.items():
        summary = data["summary"][method]
        cells = [
            str(summary["found"][f"D={d}"][str(b)]["found"])
            for d in config["dims"]
            for b in config["budgets"]
        ]
        seconds = summary["seconds"]
        cells.append(f"{seconds:.1f}" if seconds < 1 else f"{seconds:.0f}")
        rows.append(f"| {name} | " + " | ".join(cells) + " |")
    return rows


def niching_rows(report: str = "niching.json", accuracy: str = "0.001") -> list[str]:
    """The niching table at one accuracy, from ``report`` in docs/figures."""
    data = json.loads((FIGURES / report).read_text())
    methods = data["config"]["methods"]
    budgets = [str(b) for b in data["config"]["budgets"]]
    optima = {case["name"]: case["optima"] for case in data["cases"]}
    seeds = data["config"]["seeds"]
    found = {m: data["summary"][m]["found"][accuracy] for m in methods}
    rows = []
    for function in found[methods[0]][budgets[0]]:
        label = re.sub(r"(\d)D$", r"\1-D", function) + f" ({optima[function] * seeds})"
        cells = [str(found[m][b][function]) for b in budgets for m in methods]
        rows.append(f"| {label} | " + " | ".join(cells) + " |")
    totals = [str(sum(found[m][b].values())) for b in budgets for m in methods]
    rows.append("| all | " + " | ".join(totals) + " |")
    return rows


def precision_rows() -> list[str]:
    """The narrow-peak table, from docs/figures/precision.json."""
    data = json.loads((FIGURES / "precision.json").read_text())
    accuracies = data["config"]["accuracies"]
    rows = []
    for row in data["summary"]:
        cells = []
        for a in accuracies:
            median, reached = row[f"trials_to_{a:g}"], row[f"reached_{a:g}"]
            cells.append("—" if median is None else f"{median} ({reached}/{row['seeds']})")
        rows.append(
            f"| {row['peak']} | {row['dim']} | {row['method']} | "
            + " | ".join(cells)
            + f" | {row['final_gap']:.1e} | {row['cpu_seconds']:.1f} |"
        )
    return rows


def viapoint_qd_rows() -> list[str]:
    """The viapoint coverage table, from docs/figures/viapoint_qd.json."""
    data = json.loads((FIGURES / "viapoint_qd.json").read_text())
    rows = []
    for method, summary in data["summary"].items():
        cells = [
            _mean_std(summary[str(b)]["routes_per_run"][str(level)], 1)
            for b in data["config"]["budgets"]
            for level in data["config"]["levels"]
        ]
        cells += [str(len(summary[str(b)]["routes_over_runs"])) for b in data["config"]["budgets"]]
        rows.append(f"| {method} | " + " | ".join(cells) + " |")
    return rows


def noise_rows() -> list[str]:
    """The noisy-returns table, from docs/figures/noise.json: per method, the optima found
    at each noise level, one cell a dimension."""
    data = json.loads((FIGURES / "noise.json").read_text())
    config, summary = data["config"], data["summary"]
    names = {
        "DIPOLE": "DIPOLE (`best_evaluations=1`, the default)",
        "DIPOLE (best ×2)": "DIPOLE, `best_evaluations=2`",
        "DIPOLE (best ×4)": "DIPOLE, `best_evaluations=4`",
        "DIPOLE (mean of 4)": "DIPOLE, every θ evaluated 4 times and the mean told",
        "IPOP-CMA-ES": "IPOP-CMA-ES",
        "UH-IPOP-CMA-ES": "IPOP-CMA-ES with pycma's noise handling (UH-CMA-ES)",
        "NMMSO": "NMMSO",
    }
    return [
        f"| {name} | "
        + " | ".join(
            " / ".join(str(summary[f"D={d} {method} noise={s}"]) for s in config["noise"])
            for d in config["dims"]
        )
        + " |"
        for method, name in names.items()
    ]


def shown(page: Path) -> set[str]:
    """The table rows of a page, bold marks removed."""
    return {
        line.replace("**", "").strip()
        for line in page.read_text().splitlines()
        if line.startswith("|")
    }


@pytest.mark.parametrize(
    "page, rows",
    [
        ("benchmarks/paper.md", figure1_rows),
        ("benchmarks/paper.md", viapoint_rows),
        ("benchmarks/switch.md", switch_rows),
        ("benchmarks/multioptima.md", multioptima_rows),
        ("benchmarks/niching.md", niching_rows),
        ("benchmarks/niching.md", lambda: niching_rows("niching_more.json")),
        ("benchmarks/precision.md", precision_rows),
        ("benchmarks/precision.md", viapoint_qd_rows),
        ("reliability.md", noise_rows),
    ],
)
def test_the_benchmark_pages_show_the_numbers_of_the_json(page, rows):
    missing = [row for row in rows() if row not in shown(DOCS / page)]
    assert not missing, f"docs/{page} lacks these rows of its JSON:\n" + "\n".join(missing)


def test_expected_output_reads_the_prints_comment():
    code = textwrap.dedent(
        """\
        print("a")
        # Prints:
        # a
        """
    )
    assert expected_output(code) == ["a"]
    assert expected_output("print(1)  # 1\n") is None
