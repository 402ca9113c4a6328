"""Figure 3 and the report: drawn from results alone, valid files, regenerated from results.json."""

from __future__ import annotations

import dataclasses
import json
import struct

import numpy as np
import pytest

from factorq_trainers import reports
from factorq_trainers.commands.paper import command as paper
from factorq_trainers.commands.paper import report
from factorq_trainers.commands.paper.config import PaperConfig
from factorq_trainers.runner import frame

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def unit_outcomes(config: PaperConfig, metrics: dict) -> list[dict]:
    """``paper.run_unit``'s results (``UNIT_RESULT``) of ``config``'s units from made-up metrics
    ``[seeds, runs, episodes]`` per cell."""
    outcomes = []
    for unit in paper.units(config):
        start = unit["first_seed"] - config.first_seed
        seeds = slice(start, start + unit["seeds"])
        batch = {  # regime-major, as a unit's batch is
            key: np.concatenate(
                [metrics[world, unit["algorithm"]][key][seeds] for world in config.regimes]
            )
            for key in metrics[config.regimes[0], unit["algorithm"]]
        }
        outcomes.append(paper.reduced(config, unit, "fast", batch))
    return outcomes


def synthetic_results(seeds=6, runs=2, episodes=40, **options):
    """Results of ``paper.summarise`` (in the runner's envelope) on made-up metrics shaped like the
    paper's curves."""
    config = PaperConfig(seeds=seeds, runs=runs, episodes=episodes, **options)
    generator = np.random.default_rng(1)
    decay = np.exp(-np.arange(episodes) / 10.0)  # [E]
    metrics = {}
    for world, algorithm in config.cells:
        scale = 1.0 if algorithm == "q-learning" else 0.02
        shape = (seeds, runs, episodes)
        collisions = generator.poisson(scale * (40 * decay + 2), shape)
        metrics[world, algorithm] = {
            "steps": generator.poisson(300 * decay + 30, shape) + collisions,
            "collisions": collisions,
            "greedy_collisions": generator.binomial(collisions, 0.5 if scale < 1 else 0.98),
            "task_return": -generator.poisson(300 * decay + 30, shape).astype(np.float32),
        }
    summary = paper.summarise(config, unit_outcomes(config, metrics))
    results = frame.envelope(paper, config, summary, wall_s=1.5, units=2)
    results["timing"] = {
        "wall_s": 1.5,
        "where": "in-process",
        "units": 2,
        "units_resumed": 0,
        "backend": "fast",
        "threads": 2,
        "env_steps": 123,
    }
    return frame.through_json(results)  # as results.json gives it back


@pytest.fixture(scope="module")
def results():
    return synthetic_results()


def png_size(data: bytes) -> tuple[int, int]:
    assert data[:8] == PNG_SIGNATURE
    assert data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


def test_figure3_is_a_valid_png_of_paper_size_under_a_megabyte(results, tmp_path):
    path = tmp_path / "figure3.png"
    report.figure3(results, path)
    data = path.read_bytes()
    width, height = png_size(data)
    assert width >= 1200 and height >= 800  # 3 worlds x 2 rows at 150 dpi
    assert 20_000 < len(data) < 1_000_000  # something was drawn, and it is not bloated
    assert data.endswith(b"IEND\xaeB`\x82")


def test_figure3_draws_a_single_world_and_a_single_seed(tmp_path):
    single = synthetic_results(seeds=1, regimes=("dynamic",), methods=("factor-q",))
    path = tmp_path / "figure3.png"
    report.figure3(single, path)
    width, height = png_size(path.read_bytes())
    assert 0 < width < 1200 and height > 0


def test_report_has_the_claims_table_with_a_verdict_per_claim(results):
    text = report.markdown(results)
    assert "| claim | statement | measured [95% CI] | threshold | result |" in text
    for name, claim in results["claims"].items():
        row = next(line for line in text.splitlines() if line.startswith(f"| {name} |"))
        assert claim["statement"] in row and claim["threshold"] in row
        assert row.endswith({True: "| pass |", False: "| FAIL |"}[claim["pass"]])


def test_report_has_cells_config_software_and_wall_time(results):
    text = report.markdown(results)
    assert "| static | Q-learning |" in text and "| dynamic | Factor-Q |" in text
    assert "| `--seeds` | `6` |" in text and "| `--g-min` | `0.01` |" in text
    assert "| torch |" in text and "| matplotlib |" in text and "| platform |" in text
    assert (
        "Wall time 1.5 s on the fast backend with 2 thread(s): 123 environment steps, 82 " in text
    )
    assert "figure3.png" in text


def test_report_marks_claims_that_were_not_evaluated(tmp_path):
    text = report.markdown(synthetic_results(regimes=("static",)))
    c1 = next(line for line in text.splitlines() if line.startswith("| C1 |"))
    assert "not evaluated" in c1 and c1.endswith("| n/a |")
    c2 = next(line for line in text.splitlines() if line.startswith("| C2 |"))
    assert "n/a" not in c2


