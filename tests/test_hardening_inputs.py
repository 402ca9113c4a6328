"""Issue 29 item 3: bounded parsing. Float options are finite where they are parsed (every
command's, in the shared option parsing), the connect timeout is bounded, a sweep file is bounded
in size and nesting before it is parsed and its YAML may hold no alias, a checkpoint's nesting is
checked before its digest walk recurses, and a sweep grid's size is checked from its axes'
lengths before anything is expanded."""

from __future__ import annotations

import time
from dataclasses import dataclass

import pytest
from timing import patience  # tests/timing.py: bounds that stretch with the load

from factorq_torch.base.validation import check_float
from factorq_trainers.distributed import sweep_spec
from factorq_trainers.runner import cluster, options, reading
from factorq_trainers.runner.frame import Parser


@dataclass(frozen=True)
class Toy:
    rate: float = options.option(0.5, "A float option.")
    count: int = options.option(3, "An int option.")


def parse(capsys, *argv):
    parser = Parser(prog="factorq toy")
    options.add_options(parser, Toy)
    with pytest.raises(SystemExit) as exit_code:
        parser.parse_args(list(argv))
    assert exit_code.value.code == 2
    message = capsys.readouterr().err.strip()
    assert "\n" not in message  # one line, no usage block
    return message


@pytest.mark.parametrize("text", ["inf", "-inf", "nan", "1e400", "9" * 400])
def test_a_float_option_that_is_not_finite_is_refused_while_parsing(capsys, text):
    message = parse(capsys, f"--rate={text}")
    assert message.startswith(f"factorq toy: error: argument --rate: '{text}' is not a finite")


def test_a_float_option_that_is_not_a_number_says_so(capsys):
    assert parse(capsys, "--rate", "abc").endswith(
        "argument --rate: 'abc' is not a number (see factorq toy --help)"
    )


def test_finite_float_options_still_parse():
    parser = Parser(prog="factorq toy")
    options.add_options(parser, Toy)
    assert parser.parse_args(["--rate", "1e300", "--count", "7"]).rate == 1e300


@pytest.mark.parametrize("timeout", [float("inf"), 1e300, 0.0, -1.0, float("nan")])
def test_the_connect_timeout_is_bounded(timeout):
    with pytest.raises(cluster.ClusterError, match=r"--connect-timeout=.* is out of range"):
        cluster.Where(connect_timeout_s=timeout)
    assert cluster.Where(connect_timeout_s=cluster.MAX_CONNECT_TIMEOUT_S).connect_timeout_s > 0


def test_a_huge_integer_for_a_float_field_is_out_of_range_not_an_overflow():
    with pytest.raises(
        ValueError, match=r"alpha=100000000000\.\.\. \(401 digits\) is out of range"
    ):
        check_float("alpha", 10**400, 0.0, 1.0)


def write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    return path


def refused(path, match):
    start = time.perf_counter()
    with pytest.raises(sweep_spec.SweepError, match=match) as error:
        sweep_spec.spec_from_mapping(sweep_spec.read_spec_file(path), str(path))
    assert "\n" not in str(error.value) and str(path) in str(error.value)
    assert time.perf_counter() - start < patience(5)  # bounded: no minute of alias expansion


def test_a_yaml_alias_bomb_is_refused_at_once(tmp_path):
    pytest.importorskip("yaml")
    lines = ['a: &a ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for name, previous in zip("bcdefghi", "abcdefgh", strict=True):
        lines.append(f"{name}: &{name} [{', '.join([f'*{previous}'] * 9)}]")
    refused(write(tmp_path, "bomb.yaml", "\n".join(lines)), r"aliases \(\*name\) are not allowed")


def test_a_plain_yaml_sweep_file_still_reads(tmp_path):
    pytest.importorskip("yaml")
    path = write(tmp_path, "ok.yaml", "grid:\n  alpha: [0.1, 0.2]\nbase: {episodes: 3}\n")
    assert sweep_spec.read_spec_file(path) == {
        "grid": {"alpha": [0.1, 0.2]},
        "base": {"episodes": 3},
    }


@pytest.mark.parametrize(
    ("name", "text"),
    [
        ("deep.toml", "x = " + "[" * 5000 + "]" * 5000),
        ("inline.toml", "x = " + "{a = " * 3000 + "1" + "}" * 3000),
        ("dotted.toml", ".".join(["a"] * 3000) + " = 1"),
        ("deep.yaml", "x: " + "[" * 5000 + "]" * 5000),
    ],
)
def test_deep_nesting_in_a_sweep_file_is_refused_before_recursion(tmp_path, name, text):
    if name.endswith(".yaml"):
        pytest.importorskip("yaml")
    refused(write(tmp_path, name, text), "nests deeper than 32 levels")


def test_brackets_inside_toml_strings_and_comments_do_not_count():
    text = 'a = "[[[[" # [[[[\nb = \'{{{{\'\nc = """\n[[[[\n"""\n[[configs]]\n'
    assert reading.nesting_depth(text, reading.TOML_TOKENS) == 2


def test_an_oversized_sweep_file_is_refused_unread(tmp_path):
    refused(write(tmp_path, "big.toml", "# " + "x" * sweep_spec.MAX_SPEC_BYTES), "bytes, more than")


def test_the_grid_size_is_checked_from_the_axes_lengths_before_expanding():
    axis = list(range(1000))
    start = time.perf_counter()
    with pytest.raises(
        sweep_spec.SweepError, match=r"1000000000 configurations .* more than 10000"
    ):
        sweep_spec.spec_from_mapping({"grid": {"alpha": axis, "gamma": axis, "epsilon": axis}})
    assert time.perf_counter() - start < patience(5)


def test_deeper_than_walks_without_recursion():
    nested: list = []
    for _ in range(100_000):  # far past the interpreter's recursion limit
        nested = [nested]
    assert reading.deeper_than(nested, 32)
    assert not reading.deeper_than({"a": [1, (2, {"b": 3})]}, 4)
    assert reading.deeper_than({"a": [1, (2, {"b": [3]})]}, 4)
