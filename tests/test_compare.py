"""factorq compare: the schema of comparison.json, the threshold, the options."""

from __future__ import annotations

import importlib.util
import json

import numpy as np
import pytest
import torch

from factorq_trainers import cli
from factorq_trainers.commands.compare import command as compare
from factorq_trainers.commands.compare import config as compare_config
from factorq_trainers.methods.dqn import METHODS, DQNConfig
from factorq_trainers.methods.experiment import ExperimentConfig
from factorq_trainers.runner import frame, options

#: outcomes that depend on float rounding: `make test` reruns these under other CPU kernels
pytestmark = pytest.mark.float_sensitive


def _trace(
    world: str, steps: list[int], collisions: int = 0, greedy: int = 0, seed: int = 0
) -> dict:
    lengths = np.asarray(steps, dtype=np.int64)
    return {
        "world": world,
        "seed_index": seed,
        "steps": lengths,
        "env_steps": np.cumsum(lengths),
        "collisions": np.zeros_like(lengths),
        "total_collisions": collisions,
        "total_greedy_collisions": greedy,
        "total_boxed_in_greedy_collisions": 1 if greedy else 0,
    }


def test_compare_writes_the_comparison_schema_of_issue_7(tmp_path, one_thread):
    config = compare.CompareConfig(
        seeds=2,
        steps=120,
        size=4,
        obstacles=2,
        out=str(tmp_path),
        dqn=DQNConfig(learning_starts=40, batch_size=16),
    )
    # the runner's frame, step by step: units, their results through JSON, summary, files, logs
    units = compare.units(config)
    outcomes = [
        frame.unit_result(compare, config, unit, compare.run_unit(config, unit)) for unit in units
    ]
    results = frame.envelope(compare, config, compare.summarise(config, outcomes), wall_s=1.0)
    paths = frame.write_outputs(compare, results, tmp_path)
    paths.update(compare.finish(config, outcomes, tmp_path))
    assert paths["logs"].is_dir() and not list(tmp_path.glob(".*factorq-tmp"))
    saved = json.loads(paths["json"].read_text())
    assert saved["config"]["seeds"] == 2 and saved["config"]["steps"] == 120
    assert list(saved["results"]) == ["factor-q", "q-learning", "dqn", "factor-dqn"]
    for worlds in saved["results"].values():
        assert list(worlds) == ["static", "semi-dynamic", "dynamic"]
        for cell in worlds.values():
            assert cell["steps_to_threshold"] is None or isinstance(
                cell["steps_to_threshold"], float
            )
            assert isinstance(cell["collisions"], float) and cell["collisions"] >= 0
            assert 0 <= cell["greedy_collisions"] <= cell["collisions"]
            assert isinstance(cell["wall_s"], float) and cell["wall_s"] > 0
    # Per-episode logs from torchrl's CSVLogger: "env steps,value" rows, one file per scalar.
    logged = sorted(tmp_path.glob("logs/*/scalars/*/seed_*/path_length.csv"))
    assert logged and {path.parts[-5] for path in logged} <= set(METHODS)
    for path in logged:
        step, value = path.read_text().splitlines()[0].split(",")
        assert int(step) >= float(value) >= 3  # a path of >= 3 steps, ending by that env step
    assert paths["figure"].stat().st_size > 10_000
    table = [line for line in paths["report"].read_text().splitlines() if line.startswith("| ")]
    assert len(table) == 2 + 4 * 3  # header, rule and one row per method and world


def test_shortest_path_is_the_bfs_detour_in_the_static_layout_and_manhattan_when_moving(
    monkeypatch,
):
    # 5x5, walls of obstacles from the left on row 1 and from the right on row 3:
    #   S . . . .        the path zigzags: 4 east, 2 south, 4 west, 2 south, 4 east = 16
    #   # # # # .
    #   . . . . .
    #   . # # # #
    #   . . . . G
    layout = torch.zeros(25, dtype=torch.bool)
    layout[[5, 6, 7, 8, 16, 17, 18, 19]] = True
    monkeypatch.setattr(compare, "static_layout", lambda world: layout)
    experiments = ExperimentConfig(size=5, obstacles=0)
    assert compare.shortest_path_length(experiments, "static") == 16
    assert compare.shortest_path_length(experiments, "dynamic") == 8  # 2 (size - 1)


def test_steps_to_threshold_is_the_end_of_the_first_short_enough_episode():
    trace = _trace("static", [300, 40, 27, 100, 20])
    assert compare.steps_to_threshold(trace, 27.0) == 300 + 40 + 27
    assert compare.steps_to_threshold(trace, 10.0) is None


