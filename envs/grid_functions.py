"""The FactoredGrid world (SPEC sections 1-2) as pure, batched tensor functions.

State lives in a ``WorldState`` of plain tensors with a leading batch dimension ``S`` of
independent worlds; functions return new states and never mutate their inputs. The torchrl env
(``factorq_envs.torchrl_env``), the gymnasium env (``factorq_envs.gymnasium_env``) and the
compiled fast path (whose kernel mirrors these functions) all run this logic, through
``factorq_envs.grid_world``, which re-exports every name of this module.

Cells are numbered ``row * size + col``; the start is cell 0 (top-left), the goal the last cell.
Actions, in the paper's order: 0 north (row - 1), 1 west (col - 1), 2 south (row + 1), 3 east
(col + 1). Randomness comes from each world's counter stream (``factorq_torch.base.rng``): scatter
number ``m`` of a world uses counters ``m * num_obstacles .. (m + 1) * num_obstacles - 1``.
"""

from __future__ import annotations

import threading
from collections import deque
from typing import Literal, NamedTuple, overload

import torch

from factorq_envs.body import NUM_HEADINGS
from factorq_envs.grid_config import NUM_ACTIONS, WorldConfig
from factorq_torch.base.indices import constant, row_starts
from factorq_torch.base.rng import (
    GOLDEN,
    STREAM_LAYOUT,
    SUBSTREAM_ACTUATOR_NOISE,
    SUBSTREAM_DISTRACTOR,
    SUBSTREAM_SENSOR_NOISE,
    as_int64,
    derive_keys,
    probability_threshold,
    randint_from_bits,
    random_bits,
    substream_key,
)

ROW_DELTA = (-1, 0, 1, 0)
COL_DELTA = (0, -1, 0, 1)
START_CELL = 0
#: Every episode starts facing north (bodies with a heading).
START_HEADING = 0
MAX_LAYOUT_ATTEMPTS = 10_000


class WorldState(NamedTuple):
    """The state of ``S`` independent worlds (all tensors share the leading dimension ``S``)."""

    cell: torch.Tensor  # [S] int64, the agent's cell
    obstacles: torch.Tensor  # [S, N] bool, N = size * size
    bump: torch.Tensor  # [S, A] bool, the actuator whose last firing hit something
    episode_step: torch.Tensor  # [S] int64, actions taken in the current episode
    scatters: torch.Tensor  # [S] int64, obstacle scatters drawn so far (the stream's position)
    heading: torch.Tensor  # [S] int64, the direction faced (always 0 without a heading body)
    ticks: torch.Tensor  # [S] int64, index of the current observation (sensor streams' position)


class StepOutcome(NamedTuple):
    """What one step of ``S`` worlds produced (SPEC section 2)."""

    step_reward: torch.Tensor  # [S] float, -1 on every action
    goal_reward: torch.Tensor  # [S] float, +1 on the action that reaches the goal
    collision: torch.Tensor  # [S, A] float, -1 on the chosen actuator when the step bumped
    terminated: torch.Tensor  # [S] bool, the goal was reached
    truncated: torch.Tensor  # [S] bool, max_steps reached without the goal
    fired: torch.Tensor  # [S] int64, the actuator that actually fired (actuator noise)

    @property
    def task_reward(self) -> torch.Tensor:
        """step + goal: what Factor-Q's task table learns from."""
        return self.step_reward + self.goal_reward

    @property
    def reward(self) -> torch.Tensor:
        """The conventional scalar reward step + goal + sum(collision) (Q-learning, DQN)."""
        return self.task_reward + self.collision.sum(dim=-1)


def empty_state(
    batch: int,
    size: int,
    device: torch.device | str | None = None,
    num_actuators: int = NUM_ACTIONS,
) -> WorldState:
    """``batch`` worlds, the agent on the start cell, no obstacles (then call ``reset_worlds``)."""
    zeros = torch.zeros(batch, dtype=torch.int64, device=device)
    return WorldState(
        cell=zeros.clone(),
        obstacles=torch.zeros(batch, size * size, dtype=torch.bool, device=device),
        bump=torch.zeros(batch, num_actuators, dtype=torch.bool, device=device),
        episode_step=zeros.clone(),
        scatters=zeros.clone(),
        heading=zeros.clone(),
        ticks=zeros.clone(),
    )


