"""Shards: seed ranges of one configuration, run alone, equal the full run bit for bit."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from factorq_trainers.compiled import fast
from factorq_trainers.experiments import paper
from factorq_trainers.experiments import paper_shards as shards
from factorq_trainers.experiments.paper_config import PaperConfig
from factorq_trainers.runner import results as result_files

needs_fast = pytest.mark.skipif(not fast.is_available(), reason="fast backend unavailable")
SMALL = {"seeds": 6, "runs": 2, "episodes": 6, "size": 6, "obstacles": 4}


def _equal(left: shards.ShardMetrics, right: shards.ShardMetrics) -> bool:
    return left.keys() == right.keys() and all(
        left[key].dtype == right[key].dtype and np.array_equal(left[key], right[key])
        for key in left
    )


def _joined(config: PaperConfig, parts: list[shards.ShardMetrics]) -> shards.ShardMetrics:
    cells = shards.concatenate(config, parts)
    return {f"{w}/{a}/{name}": cells[w, a][name] for (w, a) in cells for name in shards.METRICS}


def test_split_cuts_the_seeds_into_contiguous_ranges_covering_each_once():
    parts = shards.split(PaperConfig(seeds=10, first_seed=3), 4)
    assert [(p.first_seed, p.seeds) for p in parts] == [(3, 4), (7, 4), (11, 2)]
    assert {replace(p, first_seed=3, seeds=10) for p in parts} == {
        PaperConfig(seeds=10, first_seed=3)
    }


def test_first_seed_must_be_a_non_negative_int():
    with pytest.raises(ValueError, match="first_seed=-1 is out of range"):
        PaperConfig(first_seed=-1)


@needs_fast
def test_a_seed_range_run_alone_draws_what_it_draws_inside_the_full_run():
    config = PaperConfig(**SMALL, out="unused")
    full = shards.run_shard(config)
    alone = shards.run_shard(replace(config, first_seed=2, seeds=3))
    assert _equal(alone, {key: value[2:5] for key, value in full.items()})


@needs_fast
@pytest.mark.parametrize("shard_seeds", [1, 4, 5])
def test_shards_concatenated_equal_one_process_bit_for_bit(shard_seeds):
    config = PaperConfig(**SMALL, threads=2, out="unused")  # the fast backend's thread pool
    full = shards.run_shard(config)
    parts = [shards.run_shard(shard, threads=1) for shard in shards.split(config, shard_seeds)]
    assert _equal(_joined(config, parts), full)


@needs_fast
def test_modular_backend_shards_equal_the_fast_backend_in_one_process():
    tiny = {"seeds": 3, "runs": 1, "episodes": 2, "size": 4, "obstacles": 2}
    config = PaperConfig(**tiny, backend="fast", out="unused")
    modular = replace(config, backend="modular")
    parts = [shards.run_shard(shard) for shard in shards.split(modular, 2)]
    assert _equal(_joined(config, parts), shards.run_shard(config))


@needs_fast
def test_results_from_shards_equal_paper_run_but_for_timing():
    config = PaperConfig(**SMALL, out="unused")
    expected = paper.run(config)
    parts = [shards.run_shard(shard) for shard in shards.split(config, 4)]
    gathered = shards.results(config, parts, expected["timing"])
    assert result_files.dumps(gathered) == result_files.dumps(expected)


def test_concatenate_refuses_shards_that_miss_seeds():
    config = PaperConfig(seeds=3, runs=1, episodes=1, worlds=("static",), out="unused")
    part = {
        f"static/{a}/{name}": np.zeros((2, 1, 1))
        for a in config.algorithms
        for name in shards.METRICS
    }
    with pytest.raises(ValueError, match="hold 2 seeds of static/q-learning, not 3"):
        shards.concatenate(config, [part])


@needs_fast
def test_a_shard_file_round_trips_and_refuses_another_config(tmp_path):
    config = PaperConfig(**SMALL, out="unused")
    shard = shards.split(config, 4)[1]
    path = shards.shard_path(tmp_path, shard)
    metrics = shards.run_shard(shard)
    shards.save(path, shard, metrics)
    assert path.name == "000004-000006.npz"
    assert _equal(shards.load(path, replace(shard, threads=3, out="elsewhere")), metrics)
    with pytest.raises(ValueError, match="holds another config .*eta"):
        shards.load(path, replace(shard, eta=0.2))
    assert list(path.parent.iterdir()) == [path]  # no temporary left behind


def test_a_damaged_shard_file_is_an_error_naming_it(tmp_path):
    path = tmp_path / "000000-000001.npz"
    path.write_bytes(b"not a zip")
    with pytest.raises(ValueError, match=f"shard file {path} is unreadable"):
        shards.load(path, PaperConfig(seeds=1))


def test_the_digest_ignores_fields_that_do_not_change_the_numbers():
    config = PaperConfig(seeds=5)
    same = replace(config, out="x", threads=2, backend="modular", first_seed=5, seeds=1)
    assert shards.digest(same) == shards.digest(config)
    assert shards.digest(replace(config, obstacles=5)) != shards.digest(config)


def test_a_checkpoint_config_from_before_first_seed_still_resumes(tmp_path):
    saved = paper.config_dict(PaperConfig(seeds=3, out=str(tmp_path)))
    del saved["first_seed"]  # as written before shards existed
    assert paper.resume_config(saved, {}, tmp_path) == PaperConfig(seeds=3, out=str(tmp_path))
