"""Agents as artifacts: save a Factor-Q agent's parts to one file and load them back.

``save_agent(module, path)`` writes a ``TaskQTable``, a ``LocalRewardTable`` (the learned local
model, or the oracle's: a table built on ``env.dependency``), a ``StructureLearner``, a network
(``TaskQNetwork``, ``LocalRewardNetwork``, ``GatedLocalRewardNetwork``) or a whole ``LocalRisk``
layer with its provider; ``load_agent(path)`` rebuilds it. The file is one
``torch.save`` of plain data, read by ``torch.load(weights_only=True)`` (tensors, numbers,
strings, lists and dicts, never pickled code)::

    format, format_version   what the file is ("factorq-agent", FORMAT_VERSION)
    package_version          factorq_torch.__version__ of the writer: another version is refused
    sha256                   digest of the content, tensor bytes included (base.files.digest)
    content:
      kind                   the class: "TaskQTable", "LocalRewardTable", "StructureLearner",
                             "TaskQNetwork", "LocalRewardNetwork", "GatedLocalRewardNetwork",
                             "LocalRisk"
      body                   the actuators and sensors it was trained on: num_actions,
                             num_sensors, actuator_names, sensor_names (names None when unknown)
      config                 the constructor's arguments (the dependency among them; a
                             network's hidden widths, activation and bias read off its layers;
                             its initialisation seed is not kept: the state overwrites it)
      state                  the module's state_dict (tables, counts, a learner's evidence)
      provider               (LocalRisk only) the provider's own kind, body, config and state

Loading checks the file before anything is built: a link or a non-regular file, a file too large,
another format or version, a content that does not match its digest (an edited or truncated file),
an unknown kind or config field; then the module is built by its own constructor (which checks
every argument and size cap) and its state loaded strictly (every tensor's name and shape). With
``env=`` the saved body is compared with the env's (its ``config.actuator_names`` /
``sensor_names`` and ``dependency``): another body is one error naming both sides. Every refusal
is an ``AgentFileError`` (a ``ValueError``) of one line naming the file; nothing half-built is
returned.
"""

from __future__ import annotations

import io
import os
import tempfile
import warnings
from pathlib import Path
from typing import Any

import torch
from tensordict.nn import TensorDictModuleBase

import factorq_torch
from factorq_torch.base.files import digest, read_regular
from factorq_torch.neural import (
    BatchedMLP,
    GatedLocalRewardNetwork,
    LocalRewardNetwork,
    TaskQNetwork,
)
from factorq_torch.risk import LocalRisk
from factorq_torch.structure import StructureLearner
from factorq_torch.tables import LocalRewardTable, TaskQTable

#: The format name written in every file.
FORMAT = "factorq-agent"
#: The file layout's version (a reader reads its own only).
FORMAT_VERSION = 1
#: The largest file read (a Q-learning table of 2**24 values per experiment, many experiments).
MAX_AGENT_BYTES = 4 * 1024**3