def test_regenerate_rebuilds_figure_and_report_from_results_json_alone(results, tmp_path):
    paths = frame.write_outputs(paper, results, tmp_path)
    assert sorted(paths) == ["figure", "json", "report"]
    original = paths["report"].read_text()
    paths["figure"].unlink()
    paths["report"].unlink()
    regenerated = reports.regenerate(tmp_path)
    assert regenerated["report"].read_text() == original
    png_size(regenerated["figure"].read_bytes())
    # results.json is strict JSON (no NaN/Infinity) and round-trips the claims exactly
    loaded = json.loads(paths["json"].read_text(), parse_constant=_reject)
    assert loaded["claims"] == json.loads(json.dumps(results["claims"]))


def _reject(constant):
    raise ValueError(f"non-standard JSON constant {constant}")


def test_regenerate_without_results_json_says_what_is_missing(tmp_path):
    with pytest.raises(FileNotFoundError, match="holds no results file .*results.json"):
        reports.regenerate(tmp_path)
    (tmp_path / "results.json").write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        reports.regenerate(tmp_path)
    (tmp_path / "results.json").write_text('{"config": {}, "schema_version": 1}')
    with pytest.raises(ValueError, match="results.json: cells, claims missing in the file"):
        reports.regenerate(tmp_path)


def test_factorq_report_redraws_a_sweep_output_folder(tmp_path, capsys):
    """``factorq report DIR`` on ``factorq sweep``'s ``--out``: ``sweep.md`` and the figure per
    axis come back from ``sweep.json`` alone, the same Markdown, the JSON untouched (issue 38)."""
    from factorq_trainers import cli

    spec_file = tmp_path / "sweep.toml"
    spec_file.write_text(
        "seeds = 2\n[base]\nshard_seeds = 1\nruns = 1\nepisodes = 3\nsize = 4\nobstacles = 2\n"
        "[grid]\neta = [0.05, 0.1]\n"
    )
    out = tmp_path / "sweep"
    assert cli.main(["sweep", str(spec_file), "--out", str(out)]) == 0
    markdown = (out / "sweep.md").read_text()
    stored = (out / "sweep.json").read_bytes()
    (out / "sweep.md").unlink()
    (out / "sweep-eta.png").unlink()
    capsys.readouterr()
    assert cli.main(["report", str(out)]) == 0
    assert (out / "sweep.md").read_text() == markdown
    assert (out / "sweep-eta.png").stat().st_size > 0
    assert (out / "sweep.json").read_bytes() == stored
    printed = capsys.readouterr().out.split()
    assert printed == [str(out / "sweep.md"), str(out / "sweep-eta.png")]
    empty = tmp_path / "empty"
    empty.mkdir()
    assert cli.main(["report", str(empty)]) == 2
    assert "sweep.json" in capsys.readouterr().err  # the files looked for name the sweep's


def test_reports_say_too_little_data_instead_of_a_ratio_of_zeros():
    """At a tiny budget the counts are 0: a ratio with a zero side (0.00x, or unbounded) says
    nothing, so the targets say "too little data" with both counts (issue 38)."""
    from factorq_trainers.commands.gym import report as gym
    from factorq_trainers.commands.minigrid import report as minigrid
    from factorq_trainers.commands.risk import report as risk_report

    def gym_methods(**crashes):
        return {
            method: {"crashes_per_1000": {"mean": value}, "greedy_return": {"mean": 0.0}}
            for method, value in crashes.items()
        }

    lines = gym.targets({"methods": gym_methods(dqn=0.0, **{"factor-dqn": 2.0})})
    assert lines[0].startswith("- Oracle Factor-Q: too little data to compare training crashes")
    lines = gym.targets(
        {"methods": gym_methods(dqn=0.0, **{"factor-dqn": 0.0, "factor-dqn-learned": 0.0})}
    )
    assert all("too little data" in line and "0.00x" not in line for line in lines), lines
    lines = gym.targets({"methods": gym_methods(dqn=30.0, **{"factor-dqn": 3.0})})
    assert "10.00x fewer training crashes" in lines[0] and "(target >= 5x: met)" in lines[0]

    summary = {"collisions": {"mean": 0.0}, "success_rate": {"mean": 0.0}}
    per_method = {"dqn": {"summary": summary}, "factor-q": {"summary": summary}}
    (line,) = minigrid._targets({"methods": {}}, per_method)
    assert "too little data to compare training collisions" in line and "x below" not in line

    from factorq_trainers.commands.risk import command as experiment

    config = experiment.RiskConfig(worlds=("grid",), methods=("dqn", "dqn+risk"), seeds=1)
    unit = {"world": "grid", "seed": 0, "greedy_collisions": 0, "final_return": -10.0}
    unit |= {"greedy_success": 1.0, "steps_to_threshold": None, "wall_s": 1.0}
    results = experiment.summarise(
        config,
        [
            {**unit, "method": "dqn", "train_collisions": 0},
            {**unit, "method": "dqn+risk", "train_collisions": 0},
        ],
    )
    (ratio,) = results["ratios"]
    assert ratio["collision_ratio"] is None  # 0 / 0: no ratio (it was 0 / 1e-9 = 0.0)
    results["config"] = dataclasses.asdict(config)  # the runner's envelope adds it
    assert "| grid | dqn / dqn+risk | too little data |" in risk_report.markdown(results)
