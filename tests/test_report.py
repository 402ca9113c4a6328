"""Figure 3 and the report: drawn from results alone, valid files, regenerated from results.json."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from factorq_trainers.experiments import paper
from factorq_trainers.experiments.paper import PaperConfig
from factorq_trainers.reports import report

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def synthetic_results(seeds=6, runs=2, episodes=40, **options):
    """Results of ``paper.summarise`` on made-up metrics shaped like the paper's curves."""
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
    results = paper.summarise(config, metrics)
    results["timing"] = {
        "wall_s": 1.5,
        "backend": "fast",
        "threads": 2,
        "env_steps": 123,
        "env_steps_per_s": 82,
        "finished_utc": "2026-01-01T00:00:00Z",
    }
    return results


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
    single = synthetic_results(seeds=1, worlds=("dynamic",), algorithms=("factor-q",))
    path = tmp_path / "figure3.png"
    report.figure3(single, path)
    width, height = png_size(path.read_bytes())
    assert 0 < width < 1200 and height > 0


def test_report_has_the_claims_table_with_a_verdict_per_claim(results):
    text = report.report_markdown(results)
    assert "| claim | statement | measured [95% CI] | threshold | result |" in text
    for name, claim in results["claims"].items():
        row = next(line for line in text.splitlines() if line.startswith(f"| {name} |"))
        assert claim["statement"] in row and claim["threshold"] in row
        assert row.endswith({True: "| pass |", False: "| FAIL |"}[claim["pass"]])


def test_report_has_cells_config_software_and_wall_time(results):
    text = report.report_markdown(results)
    assert "| static | Q-learning |" in text and "| dynamic | Factor-Q |" in text
    assert "| `--seeds` | `6` |" in text and "| `--g-min` | `0.01` |" in text
    assert "| torch |" in text and "| matplotlib |" in text and "| platform |" in text
    assert "Wall time 1.5 s" in text
    assert "figure3.png" in text


def test_report_marks_claims_that_were_not_evaluated(tmp_path):
    text = report.report_markdown(synthetic_results(worlds=("static",)))
    c1 = next(line for line in text.splitlines() if line.startswith("| C1 |"))
    assert "not evaluated" in c1 and c1.endswith("| n/a |")
    c2 = next(line for line in text.splitlines() if line.startswith("| C2 |"))
    assert "n/a" not in c2


def test_regenerate_rebuilds_figure_and_report_from_results_json_alone(results, tmp_path):
    paths = report.write_results(results, tmp_path)
    original = paths["report"].read_text()
    paths["figure"].unlink()
    paths["report"].unlink()
    regenerated = report.regenerate(tmp_path)
    assert regenerated["report"].read_text() == original
    png_size(regenerated["figure"].read_bytes())
    # results.json is strict JSON (no NaN/Infinity) and round-trips the claims exactly
    loaded = json.loads(paths["results"].read_text(), parse_constant=_reject)
    assert loaded["claims"] == json.loads(json.dumps(results["claims"]))


def _reject(constant):
    raise ValueError(f"non-standard JSON constant {constant}")


def test_regenerate_without_results_json_says_what_is_missing(tmp_path):
    with pytest.raises(FileNotFoundError, match="results.json does not exist"):
        report.regenerate(tmp_path)
    (tmp_path / "results.json").write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        report.regenerate(tmp_path)
    (tmp_path / "results.json").write_text('{"config": {}}')
    with pytest.raises(ValueError, match="cells, claims missing"):
        report.regenerate(tmp_path)