#: Each kind's constructor arguments recorded in ``config`` (read back from the module).
_CONFIG: dict[str, tuple[str, ...]] = {
    "TaskQTable": (
        "num_experiments",
        "num_cells",
        "with_sensors",
        "num_sensors",
        "num_headings",
        "num_actions",
        "sensors_key",
        "sparse_grad",
    ),
    "LocalRewardTable": ("num_experiments", "dependency", "sensors_key"),
    "StructureLearner": (
        "num_experiments",
        "num_actions",
        "num_sensors",
        "max_parents",
        "bayes_factor",
        "window",
        "prior_a",
        "prior_b",
        "prior",
        "prediction",
        "reopen",
        "reopen_factor",
        "noisy_reopen_factor",
        "likelihood",
        "pairs",
        "sensors_key",
    ),
    "TaskQNetwork": (
        "num_experiments",
        "num_cells",
        "with_proximity",
        "num_sensors",
        "num_headings",
        "num_actions",
        "hidden",
        "activation",
    ),
    "LocalRewardNetwork": (
        "num_experiments",
        "dependency",
        "hidden",
        "bias",
        "activation",
        "shared",
    ),
    "GatedLocalRewardNetwork": (
        "num_experiments",
        "num_actions",
        "num_sensors",
        "hidden",
        "l1",
        "threshold",
    ),
    "LocalRisk": (
        "dependency",
        "sensor_names",
        "actuator_names",
        "eta",
        "g_min",
        "active",
        "mask_threshold",
        "action_value_key",
        "out_key",
    ),
}
_CLASSES: dict[str, type[TensorDictModuleBase]] = {
    "TaskQTable": TaskQTable,
    "LocalRewardTable": LocalRewardTable,
    "StructureLearner": StructureLearner,
    "TaskQNetwork": TaskQNetwork,
    "LocalRewardNetwork": LocalRewardNetwork,
    "GatedLocalRewardNetwork": GatedLocalRewardNetwork,
    "LocalRisk": LocalRisk,
}
#: Arguments taken positionally by the constructor (the rest are keywords).
_POSITIONAL = {
    "TaskQTable": ("num_experiments", "num_cells"),
    "TaskQNetwork": ("num_experiments", "num_cells"),
}
_BODY = ("num_actions", "num_sensors", "actuator_names", "sensor_names")


class AgentFileError(ValueError):
    """A saved agent that cannot be loaded (the message names the file and why)."""


