"""Figure and report titles name the body and the world when they are not the paper's (issue 11)."""

from __future__ import annotations

import pytest
from matplotlib.figure import Figure
from test_report import synthetic_results  # pytest puts tests/ on sys.path

from factorq_trainers.commands.compare import report as compare_report
from factorq_trainers.commands.paper import report
from factorq_trainers.runner.results import body_label


@pytest.fixture
def titles(monkeypatch):
    """The suptitles of the figures drawn while the fixture is active."""
    seen: list[str] = []
    original = Figure.suptitle

    def record(self, text, *args, **kwargs):
        seen.append(text)
        return original(self, text, *args, **kwargs)

    monkeypatch.setattr(Figure, "suptitle", record)
    return seen


@pytest.mark.parametrize(
    ("options", "label"),
    [
        ({}, None),
        ({"body": "heading"}, "heading body"),
        (
            {"sensors": "ring", "distractors": 4, "sensor_permutation": 3},
            "ring sensors, 4 distractors, permuted sensors (seed 3)",
        ),
        ({"sensor_noise": 0.05, "actuator_noise": 0.1}, "sensor noise 0.05, actuator noise 0.1"),
    ],
)
def test_body_label_names_what_differs_from_the_paper(options, label):
    results = {"config": {"body": "translate", "sensors": "cross", **options}}
    assert body_label(results) == label


def test_body_label_of_a_config_without_body_options_is_the_paper_and_of_another_world():
    assert body_label({"config": {"size": 10}}) is None
    world = {"name": "Corridor", "config": {"length": 12, "density": 0.4}}
    assert body_label({"config": {}, "world": world}) == "Corridor world (length 12, density 0.4)"


def test_paper_figure_and_report_name_a_non_default_body(titles, tmp_path):
    default = synthetic_results(seeds=2, episodes=6)
    report.figure3(default, tmp_path / "a.png")
    assert titles[-1].splitlines()[0] == "Q-learning vs Factor-Q, 10\u00d710 grid with 10 obstacles"
    heading = report.markdown(default).splitlines()[0]
    assert heading == "# Factor-Q vs Q-learning: the paper's experiment"

    ring = synthetic_results(seeds=2, episodes=6, sensors="ring", distractors=4)
    report.figure3(ring, tmp_path / "b.png")
    assert titles[-1].splitlines()[0] == (
        "Q-learning vs Factor-Q, 10\u00d710 grid with 10 obstacles, ring sensors, 4 distractors"
    )
    assert report.markdown(ring).splitlines()[0] == (
        "# Factor-Q vs Q-learning: the paper's experiment (ring sensors, 4 distractors)"
    )

    corridor = dict(default, world={"name": "Corridor", "config": {"length": 12}})
    report.figure3(corridor, tmp_path / "c.png")
    assert titles[-1].splitlines()[0] == "Q-learning vs Factor-Q, Corridor world (length 12)"


def compare_results(**body) -> dict:
    curve = {"mean": [5.0, 4.0], "low": [4.0, 3.0], "high": [6.0, 5.0]}
    cell = {
        "steps_to_threshold": None,
        "seeds_reached": 0,
        "collisions": 1.0,
        "collisions_ci95": [None, None],
        "greedy_collisions": 1.0,
        "greedy_collisions_ci95": [None, None],
        "avoidable_greedy_collisions": 0.0,
        "final_path_length": 4.0,
        "wall_s": 1.0,
    }
    return {
        "config": {"seed": 0, "seeds": 2, "steps": 100, "size": 4, "obstacles": 2, **body},
        "results": {"factor-q": {"static": cell}},
        "thresholds": {"static": {"shortest_path": 6, "threshold": 9.0}},
        "curves": {
            "env_steps": [50, 100],
            "factor-q": {"static": {"steps": curve, "collisions": curve}},
        },
    }


def test_compare_figure_and_markdown_name_a_non_default_body(titles, tmp_path):
    default = compare_results()
    assert compare_report.markdown(default).splitlines()[0] == "# factorq compare"
    compare_report.figure(default, tmp_path / "a.png")
    assert titles[-1].startswith("per-episode means")

    heading = compare_results(body="heading", sensor_noise=0.1)
    assert compare_report.markdown(heading).splitlines()[0] == (
        "# factorq compare: heading body, sensor noise 0.1"
    )
    compare_report.figure(heading, tmp_path / "b.png")
    assert titles[-1].splitlines()[0] == "heading body, sensor noise 0.1"