def test_summary_is_null_unless_every_seed_reached_the_threshold():
    config = compare.CompareConfig(seeds=2, steps=400, regimes=("dynamic",), methods=("dqn",))
    runs = {
        "dqn": {
            "traces": [
                _trace("dynamic", [100, 20, 25], collisions=10, greedy=4),
                _trace("dynamic", [300, 50], collisions=30, greedy=8, seed=1),
            ],
            "wall_s": 2.0,
        }
    }
    cell = compare.summarise(config, [runs["dqn"]])["results"]["dqn"]["dynamic"]
    assert cell["steps_to_threshold"] is None and cell["seeds_reached"] == 1
    assert cell["steps_to_threshold_per_seed"] == [120, None]
    assert cell["collisions"] == 20.0 and cell["greedy_collisions"] == 6.0
    assert cell["avoidable_greedy_collisions"] == 5.0  # one boxed-in collision each
    runs["dqn"]["traces"][1] = _trace("dynamic", [300, 26], seed=1)
    cell = compare.summarise(config, [runs["dqn"]])["results"]["dqn"]["dynamic"]
    assert cell["steps_to_threshold"] == (120 + 326) / 2


def test_compare_config_names_the_bad_option_and_its_range():
    with pytest.raises(ValueError, match="methods: 'sarsa' is unknown"):
        compare.CompareConfig(methods=("dqn", "sarsa"))
    with pytest.raises(ValueError, match=r"steps=0 is out of range: must be in \[1, 2147483647\]"):
        compare.CompareConfig(steps=0)
    with pytest.raises(ValueError, match="logger='wandb' is unknown: choose one of csv"):
        compare.CompareConfig(logger="wandb")
    with pytest.raises(ValueError, match="local_activation='gelu' is unknown"):
        compare_config.FactorDQNConfig(local_activation="gelu")


@pytest.mark.skipif(
    importlib.util.find_spec("tensorboard") is not None, reason="tensorboard is installed"
)
def test_tensorboard_logger_without_the_package_says_how_to_install_it():
    with pytest.raises(ValueError, match="pip install tensorboard"):
        compare.CompareConfig(logger="tensorboard")


def test_command_line_options_become_the_config():
    parser = cli.build_parser()
    command = next(action for action in parser._actions if action.dest == "command")
    assert "--steps STEPS" in command.choices["compare"].format_help()  # field docs: the help
    args = parser.parse_args(
        "compare --seeds 2 --steps 500 --regimes dynamic,static --methods dqn,factor-dqn "
        "--out somewhere --seed 7 --logger csv".split()
    )
    config = compare.CompareConfig(**options.given_options(args, compare.CompareConfig))
    assert (config.seeds, config.steps, config.seed, config.out) == (2, 500, 7, "somewhere")
    assert config.regimes == ("static", "dynamic") and config.methods == ("dqn", "factor-dqn")


def test_bad_command_line_input_is_a_usage_error_that_names_it(capsys):
    assert cli.main(["compare", "--seeds", "0"]) == 2
    assert "seeds=0 is out of range" in capsys.readouterr().err
    assert cli.main(["compare", "--regimes", "windy"]) == 2
    assert "regimes: 'windy' is unknown" in capsys.readouterr().err
    assert cli.main(["compare", "--bogus", "1"]) == 2
    assert "factorq compare: error: unrecognized arguments: --bogus 1" in capsys.readouterr().err


def test_risk_aware_exploration_reaches_factor_q_and_factor_dqn_and_leaves_q_learning_uniform(
    one_thread,
):
    # issue 39: the agent's exploration is Factor-Q's (tabular and neural); Q-learning has no
    # local model, so it keeps uniform exploration instead of being refused
    from factorq_torch.base.config import AgentConfig

    def collisions(exploration: str) -> dict:
        config = compare.CompareConfig(
            seeds=2,
            steps=300,
            size=4,
            obstacles=3,
            regimes=("dynamic",),
            methods=("factor-q", "q-learning", "factor-dqn"),
            agent=AgentConfig(epsilon=0.3, exploration=exploration),
            out="unused",
        )
        results = compare.run(config)["results"]
        return {method: cells["dynamic"]["collisions"] for method, cells in results.items()}

    uniform, careful = collisions("uniform"), collisions("risk-aware")
    assert careful["q-learning"] == uniform["q-learning"]
    assert careful["factor-q"] < uniform["factor-q"]
    assert careful["factor-dqn"] != uniform["factor-dqn"]