def save_agent(module: TensorDictModuleBase, path: str | os.PathLike, *, env: Any = None) -> Path:
    """Write ``module`` (a table, a ``StructureLearner`` or a ``LocalRisk`` layer with its
    provider) to ``path``, atomically (a temporary file renamed onto it); returns the path.

    Args:
        module: the agent part to save.
        path: the file to write (replaced if it exists).
        env: the env it was trained on (optional): its actuator and sensor names are recorded
            as the body (a ``LocalRisk`` layer records its own names without it).
    """
    content = _content(module)
    if env is not None:
        names = _env_body(env)
        _compare_body(content["body"], names, "the module to save", "the env", AgentFileError)
        for key in ("actuator_names", "sensor_names"):
            if names[key] is not None:
                content["body"][key] = names[key]
    record = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "package_version": factorq_torch.__version__,
        "sha256": digest(content),
        "content": content,
    }
    path = Path(path)
    descriptor, temporary = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent or ".")
    try:
        with os.fdopen(descriptor, "wb") as handle:
            torch.save(record, handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    return path


def load_agent(
    path: str | os.PathLike, *, env: Any = None, device: torch.device | str | None = None
) -> TensorDictModuleBase:
    """The module saved in ``path`` by ``save_agent``, rebuilt and checked (module docstring);
    an ``AgentFileError`` naming the file when it cannot be used.

    Args:
        path: the saved agent.
        env: the env it will act in (optional): the saved body must be the env's.
        device: where to put the module (default the CPU).
    """
    where = os.fspath(path)
    try:
        data = read_regular(path, "a saved agent", MAX_AGENT_BYTES)
    except (OSError, ValueError) as error:
        raise AgentFileError(str(error)) from None
    try:  # torch warns of what it meets in a damaged file; the error below says it in one line
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            record = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises many kinds on a damaged file: all mean the same
        raise AgentFileError(
            f"saved agent {where} is corrupted or truncated, or not a torch file "
            f"({type(error).__name__})"
        ) from None
    if not isinstance(record, dict) or record.get("format") != FORMAT:
        raise AgentFileError(f"{where} is not a saved factorq agent (no {FORMAT!r} format)")
    if record.get("format_version") != FORMAT_VERSION:
        raise AgentFileError(
            f"saved agent {where} has format version {record.get('format_version')!r}; this "
            f"factorq_torch reads version {FORMAT_VERSION}"
        )
    saved_version = record.get("package_version")
    if saved_version != factorq_torch.__version__:
        raise AgentFileError(
            f"saved agent {where} was written by factorq_torch {saved_version!r}; this is "
            f"{factorq_torch.__version__}: load it with the version that saved it"
        )
    content: Any = record.get("content")
    if digest(content) != record.get("sha256"):
        raise AgentFileError(
            f"saved agent {where} is corrupted or edited (its content does not match its digest)"
        )
    module = _build(content, where)
    if env is not None:
        body = content["body"]
        _compare_body(body, _env_body(env), f"saved agent {where}", "the env", AgentFileError)
    return module if device is None else module.to(device)


# -- writing -------------------------------------------------------------------------------------


def _content(module: TensorDictModuleBase) -> dict[str, Any]:
    kind = next((name for name, cls in _CLASSES.items() if type(module) is cls), None)
    if kind is None:
        raise TypeError(f"save_agent saves a {', '.join(_CLASSES)}, got {type(module).__name__}")
    config = {name: _plain(_argument(module, name)) for name in _CONFIG[kind]}
    state = {name: value.detach().cpu() for name, value in module.state_dict().items()}
    content: dict[str, Any] = {"kind": kind, "config": config}
    if isinstance(module, LocalRisk):
        content["provider"] = _content(module.provider)
        state = {name: value for name, value in state.items() if not name.startswith("provider.")}
        body = dict(content["provider"]["body"])
        for key, default in (("actuator_names", "actuator"), ("sensor_names", "sensor")):
            given = getattr(module, key)
            unnamed = given is None or given == tuple(f"{default} {i}" for i in range(len(given)))
            if not unnamed:  # the layer's default names say nothing about the body
                body[key] = list(given)
    else:
        body = {
            "num_actions": int(module.num_actions),
            "num_sensors": getattr(module, "num_sensors", None),
            "actuator_names": None,
            "sensor_names": None,
        }
    content["body"], content["state"] = body, state
    return content


def _argument(module: TensorDictModuleBase, name: str) -> Any:
    """The constructor argument ``name`` of ``module``: its attribute, or for a network what its
    layers show (the hidden widths, the activation, the bias, the parents of each actuator)."""
    network = getattr(module, "network", None)
    if isinstance(network, BatchedMLP):
        if name == "hidden":
            return [int(weight.shape[-1]) for weight in network.weights[:-1]]
        if name == "activation":
            return str(network.activation.__name__)
        if name == "bias":
            return network.biases is not None
        if name == "dependency" and isinstance(module, LocalRewardNetwork):
            parents = module.parent_index.cpu()  # [A, R]: sensor indices, K past the last
            dependency = torch.zeros(module.num_actions, module.num_sensors + 1, dtype=torch.bool)
            dependency.scatter_(1, parents, True)
            return dependency[:, :-1]
    return getattr(module, name)


def _plain(value: Any) -> Any:
    """``value`` as the plain data ``weights_only`` reads (tuples of names as lists)."""
    if isinstance(value, torch.Tensor):
        return value.detach().cpu().clone()
    if isinstance(value, tuple) and all(isinstance(item, str) for item in value):
        return list(value)
    return value


# -- reading -------------------------------------------------------------------------------------


def _build(content: Any, where: str) -> TensorDictModuleBase:
    """The module described by ``content`` (checked field by field), its state loaded."""
    if not isinstance(content, dict) or content.get("kind") not in _CLASSES:
        kind = content.get("kind") if isinstance(content, dict) else None
        raise AgentFileError(
            f"saved agent {where} holds an unknown kind {kind!r}: expected one of "
            f"{', '.join(_CLASSES)}"
        )
    kind = content["kind"]
    expected = {"kind", "body", "config", "state"} | (
        {"provider"} if kind == "LocalRisk" else set()
    )
    if set(content) != expected:
        raise AgentFileError(
            f"saved agent {where} ({kind}) has fields {sorted(map(str, content))}, expected "
            f"{sorted(expected)}"
        )
    config, state, body = content["config"], content["state"], content["body"]
    if not isinstance(config, dict) or set(config) != set(_CONFIG[kind]):
        fields = sorted(map(str, config)) if isinstance(config, dict) else config
        raise AgentFileError(
            f"saved agent {where} ({kind}) has config {fields}, expected {sorted(_CONFIG[kind])}"
        )
    if not isinstance(body, dict) or set(body) != set(_BODY):
        raise AgentFileError(f"saved agent {where} ({kind}) has no body {list(_BODY)}")
    if not isinstance(state, dict) or not all(
        isinstance(name, str) and isinstance(value, torch.Tensor) for name, value in state.items()
    ):
        raise AgentFileError(f"saved agent {where} ({kind}) has a state that is not tensors")
    arguments = dict(config)
    if kind == "LocalRisk":
        provider = _build(content["provider"], where)
        arguments["action_value_key"] = _key(arguments["action_value_key"], where)
        arguments["out_key"] = _key(arguments["out_key"], where)
        args: tuple = (provider,)
        state = {**state, **{f"provider.{n}": v for n, v in provider.state_dict().items()}}
    else:
        args = tuple(arguments.pop(name) for name in _POSITIONAL.get(kind, ()))
    try:
        module = _CLASSES[kind](*args, **arguments)
        module.load_state_dict(state, strict=True)
    except (TypeError, ValueError, RuntimeError, KeyError) as error:
        reason = " ".join(str(error).split())[:300]
        raise AgentFileError(f"saved agent {where} ({kind}) cannot be rebuilt: {reason}") from None
    _compare_body(
        body, _content(module)["body"], f"saved agent {where}", "its content", AgentFileError
    )
    return module


def _key(value: Any, where: str) -> Any:
    """A tensordict key read back (a string, or a tuple / list of strings)."""
    if isinstance(value, str):
        return value
    if isinstance(value, list | tuple) and value and all(isinstance(v, str) for v in value):
        return tuple(value)
    raise AgentFileError(f"saved agent {where} has the key {value!r}: not a tensordict key")


def _env_body(env: Any) -> dict[str, Any]:
    """The actuators and sensors of ``env`` (its config's names, its dependency's shape)."""
    config = getattr(env, "config", None)
    names = {}
    for key in ("actuator_names", "sensor_names"):
        given = getattr(config, key, None)
        given = getattr(env, key, None) if given is None else given
        names[key] = None if given is None else [str(name) for name in given]
    dependency = getattr(env, "dependency", None)
    actions: int | None
    sensors: int | None
    if isinstance(dependency, torch.Tensor) and dependency.dim() == 2:
        actions, sensors = int(dependency.shape[0]), int(dependency.shape[1])
    else:
        actions = None if names["actuator_names"] is None else len(names["actuator_names"])
        sensors = None if names["sensor_names"] is None else len(names["sensor_names"])
    return {"num_actions": actions, "num_sensors": sensors, **names}


def _describe(body: dict[str, Any]) -> str:
    actuators = body["actuator_names"] or f"{body['num_actions']} unnamed"
    sensors = body["sensor_names"] or f"{body['num_sensors']} unnamed"
    return f"actuators {_words(actuators)} and sensors {_words(sensors)}"


def _words(names: Any) -> str:
    return f"({', '.join(map(str, names))})" if isinstance(names, list) else f"({names})"


def _compare_body(
    mine: dict[str, Any], theirs: dict[str, Any], me: str, them: str, error: type[Exception]
) -> None:
    """One error naming both sides where the bodies differ (what one side does not know is not
    compared)."""
    for key in _BODY:
        if mine.get(key) is not None and theirs.get(key) is not None and mine[key] != theirs[key]:
            raise error(
                f"{me} is for a body with {_describe(mine)}; {them} has {_describe(theirs)}"
            )