def _neighbour_cells(cell: torch.Tensor, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``neighbours`` computed from the cell's row and column (the definition)."""
    deltas_row = torch.tensor(ROW_DELTA, device=cell.device)
    deltas_col = torch.tensor(COL_DELTA, device=cell.device)
    row = (cell // size).unsqueeze(-1) + deltas_row  # [..., 4]
    col = (cell % size).unsqueeze(-1) + deltas_col
    inside = (row >= 0) & (row < size) & (col >= 0) & (col < size)
    return row.clamp(0, size - 1) * size + col.clamp(0, size - 1), inside


def neighbours(cell: torch.Tensor, size: int) -> tuple[torch.Tensor, ...]:
    """The cell one move away in each direction and whether it is inside the grid.

    Shapes: ``[...] -> ([..., 4] int64, [..., 4] bool)``; outside cells are clamped to the edge.
    ``cell`` must lie in ``[0, size**2)``. Looked up in ``_neighbour_cells`` of every cell,
    computed once per size and device (about fifteen small ops a step otherwise).
    """
    device = cell.device

    def build() -> tuple[torch.Tensor, ...]:
        every = torch.arange(size * size)
        return tuple(t.to(device) for t in _neighbour_cells(every, size))

    tables = constant(("neighbours", size, device), build)
    flat = cell.reshape(-1)
    shape = (*cell.shape, len(ROW_DELTA))
    return tuple(t.index_select(0, flat).reshape(shape) for t in tables)


def _move_tables(size: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """``neighbours`` of every cell flattened, ``(target, wall)`` ``[N * NUM_HEADINGS]`` with
    entry ``cell * NUM_HEADINGS + direction`` and ``wall = ~inside``: one lookup per step
    (built once per size and device)."""

    def build() -> tuple[torch.Tensor, torch.Tensor]:
        target, inside = neighbours(torch.arange(size * size, device=device), size)
        return target.reshape(-1), (~inside).reshape(-1)

    return constant(("move tables", size, device), build)


def proximity(cell: torch.Tensor, obstacles: torch.Tensor, size: int) -> torch.Tensor:
    """Proximity sensors ``[S, 4]`` bool: the neighbouring cell is wall or obstacle."""
    target, inside = neighbours(cell, size)
    return ~inside | obstacles.gather(-1, target)


def sense(
    cell: torch.Tensor, heading: torch.Tensor, obstacles: torch.Tensor, config: WorldConfig
) -> torch.Tensor:
    """The layout's sensors ``[S, L]`` bool, in layout order, noise-free: sensor ``k`` is 1 when
    the cell at its offset, turned with ``heading``, is wall or obstacle."""
    size = config.size
    offsets = config._tables["offsets"].to(cell.device)[heading]  # [S, L, 2]
    row = (cell // size).unsqueeze(-1) + offsets[..., 0]  # [S, L]
    col = (cell % size).unsqueeze(-1) + offsets[..., 1]
    inside = (row >= 0) & (row < size) & (col >= 0) & (col < size)
    target = row.clamp(0, size - 1) * size + col.clamp(0, size - 1)
    return ~inside | obstacles.gather(-1, target)


def observe(state: WorldState, key: torch.Tensor, config: WorldConfig) -> torch.Tensor:
    """All sensors as the agent receives them, ``[S, K]`` bool (a pure function of the state).

    1. the layout's sensors (``sense``), then ``num_distractors`` fair coins: distractor ``d`` of
       observation ``t = ticks`` is the top bit of draw ``t * D + d`` of the world's distractor
       sub-stream (``substream_key(key, SUBSTREAM_DISTRACTOR)``), independent of everything else;
    2. sensor noise: bit ``k`` (in that order) is flipped when draw ``t * K + k`` of the
       sensor-noise sub-stream is below ``probability_threshold(sensor_noise)``;
    3. the permutation: the agent's sensor ``j`` is bit ``permutation[j]``.

    The paper's body draws nothing here, so its world stream is untouched.
    """
    readings = sense(state.cell, state.heading, state.obstacles, config)  # [S, L]
    tick = state.ticks.unsqueeze(1)  # [S, 1]
    if config.num_distractors:
        draws = torch.arange(config.num_distractors, device=key.device)
        bits = random_bits(
            substream_key(key, SUBSTREAM_DISTRACTOR).unsqueeze(1),
            tick * config.num_distractors + draws,
        )  # [S, D]
        readings = torch.cat([readings, (bits >> 31).to(torch.bool)], dim=1)  # [S, K]
    if config.sensor_noise > 0:
        draws = torch.arange(config.num_sensors, device=key.device)
        bits = random_bits(
            substream_key(key, SUBSTREAM_SENSOR_NOISE).unsqueeze(1),
            tick * config.num_sensors + draws,
        )
        readings = readings ^ (bits < probability_threshold(config.sensor_noise))
    if config.sensor_permutation is not None:
        readings = readings[:, config._tables["permutation"].to(readings.device)]
    return readings


def scatter_obstacles(
    key: torch.Tensor,
    scatter_index: torch.Tensor,
    agent_cell: torch.Tensor,
    size: int,
    num_obstacles: int,
) -> torch.Tensor:
    """Obstacles ``[S, N]`` bool on ``num_obstacles`` distinct cells drawn uniformly at random.

    The cells are drawn from those that are not the start, the goal or ``agent_cell`` by Floyd's
    algorithm (``num_obstacles`` draws, a uniform subset, no permutation of all cells): index
    ``j`` of the last ``K`` of ``M`` allowed positions draws ``t`` in ``[0, j]`` and takes ``t``,
    or ``j`` itself if ``t`` was taken. Draw ``k`` uses counter ``scatter_index * K + k``.
    """
    num_cells = size * size
    goal = num_cells - 1
    batch = agent_cell.shape[0]
    device = agent_cell.device
    # The excluded cells, ascending: the start (cell 0, START_CELL), the agent, the goal (the
    # last cell); an agent on the start or the goal adds no exclusion. A position p in [0, M)
    # among the allowed cells is cell p + 1 (skip the start), plus 1 at or past a free agent
    # (a sentinel beyond every cell when the agent is not free); the goal is never reached: M
    # positions skip at most M + 2 = num_cells - 1 cells below it.
    agent_free = (agent_cell != START_CELL) & (agent_cell != goal)
    agent_key = torch.where(agent_free, agent_cell, 2 * num_cells)
    allowed = (num_cells - 2) - agent_free.to(torch.int64)  # [S], M
    # All K draws at once (counter scatter_index * K + k), and Floyd's K steps without a loop over
    # them (a handful of ops on [S, K] tensors, no data-dependent branch or shape). Step k draws
    # t_k in [0, j_k], j_k = M - K + k, and takes j_k when t_k was taken before ("collides"),
    # else t_k. t_k was taken iff it equals an earlier t_i (an earlier collision took t_i too:
    # found with the first step that drew each value, a scatter-min), or it equals j_i for the
    # one i = t_k - (M - K) < k and step i collided (j_k exceeds every earlier pick, so only
    # these can match). The second case chains through i < k: resolved by pointer jumping,
    # ceil(log2 K) rounds.
    # (the [S, K] int64 tensors below are written in place where nothing reads them again: at
    # S = 4096 each new one is 320 kB, which the allocator takes from the system and returns,
    # page faults included, several times a step)
    steps = row_starts(num_obstacles, 1, device)  # [K]: 0, 1, ... (cached)
    base = (allowed - num_obstacles).unsqueeze(1)  # [S, 1]
    j = base + steps  # [S, K]
    # Counter scatter_index * K + k of each world's stream: random_bits adds (counter + 1) *
    # GOLDEN to the key, and in wrapping 64-bit arithmetic that is the key moved by
    # scatter_index * K * GOLDEN (per world) plus (k + 1) * GOLDEN (per step), the same bits
    # with the [S, K] counter never built.
    row_key = key + scatter_index * as_int64(num_obstacles * GOLDEN)  # [S]
    bits = random_bits(row_key.unsqueeze(1), steps)  # [S, K], a new tensor
    t = randint_from_bits(bits, j + 1, in_place=True)  # [S, K], t_k in [0, j_k]
    # (in place on fresh tensors of the smallest dtype that holds a step: this [S, N] map and
    # the obstacles are the largest tensors of a step, and memory traffic is what they cost)
    small = torch.int16 if num_obstacles < 2**15 else torch.int64
    step_numbers = steps.to(small)
    first = _scratch((batch, num_cells), small, device).fill_(num_obstacles)
    first.scatter_reduce_(1, t, step_numbers.expand(batch, -1), "amin")  # first step drawing t
    direct = first.gather(1, t) < step_numbers  # [S, K]: an earlier step drew t_k
    # Pointer jumping on one pointer per step: a step whose t_k an earlier step drew points at a
    # sentinel K (collided, and the sentinel points at itself); else at the i with j_i = t_k
    # when 0 <= i < k (it collided iff step i did); else at itself (it did not). After r rounds
    # a pointer has gone 2**r links down its chain (at most K), so it rests on the sentinel
    # exactly when the step collided.
    # (t_k <= j_k, so link <= k: a link of k is the step itself, and only link < 0 needs the
    # self pointer written)
    # (every entry K, the sentinel's; the first K columns are written below)
    pointer = torch.full((batch, num_obstacles + 1), num_obstacles, device=device)
    link = torch.sub(t, base, out=pointer[:, :num_obstacles])
    torch.where(link >= 0, link, steps, out=link)
    link.masked_fill_(direct, num_obstacles)
    jumped = torch.empty_like(pointer)
    for _ in range(max(num_obstacles - 1, 0).bit_length()):
        pointer, jumped = torch.gather(pointer, 1, pointer, out=jumped), pointer
    collided = pointer[:, :num_obstacles] == num_obstacles  # [S, K]
    picks = torch.where(collided, j, t, out=j)  # [S, K], distinct positions in [0, M)
    # positions among the allowed cells -> cells (the start is cell 0), as indices into the
    # flattened [S * N] map (world s's row starts at s * N): index_fill_ on the flat map is
    # 2x faster on CPU than scatter_ along the rows
    rows = row_starts(batch, num_cells, device, column=True)  # [S, 1]
    cells = picks.add_(rows + 1)
    cells += cells >= (agent_key.unsqueeze(1) + rows)
    obstacles = torch.zeros(batch, num_cells, dtype=torch.bool, device=device)
    obstacles.view(-1).index_fill_(0, cells.view(-1), True)
    return obstacles


#: Per thread, ``(shape, dtype, device) -> tensor``: the scatter's ``[S, N]`` map of first draws
#: is scratch (never returned), so each thread reuses one buffer instead of a fresh ``[S, N]``
#: allocation per step (at ``S = 4096`` glibc returns and takes back that memory, page faults
#: included, at every step).
_SCRATCH = threading.local()


def _scratch(shape: tuple, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """An uninitialised buffer of ``shape`` owned by this thread, reused across calls."""
    buffers = getattr(_SCRATCH, "buffers", None)
    if buffers is None:
        buffers = _SCRATCH.buffers = {}
    key = (shape, dtype, torch.device(device))
    buffer = buffers.get(key)
    if buffer is None:
        if len(buffers) >= 8:  # a handful of batch shapes at most: drop the old ones
            buffers.clear()
        buffer = buffers[key] = torch.empty(shape, dtype=dtype, device=device)
    return buffer


def where_rows(mask: torch.Tensor, new: torch.Tensor, old: torch.Tensor) -> torch.Tensor:
    """``torch.where(mask[:, None], new, old)`` for bool maps ``[S, N]`` (``mask`` ``[S]``), the
    same bits: each row is selected as whole words (the widest integer type that divides
    ``N`` bytes), about 3x faster on CPU than the bool ``where``, which is not vectorised when
    the mask broadcasts, and by bit operations, ``old ^ ((old ^ new) & every)`` with
    ``every`` all ones in the masked rows and 0 elsewhere (new there, old elsewhere: 1.5-2x
    faster on CPU than the word ``where``, whose broadcast mask is not vectorised either; the
    ``&`` with all ones or zeros written as a product by 1 or 0, one op fewer)."""
    width = old.shape[-1]
    word = next(
        (d for d in (torch.int64, torch.int32, torch.int16) if width % d.itemsize == 0), None
    )
    if word is not None and all(t.dtype == torch.bool for t in (mask, new, old)):
        try:
            new_words, old_words = new.contiguous().view(word), old.contiguous().view(word)
            every = mask.to(word).unsqueeze(-1)  # 1 in the masked rows, 0 elsewhere
            picked = torch.bitwise_xor(old_words, new_words).mul_(every)  # (x * 1 = x, x * 0 = 0)
            return picked.bitwise_xor_(old_words).view(torch.bool)
        except RuntimeError:  # a storage offset that is no whole word, or a mask that widens
            pass  # the maps: select the bools
    return torch.where(mask.unsqueeze(-1), new, old)


def _scatter_where(
    mask: torch.Tensor,
    obstacles: torch.Tensor,
    scatters: torch.Tensor,
    key: torch.Tensor,
    agent_cell: torch.Tensor,
    config: WorldConfig,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """New obstacles and stream positions after scattering the worlds where ``mask`` is True,
    and the draw of every world (``fresh``, kept or not).

    Every world is drawn and the masked ones kept (``torch.where``): no host synchronisation and
    no data-dependent shape, so a step runs the same ops whatever the mask (CUDA graphs,
    ``torch.compile``). Counter-based streams make the unused draws free of side effects.
    """
    fresh = scatter_obstacles(key, scatters, agent_cell, config.size, config.num_obstacles)
    return where_rows(mask, fresh, obstacles), scatters + mask, fresh  # (int64 + bool: int64)


def is_reachable(obstacles: torch.Tensor, size: int) -> bool:
    """Whether the goal can be reached from the start around ``obstacles`` ``[N]``."""
    return shortest_path_length(obstacles, size) is not None


def shortest_path_length(obstacles: torch.Tensor, size: int) -> int | None:
    """Actions from start to goal on a shortest path around ``obstacles`` ``[N]`` (BFS), or
    ``None`` when the goal cannot be reached."""
    blocked = obstacles.tolist()
    goal = size * size - 1
    distance = {START_CELL: 0}
    frontier = deque([START_CELL])
    while frontier:
        cell = frontier.popleft()
        if cell == goal:
            return distance[cell]
        row, col = divmod(cell, size)
        for d_row, d_col in zip(ROW_DELTA, COL_DELTA, strict=True):
            r, c = row + d_row, col + d_col
            nxt = r * size + c
            if 0 <= r < size and 0 <= c < size and not blocked[nxt] and nxt not in distance:
                distance[nxt] = distance[cell] + 1
                frontier.append(nxt)
    return None


def static_layout(config: WorldConfig) -> torch.Tensor:
    """The static world's obstacles ``[N]`` bool: drawn from ``layout_seed``, redrawn until the
    goal is reachable from the start (SPEC section 1)."""
    # A path from start to goal crosses at least 2 * size - 3 cells besides those two, so more
    # obstacles than (size - 1)**2 can never leave one: fail at once instead of after every draw.
    most = (config.size - 1) ** 2
    if config.num_obstacles > most:
        raise ValueError(
            f"num_obstacles={config.num_obstacles} leaves no path from start to goal in a static "
            f"{config.size}x{config.size} world: must be in [0, {most}]"
        )
    key = derive_keys(config.layout_seed, STREAM_LAYOUT, 1)
    start = torch.zeros(1, dtype=torch.int64)
    for attempt in range(MAX_LAYOUT_ATTEMPTS):
        obstacles = scatter_obstacles(
            key, torch.tensor([attempt]), start, config.size, config.num_obstacles
        )[0]
        if is_reachable(obstacles, config.size):
            return obstacles
    raise ValueError(
        f"num_obstacles={config.num_obstacles}: no layout of a {config.size}x{config.size} grid "
        f"with a path from start to goal was found in {MAX_LAYOUT_ATTEMPTS} draws; use fewer"
    )


def reset_worlds(
    state: WorldState,
    mask: torch.Tensor,
    key: torch.Tensor,
    period: torch.Tensor,
    static_obstacles: torch.Tensor | None,
    config: WorldConfig,
    draws: torch.Tensor | None = None,
) -> WorldState:
    """Start a new episode in the worlds where ``mask`` ``[S]`` is True; the others are unchanged.

    The agent goes to the start with no bump; a static world (``period == 0``) gets
    ``static_obstacles`` ``[N]``, a moving one a fresh scatter. ``static_obstacles=None`` says
    that no world of the batch is static (the caller knows it from ``period``; nothing to copy).
    ``draws`` ``[S, N]``: the scatter each moving world in ``mask`` would draw now (its stream
    position, the agent on the start), when the caller already has it (``step_worlds`` with
    ``keep_draws``: exact for the worlds whose episode that step terminated); None draws it.
    """
    moves_obstacles, _, still = _period_tables(period)
    moving = mask & moves_obstacles
    obstacles = state.obstacles
    if static_obstacles is not None:
        static = mask & still
        obstacles = where_rows(static, static_obstacles.expand_as(obstacles), obstacles)
    scatters = state.scatters
    if config.num_obstacles:
        if draws is None:
            start = torch.full_like(state.cell, START_CELL)
            obstacles, scatters, _ = _scatter_where(moving, obstacles, scatters, key, start, config)
        else:
            obstacles = where_rows(moving, draws, obstacles)
            scatters = scatters + moving  # int64 + bool: int64
    return WorldState(
        cell=state.cell.masked_fill(mask, START_CELL),
        obstacles=obstacles,
        bump=state.bump.masked_fill(mask.unsqueeze(1), False),
        episode_step=state.episode_step.masked_fill(mask, 0),
        scatters=scatters,
        heading=state.heading.masked_fill(mask, START_HEADING),
        ticks=state.ticks + mask,  # a new episode is a new observation (int64 + bool: int64)
    )


#: The last ``period`` tensor seen and its ``(period > 0, period.clamp(min=1), period == 0)``:
#: an env hands the same tensor to every step and reset.
_PERIOD_TABLES: list = [None, None]


def _period_tables(period: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(period > 0, period.clamp(min=1), period == 0)``, computed again only for another
    tensor or after it was modified in place (its ``_version`` moved)."""
    cached, tables = _PERIOD_TABLES
    if cached is None or cached[0] is not period or cached[1] != period._version:
        tables = (period > 0, period.clamp(min=1), period == 0)
        _PERIOD_TABLES[:] = [(period, period._version), tables]
    return tables


@overload
def step_worlds(
    state: WorldState,
    action: torch.Tensor,
    key: torch.Tensor,
    period: torch.Tensor,
    config: WorldConfig,
    keep_draws: Literal[False] = False,
) -> tuple[WorldState, StepOutcome]: ...
@overload
def step_worlds(
    state: WorldState,
    action: torch.Tensor,
    key: torch.Tensor,
    period: torch.Tensor,
    config: WorldConfig,
    keep_draws: Literal[True],
) -> tuple[WorldState, StepOutcome, torch.Tensor | None]: ...
def step_worlds(
    state: WorldState,
    action: torch.Tensor,
    key: torch.Tensor,
    period: torch.Tensor,
    config: WorldConfig,
    keep_draws: bool = False,
) -> tuple[WorldState, StepOutcome] | tuple[WorldState, StepOutcome, torch.Tensor | None]:
    """One action in each of ``S`` worlds (SPEC section 1's order).

    Returns ``(state, outcome)``; with ``keep_draws``, ``(state, outcome, draws)``: the scatter
    every world drew at this step (``[S, N]``, kept only where it scatters; None without
    obstacles). For a world whose episode this step *terminated* it is exactly the scatter its
    next reset draws: a terminating step does not scatter (same stream position) and an agent
    on the goal excludes the same cells as one on the start (neither is a free cell).

    read action -> (actuator noise) -> move or collide, turn -> reward -> (maybe) scatter -> new
    observation. A moving actuator goes one cell in its direction turned with the heading; a
    blocked move (wall or obstacle) leaves the agent in place and sets the bump bit of the chosen
    actuator. Turning actuators change the heading and never move or collide. A world with
    ``period = k > 0`` scatters after every ``k``-th action of the episode, except on the step
    that reaches the goal. ``action`` is int64 ``[S]`` in ``[0, A)``.

    Actuator noise: with probability ``actuator_noise`` (draw ``2t`` of the actuator-noise
    sub-stream, ``t = ticks``, below the threshold) actuator ``(action + 1 + r) % A`` fires
    instead, ``r`` uniform in ``[0, A - 1)`` from draw ``2t + 1``. The collision is attributed
    to the *chosen* actuator (``collision``, ``bump``): the local reward then measures what
    choosing it under the observation costs, which is what eq. 2 ranks actions by, and the agent
    never sees which actuator fired (``StepOutcome.fired`` records it for tests).
    """
    tables = config._tables
    num_actuators = config.num_actuators
    fired = action
    if config.actuator_noise > 0:
        noise_key = substream_key(key, SUBSTREAM_ACTUATOR_NOISE)
        slip = random_bits(noise_key, 2 * state.ticks) < probability_threshold(
            config.actuator_noise
        )
        other = randint_from_bits(random_bits(noise_key, 2 * state.ticks + 1), num_actuators - 1)
        fired = torch.where(slip, (action + 1 + other) % num_actuators, action)
    body = config.body_spec
    always_moves = all(move is not None for move in body.moves)
    # (index_select: the same entries as advanced indexing, a fraction of its per-call cost)
    move = tables["moves"].to(action.device).index_select(0, fired)  # [S], -1: no move
    if body.has_heading:
        direction = (move.clamp(min=0) + state.heading) % NUM_HEADINGS  # [S]
    else:  # the heading stays START_HEADING = 0: relative directions are absolute
        direction = move if always_moves else move.clamp(min=0)
    # the cell one move away in that direction and whether a wall is there, looked up for
    # (cell, direction) at once (the same entries as ``neighbours`` and a gather of its column)
    target_of, wall_of = _move_tables(config.size, action.device)  # [N * 4] each
    entry = state.cell * NUM_HEADINGS + direction  # [S]
    target = target_of.index_select(0, entry)
    blocked = wall_of.index_select(0, entry) | state.obstacles.gather(1, target.unsqueeze(1))[:, 0]
    if always_moves:
        collided = blocked  # [S]
        cell = torch.where(collided, state.cell, target)
    else:
        moving = move >= 0
        collided = moving & blocked
        cell = torch.where(collided | ~moving, state.cell, target)
    if any(body.turns):
        turn = tables["turns"].to(action.device).index_select(0, fired)  # [S]
        heading = (state.heading + turn) % NUM_HEADINGS
    else:
        heading = state.heading
    # the chosen actuator's bit, where it collided: one scatter into zeros
    bump = torch.zeros_like(state.bump).scatter_(1, action.unsqueeze(1), collided.unsqueeze(1))
    episode_step = state.episode_step + 1
    terminated = cell == config.goal_cell
    truncated = ~terminated & (episode_step >= config.max_steps)
    outcome = StepOutcome(
        step_reward=torch.full(cell.shape, -1.0, device=cell.device),
        goal_reward=terminated.to(torch.float32),
        # -1 where it bumped, +0.0 elsewhere (not -bump: that prints, and stores, -0.0)
        collision=torch.zeros(bump.shape, device=bump.device).masked_fill_(bump, -1.0),
        terminated=terminated,
        truncated=truncated,
        fired=fired,
    )
    obstacles, scatters, draws = state.obstacles, state.scatters, None
    moves_obstacles, every, _ = _period_tables(period)
    scatter = moves_obstacles & ~terminated & (episode_step % every == 0)
    if config.num_obstacles:
        obstacles, scatters, draws = _scatter_where(scatter, obstacles, scatters, key, cell, config)
    new_state = WorldState(cell, obstacles, bump, episode_step, scatters, heading, state.ticks + 1)
    if keep_draws:
        return new_state, outcome, draws
    return new_state, outcome


def render_world(cell: int, obstacles: torch.Tensor, size: int) -> str:
    """A text picture of one world: ``#`` wall, ``o`` obstacle, ``A`` agent, ``G`` goal.

    >>> print(render_world(0, torch.zeros(4, dtype=torch.bool), 2))
    ####
    #A.#
    #.G#
    ####
    """
    blocked = obstacles.tolist()
    rows = ["#" * (size + 2)]
    for row in range(size):
        line = ""
        for col in range(size):
            index = row * size + col
            if index == cell:
                line += "A"
            elif index == size * size - 1:
                line += "G"
            else:
                line += "o" if blocked[index] else "."
        rows.append("#" + line + "#")
    rows.append("#" * (size + 2))
    return "\n".join(rows)
