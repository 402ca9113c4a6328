/*
 * The fused fast path of factorq_torch: whole experiments (SPEC section 4) in one tight C loop.
 *
 * This file mirrors, operation for operation, two Python sources and must stay identical to them:
 *   - envs/grid_functions.py   the FactoredGrid world (SPEC sections 1-2): move or collide ->
 *                              reward -> maybe scatter (Floyd's algorithm) -> observation;
 *   - factorq_torch/functional.py  the paper's equations (eq. 1-5) with its float32 order
 *                              contract: explicit left-to-right sums, no fused multiply-add
 *                              (build with -ffp-contract=off), every operation rounded to float.
 * Random numbers come from the counter streams of factorq_torch/rng.py (SplitMix64 finaliser), so
 * experiment i draws exactly what the reference (tests/reference.py) and the torch modules draw.
 * tests/test_fast.py checks equality bit for bit (metrics and final tables).
 *
 * Plain C99 (SSE2 intrinsics where the target has them, the same floats by a scalar route
 * elsewhere), no Python or torch headers: loader.py compiles it on first use and loads it through
 * ctypes, passing the data pointers of contiguous tensors in an fq_batch struct. Each experiment
 * is independent and sequential; threads share the batch and take whole experiments from an
 * atomic counter, so the results do not depend on the thread count or on the scheduling.
 *
 * Where it saves time it computes the same floats by a shorter route, never other floats:
 *   - one experiment runs many steps in a row, its tables hot in L1/L2 (measured: interleaving
 *     2-4 experiments per thread to overlap their dependency chains was no faster);
 *   - draws whose value cannot matter are skipped (the tie draw with a single maximum, the
 *     random action when not exploring): counter-based streams make that free;
 *   - C(s') computed for the eq. 4 target is reused for the next decision when nothing it read
 *     has changed; the spread of rho (eq. 3's denominator) is kept per proximity pattern;
 *   - walls are a ring of blocked cells around the obstacle map, so sensing is four loads;
 *   - the obstacle scatter after a move does not wait for the move (see scatter): waiting would
 *     lengthen every step's chain from one action to the next in the dynamic world.
 */
#include <float.h>
#include <math.h>
#include <stdint.h>
#include <string.h>
#if defined(__SSE2__)
#include <emmintrin.h>
#endif

#define NUM_ACTIONS 4
#define FQ_ABI_VERSION 10
/* Most actuators of a body the generic loop handles (bit masks, small stack arrays). */
#define MAX_ACTUATORS 32
/* Most candidates of the structure learner (1 + K + K (K - 1) / 2 for K <= 62). */
#define LEARNER_SCRATCH 1954

/* rng.py's constants: key + (counter + 1) * GOLDEN, then the SplitMix64 finaliser. */
#define GOLDEN 0x9E3779B97F4A7C15ULL
#define MIX1 0xBF58476D1CE4E5B9ULL
#define MIX2 0x94D049BB133111EBULL

/* rng.py's POLICY_DRAWS_PER_STEP and the meaning of each draw of decision t. */
#define POLICY_DRAWS 3
#define DRAW_EXPLORE 0
#define DRAW_ACTION 1
#define DRAW_TIE 2

enum { ALG_RANDOM_WALK = 0, ALG_Q_LEARNING = 1, ALG_FACTOR_Q = 2 };

/*
 * One batch of S experiments. Layouts (all C-contiguous, leading dimension S):
 *   q [S, states, 4] float (states = N for Factor-Q, N * 16 for Q-learning, cell * 16 + pattern),
 *   rho [S, 4, 2] float and kappa [S, 4, 2] int64 (actuator, sensor value),
 *   grid [S, P] uint8: the obstacle map padded by a one-cell wall ring, P = (size + 2)^2, so that
 *   a wall and an obstacle are the same thing (blocked = 1) and no bounds checks are needed,
 *   obstacle_pads [S, K] int32: padded indices of the current obstacles (cleared on a scatter),
 *   metrics [S, runs, episodes].
 * The blocks a thread writes in its inner loop (q, rho, kappa, grid, obstacle_pads) start every
 * experiment at its own 64-byte cache line: experiment i's block is at i * *_stride elements (a
 * row of the [S, stride] storage, stride rounded up by batch_options.py), so two threads working on
 * neighbouring experiments never write one cache line (false sharing halved the second thread's
 * throughput when the 144-byte grids and 40-byte obstacle lists were packed back to back).
 * Field order and types must match loader.py's _Batch (checked through fq_batch_size()).
 */
typedef struct {
    int64_t algorithm;
    int64_t num_experiments;
    int64_t size;
    int64_t num_obstacles;
    int64_t max_steps;
    int64_t runs;
    int64_t episodes;
    int64_t explore_threshold; /* rng.probability_threshold(epsilon), in [0, 2^32] */
    const int64_t *periods;    /* [S] 0 static, k > 0 scatter after every k-th action */
    const int64_t *world_keys; /* [S] */
    const int64_t *policy_keys; /* [S] */
    const uint8_t *static_grid; /* [P] the static layout, padded */
    const int32_t *pad_of_cell; /* [N] padded index of each cell */
    float *q;
    float *rho;
    int64_t *kappa;
    uint8_t *grid;
    int32_t *obstacle_pads;
    int64_t *cell;
    int64_t *episode_step;
    int64_t *scatters;
    int64_t *policy_counter;
    int64_t *run;
    int64_t *episode;
    uint8_t *bump; /* [S, 4] */
    int64_t *episode_collisions;
    int64_t *episode_greedy_collisions;
    float *episode_task_return;
    int64_t *steps;
    int64_t *collisions;
    int64_t *greedy_collisions;
    float *task_return;
    float gamma;
    float alpha;
    float eta_factor; /* float32(1 + eta), as torch applies the Python scalar */
    float g_min;
    /* The body (envs/body.py) for the generic loop (generic != 0); the paper's body runs the
       specialised loop above and ignores these. */
    int64_t generic;
    int64_t num_actuators;   /* A */
    int64_t num_sensors;     /* K: layout sensors + distractors, all received by the agent */
    int64_t num_layout;      /* L: layout sensors */
    int64_t num_headings;    /* 1, or 4 with a heading */
    int64_t table_width;     /* P = 2^max |D(a)|: entries per actuator in rho and kappa */
    int64_t sensor_noise_threshold;   /* rng.probability_threshold(sensor_noise) */
    int64_t actuator_noise_threshold; /* rng.probability_threshold(actuator_noise) */
    const int64_t *moves;          /* [A] direction relative to the heading, -1: no move */
    const int64_t *turns;          /* [A] quarter turns to the left */
    const int64_t *offsets;        /* [4, L] padded-grid offset of layout sensor k at heading h */
    const int64_t *permutation;    /* [K] agent's sensor j = sensor permutation[j] */
    const int64_t *parent_weights; /* [A, K] functional.parent_weights(dependency) */
    int64_t *heading;              /* [S] */
    int64_t *ticks;                /* [S] index of the current observation (world.WorldState) */
    /* Elements from one experiment's block to the next (each a multiple of 64 bytes). */
    int64_t q_stride;
    int64_t rho_stride;
    int64_t kappa_stride;
    int64_t grid_stride;
    int64_t obstacle_stride;
    /* The structure learner (factorq_torch/structure.py) as the local value provider of
       the generic Factor-Q loop (learner != 0); see the learner section below. */
    int64_t learner;
    int64_t num_candidates;   /* C */
    int64_t learner_patterns; /* 2^max_parents: patterns of a candidate */
    int64_t prediction;       /* 0: map, 1: committed (0 before commitment), 2: optimistic */
    int64_t window;
    int64_t change_run;       /* run at which orders_after replaces orders; 0: never */
    int64_t curve_every;
    int64_t curve_length;
    int64_t lgamma_length;    /* M: entries of each lgamma table */
    int64_t learner_stride;   /* doubles of one experiment's counts block */
    int64_t reopen_body;      /* a reopening forgets every actuator (1) or its own (0) */
    int64_t likelihood_flip;  /* functional.LIKELIHOODS: 1 "flip", 0 "pattern" or "mixture" */
    int64_t mixture;          /* 1: "mixture" (each pattern's rate clean or noisy) */
    int64_t prune_pairs;      /* 1: functional.PAIR_MODES "pruned" (pairs counted while active) */
    int64_t history_capacity; /* L: firings the history of one experiment holds (pruned) */
    double log_bayes_factor;
    double log_reopen_factor;          /* the change-point test's threshold */
    double log_noisy_reopen_factor;    /* its threshold once noise_seen (noisy_reopen_factor) */
    double log_beta_prior;
    double log_noisy_beta_prior;       /* functional.NOISY_PRIOR's log B(a, b) */
    double log_mixture_total;          /* log(1 + NOISY_ODDS) */
    double log_noisy_weight;           /* log(NOISY_ODDS) - log(1 + NOISY_ODDS) */
    const int64_t *candidate_sensors; /* [C, 2] the candidate's sensors, -1: none */
    const double *log_prior;          /* [C] */
    const uint8_t *competitors;       /* [C, C] */
    const double *lgamma_table;       /* [3, M] lgamma(a + m), lgamma(b + m), lgamma(a + b + m) */
    const double *noisy_lgamma_table; /* [3, M] the same of functional.NOISY_PRIOR ("mixture") */
    const int64_t *orders;            /* [S, K] agent sensor j = world sensor orders[s, j]; NULL:
                                         the world's order (any algorithm may have orders) */
    const int64_t *orders_after;      /* [S, K] the order after the change */
    const int64_t *truth;             /* [S, 2, A] candidate index of the true parents, -2: none */
    const uint8_t *initial_active;    /* [C] functional.initial_activity */
    const int16_t *all_candidates;    /* [C] 0, 1, ..., C - 1 (the list without pruning) */
    double *counts;                   /* [S, stride]: [A, C, 8, P] (learner_view) */
    int64_t *committed;               /* [S, A] candidate, -1 open */
    int64_t *samples;                 /* [S, A] */
    int64_t *block_samples;           /* [S, A] */
    int64_t *reopened;                /* [S, A] */
    int64_t *map_cache;               /* [S, A] argmax of the log posterior */
    uint8_t *plausible;               /* [S, A, C] log posterior >= its max - log bayes_factor */
    int64_t *right_since;             /* [S, A] samples when it last became right, -1 */
    int64_t *samples_at_change;       /* [S, A] */
    int64_t *wrong_commitments;       /* [S] */
    int64_t *noise_seen;              /* [S] 1 once a commitment's data held a minority outcome */
    int64_t *change_tick;             /* [S] tick of the last observation in the old order, -1 */
    uint8_t *curve;                   /* [S, curve_length] all right at step t * curve_every */
    /* pair pruning (prune_pairs): the active candidates and every firing since the start */
    uint8_t *active;                  /* [S, A, C] counted and scored */
    int64_t *history_readings;        /* [S, L] the agent's sensor bits before the firing */
    uint8_t *history_action;          /* [S, L] the fired actuator */
    float *history_reward;            /* [S, L] its local reward */
    int64_t *history_length;          /* [S] firings recorded */
    int64_t *history_start;           /* [S, A] the actuator's counts start at this firing */
    int64_t *block_start;             /* [S, A] its block starts at this firing */
    int16_t *active_list;             /* [S, A, C] the active candidates, increasing */
    int64_t *active_count;            /* [S, A] how many */
    /* Factor-Q's risk options (AgentConfig; generic loop only, docs/decisions.md, issue 39). */
    int64_t risk_gate;    /* eqs. 2-3 see functional.significant_local(rho, risk_threshold) */
    int64_t risk_explore; /* exploration "risk-aware": epsilon actions among risk_mask(rho) */
    float risk_threshold; /* float32(risk_threshold), as torch's 0-d constant */
} fq_batch;

int64_t fq_abi_version(void) { return FQ_ABI_VERSION; }
int64_t fq_batch_size(void) { return (int64_t)sizeof(fq_batch); }

/* rng.random_bits: the top 32 bits of mix64(key + (counter + 1) * GOLDEN). */
static inline uint64_t random_bits(uint64_t key, uint64_t counter) {
    uint64_t z = key + (counter + 1) * GOLDEN;
    z = (z ^ (z >> 30)) * MIX1;
    z = (z ^ (z >> 27)) * MIX2;
    z ^= z >> 31;
    return z >> 32;
}

/* world.proximity: bit a is set when the neighbour in direction a is wall or obstacle. */
static inline unsigned proximity(const uint8_t *grid, int64_t pos, int64_t width) {
    return (unsigned)grid[pos - width] | (unsigned)grid[pos - 1] << 1 |
           (unsigned)grid[pos + width] << 2 | (unsigned)grid[pos + 1] << 3;
}

/*
 * world.scatter_obstacles: num_obstacles distinct cells, uniformly among those other than the
 * start, the goal and the agent, by Floyd's algorithm. Position j of the last K of the M allowed
 * positions draws t in [0, j] (counter scatter_index * K + k) and takes t, or j if t is taken.
 * Positions map to cells in ascending order skipping the excluded cells, a bijection, so "t is
 * taken" is read straight off the (cleared) obstacle map instead of a separate bitmap. The branch
 * on it is predicted "free" (taken on about 5% of the draws), so each draw's store address is
 * known early and j's cell is looked up only when needed: fewer instructions per draw, which is
 * what bounds the dynamic world (measured: a branch-free 128-bit mask of taken positions in
 * registers chained the draws one after the other and was 9% slower there).
 */
static inline __attribute__((always_inline)) void scatter_positions(
    uint8_t *grid, int32_t *obstacle_pads, const int32_t *pad_of_cell, int64_t allowed,
    int64_t skip, int64_t num_obstacles, uint64_t key, uint64_t first_counter) {
    for (int64_t k = 0; k < num_obstacles; k++) {
        const int64_t j = allowed - num_obstacles + k;
        const int64_t t = (int64_t)((random_bits(key, first_counter + (uint64_t)k) *
                                     (uint64_t)(j + 1)) >> 32);
        /* position -> cell: skip the start (cell 0), then the agent; the goal, the last cell,
           is never reached because positions stop at allowed - 1. Both candidate cells are
           read before the agent's cell is compared, so that only a select waits on it. */
        const int32_t below = pad_of_cell[t + 1], above = pad_of_cell[t + 2];
        int32_t pad = t + 1 >= skip ? above : below;
        if (__builtin_expect(grid[pad], 0)) { /* t taken: take j */
            int64_t cell_j = j + 1;
            cell_j += cell_j >= skip;
            pad = pad_of_cell[cell_j];
        }
        grid[pad] = 1;
        obstacle_pads[k] = pad;
    }
}

static void scatter(uint8_t *grid, int32_t *obstacle_pads, const int32_t *pad_of_cell,
                    int64_t num_cells, int64_t num_obstacles, uint64_t key, uint64_t scatter_index,
                    int64_t agent) {
    const uint64_t first_counter = scatter_index * (uint64_t)num_obstacles;
    for (int64_t k = 0; k < num_obstacles; k++) grid[obstacle_pads[k]] = 0;
    /* The agent is almost always on a free cell (a scatter never happens on the goal): with
       the number of allowed positions a constant on that predicted branch, the draws do not
       wait for the agent's move, which the dynamic world's every step otherwise did. */
    if (__builtin_expect(agent != 0 && agent != num_cells - 1, 1))
        scatter_positions(grid, obstacle_pads, pad_of_cell, num_cells - 3, agent, num_obstacles,
                          key, first_counter);
    else /* the start (and the goal) excluded anyway: nothing after the start to skip */
        scatter_positions(grid, obstacle_pads, pad_of_cell, num_cells - 2, num_cells,
                          num_obstacles, key, first_counter);
}

/* Index of the k-th set bit (k counted from 0) of a 4-bit mask. */
static inline int kth_set_bit(unsigned mask, uint64_t k) {
    for (; k > 0; k--) mask &= mask - 1;
    return __builtin_ctz(mask);
}

/*
 * functional.greedy_action_from_bits inside epsilon_greedy_from_bits: the k-th maximal action in
 * index order, k = bits * count >> 32. The tie draw is made only when there is a tie (with one
 * maximum k = 0 whatever the bits; counter-based streams make skipping a draw free).
 */
static inline int greedy_action(const float values[NUM_ACTIONS], uint64_t key, uint64_t counter) {
    float best = values[0];
    for (int a = 1; a < NUM_ACTIONS; a++) best = values[a] > best ? values[a] : best;
    unsigned is_max = 0;
#if defined(__SSE2__) && NUM_ACTIONS == 4
    /* the four == at once (ordered, quiet: NaN equals nothing, -0 == +0, as C's ==): 3
       instructions instead of about 20 (each scalar == is a compare, two flag reads and an and) */
    is_max = (unsigned)_mm_movemask_ps(_mm_cmpeq_ps(_mm_loadu_ps(values), _mm_set1_ps(best)));
#else
    for (int a = 0; a < NUM_ACTIONS; a++) is_max |= (unsigned)(values[a] == best) << a;
#endif
    is_max |= is_max == 0; /* none equals the max (NaN): action 0, as functional does */
    if ((is_max & (is_max - 1)) == 0) return __builtin_ctz(is_max);
    /* the count of a 4-bit mask by hand: __builtin_popcount is a libgcc call where the build
       targets CPUs without POPCNT (the portable -O3 build) */
    const uint64_t count = (is_max & 1u) + (is_max >> 1 & 1u) + (is_max >> 2 & 1u) + (is_max >> 3);
    const uint64_t k = (random_bits(key, counter * POLICY_DRAWS + DRAW_TIE) * count) >> 32;
    return kth_set_bit(is_max, k);
}

/* max_a values[a] as in q_learning_target (the sign of a zero never matters there). */
static inline float max4(const float values[NUM_ACTIONS]) {
    float best = values[0];
    for (int a = 1; a < NUM_ACTIONS; a++) best = values[a] > best ? values[a] : best;
    return best;
}

/*
 * Eq. 3, functional.normaliser, in two halves:
 *   G = (Q(s,a_hat) - Q_bar) / (P_bar - rho[a_check]) * (1 + eta),
 * a_hat the first maximum of Q, a_check the first minimum of rho, the bars the mean of the other
 * three (summed left to right, then divided by 3); G = g_min when the denominator is not > 0 or
 * when G < g_min (also catches NaN). The denominator (the local spread) depends on rho(o) only,
 * that is on the proximity pattern and the rho table, so it is computed for all 16 patterns when
 * rho changes (rarely) rather than at every step; the result is the same float.
 */
static inline float local_spread(const float rho[NUM_ACTIONS]) {
    int a_check = 0;
    for (int a = 1; a < NUM_ACTIONS; a++)
        if (rho[a] < rho[a_check]) a_check = a;
    float rho_sum = 0.0f;
    for (int a = 0; a < NUM_ACTIONS; a++)
        if (a != a_check) rho_sum = rho_sum + rho[a];
    return rho_sum / (float)(NUM_ACTIONS - 1) - rho[a_check];
}

static inline float normaliser(const float q[NUM_ACTIONS], float spread, float eta_factor,
                               float g_min) {
    if (!(spread > 0.0f)) return g_min;
    int a_hat = 0;
    for (int a = 1; a < NUM_ACTIONS; a++)
        if (q[a] > q[a_hat]) a_hat = a;
    float q_sum = 0.0f;
    for (int a = 0; a < NUM_ACTIONS; a++)
        if (a != a_hat) q_sum = q_sum + q[a];
    const float x = q[a_hat] - q_sum / (float)(NUM_ACTIONS - 1);
    const float g = x / spread * eta_factor;
    /* an overflowed ratio is capped at the largest float, as functional.normaliser does */
    return g >= g_min ? (g > FLT_MAX ? FLT_MAX : g) : g_min;
}

/* rho(o) (rho(o)_a = rho_a[o_a]) and its spread for each of the 16 proximity patterns o. */
typedef struct {
    float local[16][NUM_ACTIONS];
    float spread[16];
} local_patterns;

static void project_local(const float rho_table[8], local_patterns *patterns) {
    for (unsigned pattern = 0; pattern < 16; pattern++) {
        for (int a = 0; a < NUM_ACTIONS; a++)
            patterns->local[pattern][a] = rho_table[a * 2 + ((pattern >> a) & 1u)];
        patterns->spread[pattern] = local_spread(patterns->local[pattern]);
    }
}

/* Eq. 2, functional.combined_values: C = Q + G rho, capped to the float range. */
static inline void combine(const float q[NUM_ACTIONS], float g, const float local[NUM_ACTIONS],
                           float out[NUM_ACTIONS]) {
#if defined(__SSE2__) && NUM_ACTIONS == 4
    /* The same four roundings (a product, then a sum, per lane; no FMA) and the same cap:
       minps(x, y) is x < y ? x : y, so min(FLT_MAX, c) is c > FLT_MAX ? FLT_MAX : c (a NaN c
       kept) and max(-FLT_MAX, that) is its < -FLT_MAX branch: 4 instructions, not 30. */
    const __m128 c = _mm_add_ps(_mm_loadu_ps(q), _mm_mul_ps(_mm_set1_ps(g), _mm_loadu_ps(local)));
    const __m128 capped = _mm_max_ps(_mm_set1_ps(-FLT_MAX), _mm_min_ps(_mm_set1_ps(FLT_MAX), c));
    _mm_storeu_ps(out, capped);
#else
    for (int a = 0; a < NUM_ACTIONS; a++) {
        const float c = q[a] + g * local[a];
        out[a] = c > FLT_MAX ? FLT_MAX : (c < -FLT_MAX ? -FLT_MAX : c);
    }
#endif
}

/* C(s) for the rho(o) of proximity pattern prox. */
static inline void combined_values(const float q[NUM_ACTIONS], const local_patterns *patterns,
                                   unsigned prox, float eta_factor, float g_min,
                                   float out[NUM_ACTIONS]) {
    const float *local = patterns->local[prox];
    combine(q, normaliser(q, patterns->spread[prox], eta_factor, g_min), local, out);
}

/* The end of an episode, in both loops (SPEC section 4): its metrics into its slot, the episode's
   counts zeroed, the next episode (and run) begun; at the start of a further run the Q table
   (q_floats entries, NULL: none) restarts at 0 while Factor-Q's local tables carry over, and a
   moving world draws a fresh scatter with the agent at the start (grid_world.reset_worlds).
   Putting the agent back at the start is the caller's. */
static inline void end_episode(const fq_batch *b, int64_t i, int64_t episode_step, int64_t *run,
                               int64_t *episode, int64_t *collisions, int64_t *greedy,
                               float *task_return, float *q, size_t q_floats, uint8_t *grid,
                               int32_t *obstacle_pads, int moving, uint64_t world_key,
                               int64_t *scatters) {
    const int64_t slot = (i * b->runs + *run) * b->episodes + *episode;
    b->steps[slot] = episode_step;
    b->collisions[slot] = *collisions;
    b->greedy_collisions[slot] = *greedy;
    b->task_return[slot] = *task_return;
    *collisions = 0;
    *greedy = 0;
    *task_return = 0.0f;
    if (++*episode == b->episodes) {
        *episode = 0;
        ++*run;
    }
    if (*run < b->runs) {
        if (*episode == 0 && q != NULL) memset(q, 0, q_floats * sizeof(float));
        if (moving) {
            scatter(grid, obstacle_pads, b->pad_of_cell, b->size * b->size, b->num_obstacles,
                    world_key, (uint64_t)*scatters, 0);
            ++*scatters;
        }
    }
}

/* Run experiment i for up to budget steps; returns the episodes it completed. Forced inline: each
   of run_random_walk, run_q_learning and run_factor_q below gets its own copy with the algorithm
   a constant (without the attribute gcc -O3 kept one shared copy, the algorithm a runtime
   argument tested in every step). */
static inline __attribute__((always_inline)) int64_t run_experiment(const fq_batch *b, int64_t i, int64_t budget,
                                     const int algorithm) {
    const int64_t size = b->size, width = size + 2, num_cells = size * size;
    const int64_t goal = num_cells - 1, num_obstacles = b->num_obstacles;
    const int64_t max_steps = b->max_steps;
    const int64_t runs = b->runs;
    const int64_t period = b->periods[i];
    const int moving = period > 0 && num_obstacles > 0;
    const uint64_t world_key = (uint64_t)b->world_keys[i];
    const uint64_t policy_key = (uint64_t)b->policy_keys[i];
    const uint64_t explore_threshold = (uint64_t)b->explore_threshold;
    const int64_t num_states = algorithm == ALG_Q_LEARNING ? num_cells * 16 : num_cells;
    const float gamma = b->gamma, alpha = b->alpha, eta_factor = b->eta_factor, g_min = b->g_min;
    const int32_t *pad_of_cell = b->pad_of_cell;
    const int64_t move_pad[NUM_ACTIONS] = {-width, -1, width, 1};
    const int64_t move_cell[NUM_ACTIONS] = {-size, -1, size, 1};

    float *q = algorithm == ALG_RANDOM_WALK ? NULL : b->q + i * b->q_stride;
    uint8_t *grid = b->grid + i * b->grid_stride;
    int32_t *obstacle_pads = num_obstacles > 0 ? b->obstacle_pads + i * b->obstacle_stride : NULL;
    uint8_t *bump = b->bump + i * NUM_ACTIONS;

    /* Eq. 5's tables live in registers/L1 for the call and are written back at the end. */
    float rho[8];
    int64_t kappa[8];
    local_patterns patterns;
    if (algorithm == ALG_FACTOR_Q) {
        memcpy(rho, b->rho + i * b->rho_stride, sizeof rho);
        memcpy(kappa, b->kappa + i * b->kappa_stride, sizeof kappa);
        project_local(rho, &patterns);
    }

    int64_t cell = b->cell[i], pos = pad_of_cell[cell];
    int64_t episode_step = b->episode_step[i], scatters = b->scatters[i];
    uint64_t counter = (uint64_t)b->policy_counter[i];
    int64_t run = b->run[i], episode = b->episode[i];
    int64_t episode_collisions = b->episode_collisions[i];
    int64_t episode_greedy = b->episode_greedy_collisions[i];
    float episode_return = b->episode_task_return[i];
    int64_t until_scatter = period > 0 ? period - episode_step % period : 0;
    int last_bump = -2; /* -2: no step taken in this call, bump unchanged */
    int64_t completed = 0;

    /* A world that never scatters senses from a table of each cell's pattern: one load after
       the move instead of four and their combination. Built per call, so only where the call
       may run enough steps to pay for it (the paper's 100 cells: from 400 steps). */
    uint8_t prox_of_cell[4096];
    const int sense_table = !moving && num_cells <= 4096 && budget >= 4 * num_cells;
    if (sense_table)
        for (int64_t c = 0; c < num_cells; c++)
            prox_of_cell[c] = (uint8_t)proximity(grid, pad_of_cell[c], width);
#define SENSE() (sense_table ? (unsigned)prox_of_cell[cell] : proximity(grid, pos, width))
    unsigned prox = SENSE();
    /* C(s) of the current state, computed for the previous target and still exact when neither
       the Q row nor the rho entries it used have changed since (see the end of the step). */
    float cached[NUM_ACTIONS];
    int cache_valid = 0;

    for (; budget > 0 && run < runs; budget--) {
        /* --- act: epsilon-greedy on Q (eq. 1) or on C(s) (eq. 2-3) --- */
        const int64_t state = algorithm == ALG_Q_LEARNING ? cell * 16 + prox : cell;
        float values[NUM_ACTIONS];
        int action, exploratory;
        if (algorithm == ALG_RANDOM_WALK) {
            action = (int)(random_bits(policy_key, counter * POLICY_DRAWS + DRAW_ACTION) >> 30);
            exploratory = 1;
        } else {
            if (algorithm == ALG_Q_LEARNING) {
                memcpy(values, q + state * NUM_ACTIONS, sizeof values);
            } else if (cache_valid) {
                memcpy(values, cached, sizeof values);
            } else {
                combined_values(q + state * NUM_ACTIONS, &patterns, prox, eta_factor, g_min, values);
            }
            exploratory =
                random_bits(policy_key, counter * POLICY_DRAWS + DRAW_EXPLORE) < explore_threshold;
            if (exploratory) {
                /* randint_from_bits(bits, 4) = bits * 4 >> 32 */
                action =
                    (int)(random_bits(policy_key, counter * POLICY_DRAWS + DRAW_ACTION) >> 30);
            } else {
                action = greedy_action(values, policy_key, counter);
            }
        }
        counter++;

        /* --- world step (grid_world.step_worlds): move or collide, reward, maybe scatter --- */
        const int collided = (prox >> action) & 1u;
        if (!collided) {
            pos += move_pad[action];
            cell += move_cell[action];
        }
        last_bump = collided ? action : -1;
        episode_step++;
        const int terminated = cell == goal;
        const int truncated = !terminated && episode_step >= max_steps;
        const float task_reward = -1.0f + (float)terminated; /* step + goal */
        const float local_reward = collided ? -1.0f : 0.0f; /* collision[action] */
        if (period > 0 && --until_scatter == 0) {
            until_scatter = period;
            if (moving && !terminated) {
                scatter(grid, obstacle_pads, pad_of_cell, num_cells, num_obstacles, world_key,
                        (uint64_t)scatters, cell);
                scatters++;
            }
        }
        const unsigned next_prox = SENSE();

        /* --- learn --- */
        if (algorithm == ALG_Q_LEARNING) {
            /* Eq. 1 with the conventional reward step + goal + sum(collision). */
            const float reward = task_reward + local_reward;
            float *q_sa = q + state * NUM_ACTIONS + action;
            float target = reward;
            if (!terminated) target = reward + gamma * max4(q + (cell * 16 + next_prox) * NUM_ACTIONS);
            *q_sa = *q_sa + alpha * (target - *q_sa);
        } else if (algorithm == ALG_FACTOR_Q) {
            /* Eq. 4: target r_task + gamma max C(s'), C(s') with G and rho at s' (eq. 2-3). */
            float next_values[NUM_ACTIONS];
            float target = task_reward;
            if (!terminated) {
                combined_values(q + cell * NUM_ACTIONS, &patterns, next_prox, eta_factor, g_min,
                                next_values);
                target = task_reward + gamma * max4(next_values);
            }
            float *q_sa = q + state * NUM_ACTIONS + action;
            *q_sa = *q_sa + alpha * (target - *q_sa);
            /* Eq. 5 for the fired actuator on the sensor value read before acting (= collided):
               kappa += 1, rho += (r_L - rho) / kappa. */
            const int entry = action * 2 + collided;
            const float old_rho = rho[entry];
            kappa[entry] += 1;
            rho[entry] = old_rho + (local_reward - old_rho) / (float)kappa[entry];
            uint32_t old_bits, new_bits;
            memcpy(&old_bits, &old_rho, sizeof old_bits);
            memcpy(&new_bits, &rho[entry], sizeof new_bits);
            /* C(s') stays exact for the next decision when the Q row of s' was not the one just
               updated (it was only if the agent stayed, i.e. collided) and rho did not change. */
            cache_valid = !terminated && !collided && old_bits == new_bits;
            if (old_bits != new_bits) project_local(rho, &patterns);
            if (cache_valid) memcpy(cached, next_values, sizeof cached);
        }

        /* --- episode bookkeeping (SPEC section 4) --- */
        episode_collisions += collided;
        episode_greedy += collided && !exploratory;
        episode_return = episode_return + task_reward;
        if (terminated || truncated) {
            end_episode(b, i, episode_step, &run, &episode, &episode_collisions, &episode_greedy,
                        &episode_return, q, (size_t)num_states * NUM_ACTIONS, grid, obstacle_pads,
                        moving, world_key, &scatters);
            completed++;
            /* grid_world.reset_worlds: the agent to the start, no bump */
            cell = 0;
            pos = pad_of_cell[0];
            episode_step = 0;
            last_bump = -1;
            until_scatter = period;
            cache_valid = 0;
            prox = SENSE();
        } else {
            prox = next_prox;
        }
    }

#undef SENSE
    if (algorithm == ALG_FACTOR_Q) {
        memcpy(b->rho + i * b->rho_stride, rho, sizeof rho);
        memcpy(b->kappa + i * b->kappa_stride, kappa, sizeof kappa);
    }
    b->cell[i] = cell;
    b->episode_step[i] = episode_step;
    b->scatters[i] = scatters;
    b->policy_counter[i] = (int64_t)counter;
    b->run[i] = run;
    b->episode[i] = episode;
    b->episode_collisions[i] = episode_collisions;
    b->episode_greedy_collisions[i] = episode_greedy;
    b->episode_task_return[i] = episode_return;
    if (last_bump != -2) {
        for (int a = 0; a < NUM_ACTIONS; a++) bump[a] = a == last_bump;
    }
    return completed;
}

/*
 * Put experiments [0, S) at the start of their first episode: walls around every grid, the
 * static layout or a first scatter, the agent on the start. Expects zeroed tables and counters.
 */
void fq_start(const fq_batch *b) {
    const int64_t size = b->size, width = size + 2, num_cells = size * size;
    const int64_t padded = width * width, num_obstacles = b->num_obstacles;
    for (int64_t i = 0; i < b->num_experiments; i++) {
        uint8_t *grid = b->grid + i * b->grid_stride;
        const int64_t period = b->periods[i];
        if (period == 0) {
            memcpy(grid, b->static_grid, (size_t)padded);
        } else {
            memset(grid, 1, (size_t)padded);
            for (int64_t c = 0; c < num_cells; c++) grid[b->pad_of_cell[c]] = 0;
            if (num_obstacles > 0) {
                int32_t *obstacle_pads = b->obstacle_pads + i * b->obstacle_stride;
                for (int64_t k = 0; k < num_obstacles; k++) obstacle_pads[k] = b->pad_of_cell[0];
                scatter(grid, obstacle_pads, b->pad_of_cell, num_cells, num_obstacles,
                        (uint64_t)b->world_keys[i], (uint64_t)b->scatters[i], 0);
                b->scatters[i] += 1;
            }
        }
        b->cell[i] = 0;
        b->episode_step[i] = 0;
        if (b->generic) {
            b->heading[i] = 0;
            b->ticks[i] += 1; /* the first reset is the first observation */
        }
    }
}

/* One specialised loop per algorithm (the algorithm is a compile-time constant inside). */
static int64_t run_random_walk(const fq_batch *b, int64_t i, int64_t budget) {
    return run_experiment(b, i, budget, ALG_RANDOM_WALK);
}
static int64_t run_q_learning(const fq_batch *b, int64_t i, int64_t budget) {
    return run_experiment(b, i, budget, ALG_Q_LEARNING);
}
static int64_t run_factor_q(const fq_batch *b, int64_t i, int64_t budget) {
    return run_experiment(b, i, budget, ALG_FACTOR_Q);
}


/* ----------------------------------------------------------------------------------------------
 * The generic loop: any body and sensor layout of envs/body.py, with distractors, a permutation
 * and noise. The same equations and float order as the paper's loop above, without
 * its caches: observations are bit masks of the K sensors in the agent's order (K <= 62).
 */

/* rng.substream_key: mix64(key + substream * MIX1). */
static inline uint64_t substream_key(uint64_t key, uint64_t substream) {
    uint64_t z = key + substream * MIX1;
    z = (z ^ (z >> 30)) * MIX1;
    z = (z ^ (z >> 27)) * MIX2;
    return z ^ (z >> 31);
}
#define SUBSTREAM_DISTRACTOR 1
#define SUBSTREAM_SENSOR_NOISE 2
#define SUBSTREAM_ACTUATOR_NOISE 3

/* world.observe: layout sensors at the heading, distractor coins, noise flips, permutation. */
static uint64_t observe(const fq_batch *b, const uint8_t *grid, int64_t pos, int64_t heading,
                        uint64_t tick, uint64_t distractor_key, uint64_t noise_key) {
    const int64_t layout = b->num_layout, count = b->num_sensors, distractors = count - layout;
    const int64_t *offsets = b->offsets + heading * layout;
    uint64_t raw = 0; /* layout order, distractors last */
    for (int64_t k = 0; k < layout; k++) raw |= (uint64_t)grid[pos + offsets[k]] << k;
    for (int64_t d = 0; d < distractors; d++)
        raw |= (random_bits(distractor_key, tick * (uint64_t)distractors + (uint64_t)d) >> 31)
               << (layout + d);
    const uint64_t threshold = (uint64_t)b->sensor_noise_threshold;
    if (threshold > 0)
        for (int64_t k = 0; k < count; k++)
            raw ^= (uint64_t)(random_bits(noise_key, tick * (uint64_t)count + (uint64_t)k) <
                              threshold)
                   << k;
    uint64_t readings = 0;
    for (int64_t j = 0; j < count; j++) readings |= ((raw >> b->permutation[j]) & 1u) << j;
    return readings;
}

/* functional.local_patterns for one actuator: sum of parent_weights[a, k] over the set bits. */
static inline int64_t local_pattern(const fq_batch *b, int64_t actuator, uint64_t readings) {
    const int64_t *weights = b->parent_weights + actuator * b->num_sensors;
    int64_t pattern = 0;
    for (int64_t k = 0; k < b->num_sensors; k++)
        if ((readings >> k) & 1u) pattern += weights[k];
    return pattern;
}

/* functional.project_local: rho(o)_a = rho_a[o_D(a)]. */
static inline void project_local_body(const fq_batch *b, const float *rho, uint64_t readings,
                                      float *local) {
    for (int64_t a = 0; a < b->num_actuators; a++)
        local[a] = rho[a * b->table_width + local_pattern(b, a, readings)];
}

/* Eq. 3 (functional.normaliser) for A actions: the halves of local_spread / normaliser. */
static inline float local_spread_n(const float *rho, int64_t n) {
    int64_t a_check = 0;
    for (int64_t a = 1; a < n; a++)
        if (rho[a] < rho[a_check]) a_check = a;
    float rho_sum = 0.0f;
    for (int64_t a = 0; a < n; a++)
        if (a != a_check) rho_sum = rho_sum + rho[a];
    return rho_sum / (float)(n - 1) - rho[a_check];
}

static inline float normaliser_n(const float *q, float spread, int64_t n, float eta_factor,
                                 float g_min) {
    if (!(spread > 0.0f)) return g_min;
    int64_t a_hat = 0;
    for (int64_t a = 1; a < n; a++)
        if (q[a] > q[a_hat]) a_hat = a;
    float q_sum = 0.0f;
    for (int64_t a = 0; a < n; a++)
        if (a != a_hat) q_sum = q_sum + q[a];
    const float x = q[a_hat] - q_sum / (float)(n - 1);
    const float g = x / spread * eta_factor;
    return g >= g_min ? (g > FLT_MAX ? FLT_MAX : g) : g_min;
}

/* Eq. 2-3 (functional.combined_values with functional.normaliser) for A actions. */
static inline void combined_values_n(const float *q, const float *local, int64_t n,
                                     float eta_factor, float g_min, float *out) {
    const float g = normaliser_n(q, local_spread_n(local, n), n, eta_factor, g_min);
    for (int64_t a = 0; a < n; a++) {
        const float c = q[a] + g * local[a];
        out[a] = c > FLT_MAX ? FLT_MAX : (c < -FLT_MAX ? -FLT_MAX : c);
    }
}

static inline float max_n(const float *values, int64_t n) {
    float best = values[0];
    for (int64_t a = 1; a < n; a++) best = values[a] > best ? values[a] : best;
    return best;
}

/* functional.greedy_action_from_bits for A actions (tie draw only when there is a tie). */
static inline int64_t greedy_action_n(const float *values, int64_t n, uint64_t key,
                                      uint64_t counter) {
    const float best = max_n(values, n);
    uint64_t is_max = 0;
    for (int64_t a = 0; a < n; a++) is_max |= (uint64_t)(values[a] == best) << a;
    is_max |= is_max == 0;
    if ((is_max & (is_max - 1)) == 0) return __builtin_ctzll(is_max);
    const uint64_t count = (uint64_t)__builtin_popcountll(is_max);
    uint64_t k = (random_bits(key, counter * POLICY_DRAWS + DRAW_TIE) * count) >> 32;
    for (; k > 0; k--) is_max &= is_max - 1;
    return __builtin_ctzll(is_max);
}

/* functional.significant_local in place: rho_a where |rho_a| > threshold, else +0.0. */
static inline void significant_local_n(float *local, int64_t n, float threshold) {
    for (int64_t a = 0; a < n; a++)
        if (!(fabsf(local[a]) > threshold)) local[a] = 0.0f;
}

/* functional.safe_exploration_from_bits over functional.risk_mask(rho, threshold): the k-th
   actuator with rho_a >= -threshold, k = bits * n >> 32 (every actuator where none is). */
static inline int64_t safe_exploration_n(const float *local, int64_t n, float threshold,
                                         uint64_t bits) {
    const float limit = -threshold;
    int64_t allowed = 0;
    for (int64_t a = 0; a < n; a++) allowed += local[a] >= limit;
    const int all = allowed == 0;
    if (all) allowed = n;
    int64_t k = (int64_t)((bits * (uint64_t)allowed) >> 32);
    for (int64_t a = 0; a < n; a++)
        if (all || local[a] >= limit) {
            if (k == 0) return a;
            k--;
        }
    return n - 1; /* not reached */
}

/* ----------------------------------------------------------------------------------------------
 * The structure learner (factorq_torch/structure.py StructureLearner, with the math of
 * factorq_torch/functional.py): per actuator, counts of every candidate parent set and pattern,
 * Beta-Bernoulli log marginals (lgamma looked up in torch's tables: the counts are integers and
 * the priors dyadic, so every argument is one of the tables' exact doubles), commitment at the
 * Bayes factor, the change-point test on the block. The same float64 operations in the same
 * order as the torch module; tests/test_fast_structure.py checks equality bit for bit.
 */

/* The 8 arrays of one experiment's counts block, in this order, interleaved per candidate:
   [A, C, 8, P] (one candidate's counts, sums and marginals, all and the block's, in 8 P adjacent
   doubles: a firing touches 4 cache lines per candidate, not 8 scattered ones). array[k][h + p]
   is array k at pattern p of the candidate whose block starts at h = (a C + c) W, W = 8 P. */
enum { L_COUNT, L_SUCC, L_RSUM, L_LM, L_BCOUNT, L_BSUCC, L_BRSUM, L_BLM, L_ARRAYS };

typedef struct {
    double *array[L_ARRAYS];
    int64_t C, P, A, W;
} learner_view;

static inline learner_view learner_of(const fq_batch *b, int64_t i) {
    learner_view v;
    for (int k = 0; k < L_ARRAYS; k++)
        v.array[k] = b->counts + i * b->learner_stride + k * b->learner_patterns;
    v.C = b->num_candidates;
    v.P = b->learner_patterns;
    v.W = L_ARRAYS * v.P;
    v.A = b->num_actuators;
    return v;
}

/* functional.beta_bernoulli_log_marginal for integral n, s (exact table indices). */
static inline double bb_log_marginal(const fq_batch *b, double n, double s) {
    const double *t = b->lgamma_table;
    const int64_t M = b->lgamma_length, ni = (int64_t)n, si = (int64_t)s;
    return ((t[si] + t[M + (ni - si)]) - t[2 * M + ni]) - b->log_beta_prior;
}

/* StructureLearner._pattern_log_marginal for integral n, s: Beta-Bernoulli, or
   functional.mixture_log_marginal (the more probable of the clean and the noisy level). */
static inline double pattern_log_marginal(const fq_batch *b, double n, double s) {
    const double clean = bb_log_marginal(b, n, s);
    if (!b->mixture) return clean;
    if (!(n > 0)) return 0.0;
    const double *t = b->noisy_lgamma_table;
    const int64_t M = b->lgamma_length, ni = (int64_t)n, si = (int64_t)s;
    const double noisy =
        (((t[si] + t[M + (ni - si)]) - t[2 * M + ni]) - b->log_noisy_beta_prior) +
        b->log_noisy_weight;
    const double weighted = clean - b->log_mixture_total;
    return weighted >= noisy ? weighted : noisy; /* torch.maximum (no NaN here) */
}

/* The pattern of candidate c's sensors in readings (structure.patterns). */
static inline int64_t candidate_pattern(const fq_batch *b, int64_t c, uint64_t readings) {
    const int64_t j = b->candidate_sensors[2 * c], k = b->candidate_sensors[2 * c + 1];
    int64_t pattern = 0;
    if (j >= 0) pattern += (int64_t)((readings >> j) & 1u);
    if (k >= 0) pattern += (int64_t)((readings >> k) & 1u) << 1;
    return pattern;
}

/* functional.log_posterior_of for one candidate: log_prior + (((m_0 + m_1) + m_2) + m_3). */
static inline double candidate_sum(const double *lm, int64_t P) {
    double total = lm[0];
    for (int64_t p = 1; p < P; p++) total = total + lm[p];
    return total;
}

/* functional.LOG_TWO (math.log(2.0): the double nearest ln 2, as this literal). */
#define FQ_LOG_TWO 0.69314718055994530942

/* functional.flip_log_marginal for one candidate's P patterns (count - minus_count, succ -
   minus_succ where minus_count is given): log B(a + m, b + n - m) - log B(a, b) - v log 2 with
   m the patterns' minority outcomes, n their firings, v the visited patterns (sums left to right;
   integral, hence exact). */
static inline double flip_log_marginal(const fq_batch *b, const double *count, const double *succ,
                                       const double *minus_count, const double *minus_succ,
                                       int64_t P) {
    double m = 0.0, n = 0.0, labels = 0.0;
    for (int64_t p = 0; p < P; p++) {
        const double np = minus_count ? count[p] - minus_count[p] : count[p];
        const double sp = minus_count ? succ[p] - minus_succ[p] : succ[p];
        const double other = np - sp;
        const double d = sp < other ? sp : other; /* torch.minimum(s, n - s) */
        m = p == 0 ? d : m + d;
        n = p == 0 ? np : n + np;
        labels = p == 0 ? (double)(np > 0) : labels + (double)(np > 0);
    }
    return bb_log_marginal(b, n, m) - labels * FQ_LOG_TWO;
}

/* The log marginal of the candidate whose patterns start at h in the counts block (all counts,
   or the block's): the sum of its patterns' Beta-Bernoulli log marginals (functional.
   log_posterior_of's, "pattern") or functional.flip_log_marginal ("flip"). */
static inline double candidate_log_marginal(const fq_batch *b, const learner_view *v, int64_t h,
                                            int block) {
    if (!b->likelihood_flip) return candidate_sum(v->array[block ? L_BLM : L_LM] + h, v->P);
    return flip_log_marginal(b, v->array[block ? L_BCOUNT : L_COUNT] + h,
                             v->array[block ? L_BSUCC : L_SUCC] + h, NULL, NULL, v->P);
}

/* First index of the maximum (torch.argmax). */
static inline int64_t argmax_d(const double *x, int64_t n) {
    int64_t best = 0;
    for (int64_t c = 1; c < n; c++)
        if (x[c] > x[best]) best = c;
    return best;
}

/* The candidates actuator a of experiment i counts, in increasing order: the active ones with
   pair pruning (active_list), else all (all_candidates); *count their number. Every loop over the
   candidates below runs over this list: with pruning a firing costs O(K + active pairs), not
   O(C), and the first maximum in index order is still torch.argmax's. */
static inline const int16_t *learner_list(const fq_batch *b, int64_t i, int64_t a,
                                          int64_t *count) {
    if (!b->prune_pairs) {
        *count = b->num_candidates;
        return b->all_candidates;
    }
    *count = b->active_count[i * b->num_actuators + a];
    return b->active_list + (i * b->num_actuators + a) * b->num_candidates;
}

/* active_list and active_count of actuator a from its active flags (after they changed). */
static void learner_relist(const fq_batch *b, int64_t i, int64_t a) {
    const int64_t C = b->num_candidates, row = i * b->num_actuators + a;
    const uint8_t *active = b->active + row * C;
    int16_t *list = b->active_list + row * C;
    int64_t n = 0;
    for (int64_t c = 0; c < C; c++)
        if (active[c]) list[n++] = (int16_t)c;
    b->active_count[row] = n;
}

/* StructureLearner.local_values for one experiment: local[a] for every actuator. */
static void learner_predict(const fq_batch *b, int64_t i, uint64_t readings, float *local) {
    const learner_view v = learner_of(b, i);
    const int64_t *committed = b->committed + i * v.A, *map = b->map_cache + i * v.A;
    for (int64_t a = 0; a < v.A; a++) {
        int64_t c = committed[a];
        if (c < 0 && b->prediction == 2) { /* optimistic: the largest plausible mean */
            const uint8_t *plausible = b->plausible + (i * v.A + a) * v.C;
            double best = -INFINITY;
            int64_t listed;
            const int16_t *list = learner_list(b, i, a, &listed); /* plausible ones are active */
            for (int64_t m = 0; m < listed; m++) {
                const int64_t d = list[m];
                if (!plausible[d]) continue;
                const int64_t e = (a * v.C + d) * v.W + candidate_pattern(b, d, readings);
                const double n = v.array[L_COUNT][e];
                const double mean = n > 0 ? v.array[L_RSUM][e] / n : 0.0;
                if (mean > best) best = mean;
            }
            local[a] = (float)best;
            continue;
        }
        if (c < 0) {
            if (b->prediction != 0) {
                local[a] = 0.0f;
                continue;
            }
            c = map[a];
        }
        const int64_t e = (a * v.C + c) * v.W + candidate_pattern(b, c, readings);
        const double n = v.array[L_COUNT][e];
        local[a] = n > 0 ? (float)(v.array[L_RSUM][e] / n) : 0.0f;
    }
}

/* StructureLearner._refresh_cache for actuator a: the MAP candidate and the plausible ones, from
   lp (read at the listed candidates) when given, else from the counts (and every flag rewritten:
   after a reopening the active set is new). An inactive candidate (-inf) is never plausible;
   learner_enter clears the flag of a pair that leaves. */
static void learner_refresh(const fq_batch *b, int64_t i, int64_t a, double *lp, int have_lp) {
    const learner_view v = learner_of(b, i);
    const int64_t C = v.C, W = v.W, base = a * C * W;
    int64_t listed;
    const int16_t *list = learner_list(b, i, a, &listed);
    uint8_t *plausible = b->plausible + (i * v.A + a) * C;
    if (!have_lp) {
        for (int64_t m = 0; m < listed; m++)
            lp[list[m]] =
                b->log_prior[list[m]] + candidate_log_marginal(b, &v, base + list[m] * W, 0);
        memset(plausible, 0, (size_t)C);
    }
    int64_t map = list[0];
    for (int64_t m = 1; m < listed; m++)
        if (lp[list[m]] > lp[map]) map = list[m];
    b->map_cache[i * v.A + a] = map;
    const double floor = lp[map] - b->log_bayes_factor;
    for (int64_t m = 0; m < listed; m++) plausible[list[m]] = lp[list[m]] >= floor;
}

/* Forget everything actuator a of experiment i has counted (a reopening). */
static void learner_forget(const fq_batch *b, int64_t i, int64_t a) {
    const learner_view v = learner_of(b, i);
    memset(v.array[0] + a * v.C * v.W, 0, (size_t)(v.C * v.W) * 8); /* all 8 arrays */
    b->committed[i * v.A + a] = -1;
    b->block_samples[i * v.A + a] = 0;
    if (b->prune_pairs) { /* the history restarts after this firing, as the counts do */
        memcpy(b->active + (i * v.A + a) * v.C, b->initial_active, (size_t)v.C);
        learner_relist(b, i, a);
        b->history_start[i * v.A + a] = b->history_length[i];
        b->block_start[i * v.A + a] = b->history_length[i];
    }
}

/* Candidate index of the pair (j, k), j < k, in functional.candidate_sets' order. */
static inline int64_t pair_index(int64_t K, int64_t j, int64_t k) {
    return 1 + K + j * (2 * K - j - 1) / 2 + (k - j - 1);
}

/* functional.has_minority for the P patterns of one candidate (its all-counts at h). */
static inline int has_minority(const learner_view *v, int64_t h) {
    for (int64_t p = 0; p < v->P; p++) {
        const double n = v->array[L_COUNT][h + p], s = v->array[L_SUCC][h + p];
        const double other = n - s;
        if ((s < other ? s : other) > 0.0) return 1;
    }
    return 0;
}

/* functional.single_explains: "no sensor" or a single (candidates 0..K) without a minority
   outcome, for the actuator whose counts start at base. */
static inline int single_explains(const learner_view *v, int64_t base, int64_t K) {
    for (int64_t c = 0; c <= K; c++)
        if (!has_minority(v, base + c * v->W)) return 1;
    return 0;
}

/* StructureLearner._enter (pairs "pruned"): functional.pair_activity on lp (the active
   candidates' log posterior), then the counts of every entering pair rebuilt from the actuator's
   firings since history_start (functional.rebuild_pair_counts: in firing order, so the sums are
   the ones counting every firing would have left) and its lp. While "no sensor" or a single
   explains every firing (single_explains) only a committed pair stays; otherwise a pair leaves
   when neither it nor its singles are plausible and it is not committed, and it enters when one
   of its singles is plausible (an inactive pair has no log posterior: never plausible itself). */
static void learner_enter(const fq_batch *b, int64_t i, int64_t a, double *lp) {
    const learner_view v = learner_of(b, i);
    const int64_t C = v.C, P = v.P, W = v.W, K = b->num_sensors, base = a * C * W;
    const int64_t L = b->history_capacity, row = i * v.A + a;
    uint8_t *active = b->active + row * C;
    uint8_t *plausible = b->plausible + row * C;
    int64_t listed;
    const int16_t *list = learner_list(b, i, a, &listed);
    double best = lp[list[0]];
    for (int64_t m = 1; m < listed; m++)
        if (lp[list[m]] > best) best = lp[list[m]];
    const double floor = best - b->log_bayes_factor;
    const int64_t held = b->committed[row];
    const int explained = single_explains(&v, base, K);
    int changed = 0;
    for (int64_t m = 1 + K; m < listed; m++) { /* the active pairs: stay or leave */
        const int64_t c = list[m];
        const int64_t j = b->candidate_sensors[2 * c], k = b->candidate_sensors[2 * c + 1];
        if (!explained && (lp[c] >= floor || lp[1 + j] >= floor || lp[1 + k] >= floor)) continue;
        if (c == held) continue;
        active[c] = 0;
        plausible[c] = 0;
        changed = 1;
    }
    int64_t entering[LEARNER_SCRATCH], count = 0;
    for (int64_t j = 0; j < K; j++) { /* the pairs of a plausible single: enter */
        if (explained || !(lp[1 + j] >= floor)) continue;
        for (int64_t k = 0; k < K; k++) {
            if (k == j) continue;
            const int64_t c = k < j ? pair_index(K, k, j) : pair_index(K, j, k);
            if (active[c]) continue;
            active[c] = 1;
            entering[count++] = c;
        }
    }
    if (changed || count > 0) learner_relist(b, i, a);
    if (count == 0) return;
    for (int64_t m = 0; m < count; m++) memset(v.array[0] + base + entering[m] * W, 0, (size_t)W * 8);
    const int64_t start = b->history_start[row], length = b->history_length[i];
    const int64_t block_start = b->block_start[row];
    const int64_t *readings = b->history_readings + i * L;
    const uint8_t *actions = b->history_action + i * L;
    const float *rewards = b->history_reward + i * L;
    for (int64_t t = start; t < length; t++) {
        if (actions[t] != a) continue;
        const double reward = (double)rewards[t];
        const double negated = -reward;
        const double success = negated < 0.0 ? 0.0 : (negated > 1.0 ? 1.0 : negated);
        const int blocks = t >= block_start ? 2 : 1;
        for (int64_t m = 0; m < count; m++) {
            const int64_t e =
                base + entering[m] * W + candidate_pattern(b, entering[m], (uint64_t)readings[t]);
            for (int block = 0; block < blocks; block++) {
                double *n = v.array[block ? L_BCOUNT : L_COUNT];
                double *succ = v.array[block ? L_BSUCC : L_SUCC];
                double *rsum = v.array[block ? L_BRSUM : L_RSUM];
                n[e] = n[e] + 1.0;
                succ[e] = succ[e] + success;
                rsum[e] = rsum[e] + reward;
            }
        }
    }
    for (int64_t m = 0; m < count; m++) {
        const int64_t h = base + entering[m] * W;
        for (int block = 0; block < 2; block++) {
            const double *n = v.array[block ? L_BCOUNT : L_COUNT] + h;
            const double *succ = v.array[block ? L_BSUCC : L_SUCC] + h;
            double *lm = v.array[block ? L_BLM : L_LM] + h;
            for (int64_t p = 0; p < P; p++)
                lm[p] = n[p] > 0 ? pattern_log_marginal(b, n[p], succ[p]) : 0.0;
        }
        lp[entering[m]] = b->log_prior[entering[m]] + candidate_log_marginal(b, &v, h, 0);
    }
}

/* StructureLearner.update_running_mean for one firing, then _decide and _refresh_cache. */
static void learner_update(const fq_batch *b, int64_t i, uint64_t readings, int64_t a,
                           float local_reward, double *scratch) {
    const learner_view v = learner_of(b, i);
    const int64_t C = v.C, P = v.P, W = v.W;
    const double reward = (double)local_reward;
    const double negated = -reward;
    const double success = negated < 0.0 ? 0.0 : (negated > 1.0 ? 1.0 : negated);
    int64_t listed;
    const int16_t *list = learner_list(b, i, a, &listed); /* an inactive pair is not counted */
    for (int64_t m = 0; m < listed; m++) {
        const int64_t c = list[m];
        const int64_t e = (a * C + c) * W + candidate_pattern(b, c, readings);
        for (int block = 0; block < 2; block++) {
            double *count = v.array[block ? L_BCOUNT : L_COUNT];
            double *succ = v.array[block ? L_BSUCC : L_SUCC];
            double *rsum = v.array[block ? L_BRSUM : L_RSUM];
            double *lm = v.array[block ? L_BLM : L_LM];
            const double n = count[e] + 1.0, s = succ[e] + success;
            count[e] = n;
            succ[e] = s;
            rsum[e] = rsum[e] + reward;
            lm[e] = pattern_log_marginal(b, n, s);
        }
    }
    int64_t *committed = b->committed + i * v.A + a;
    int64_t *block_samples = b->block_samples + i * v.A + a;
    b->samples[i * v.A + a] += 1;
    *block_samples += 1;
    /* _decide, over the listed candidates (lp is read nowhere else) */
    const int64_t base = a * C * W;
    double *lp = scratch; /* [C] */
    for (int64_t m = 0; m < listed; m++)
        lp[list[m]] = b->log_prior[list[m]] + candidate_log_marginal(b, &v, base + list[m] * W, 0);
    if (b->prune_pairs) {
        const int64_t t = b->history_length[i]++;
        b->history_readings[i * b->history_capacity + t] = (int64_t)readings;
        b->history_action[i * b->history_capacity + t] = (uint8_t)a;
        b->history_reward[i * b->history_capacity + t] = local_reward;
        learner_enter(b, i, a, lp);
        list = learner_list(b, i, a, &listed);
    }
    int64_t best = list[0];
    for (int64_t m = 1; m < listed; m++)
        if (lp[list[m]] > lp[best]) best = list[m];
    double rival_max = -INFINITY;
    const uint8_t *rivals = b->competitors + best * C;
    for (int64_t m = 0; m < listed; m++)
        if (rivals[list[m]] && lp[list[m]] > rival_max) rival_max = lp[list[m]];
    const double margin = lp[best] - rival_max;
    const int64_t held = *committed;
    const int commit = held < 0 && margin >= b->log_bayes_factor;
    int reopen = 0;
    if (held >= 0) {
        const int64_t h = base + held * W;
        double lead;
        if (b->likelihood_flip) { /* the whole candidate's ratio: it does not split over patterns */
            const double all = candidate_log_marginal(b, &v, h, 0);
            const double earlier =
                flip_log_marginal(b, v.array[L_COUNT] + h, v.array[L_SUCC] + h,
                                  v.array[L_BCOUNT] + h, v.array[L_BSUCC] + h, P);
            lead = b->log_prior[held] + (all - earlier);
        } else {
            double predicted = 0.0;
            for (int64_t p = 0; p < P; p++) {
                const double earlier = pattern_log_marginal(
                    b, v.array[L_COUNT][h + p] - v.array[L_BCOUNT][h + p],
                    v.array[L_SUCC][h + p] - v.array[L_BSUCC][h + p]);
                const double term = v.array[L_LM][h + p] - earlier;
                predicted = p == 0 ? term : predicted + term;
            }
            lead = b->log_prior[held] + (0.0 + predicted);
        }
        double rival = -INFINITY;
        for (int64_t m = 0; m < listed; m++) {
            const int64_t c = list[m];
            const double x = b->log_prior[c] + candidate_log_marginal(b, &v, base + c * W, 1);
            if (x > rival) rival = x;
        }
        const double threshold =
            b->noise_seen[i] ? b->log_noisy_reopen_factor : b->log_reopen_factor;
        reopen = rival - lead >= threshold;
    }
    if (commit) {
        *committed = best;
        /* functional.has_minority: an outcome against its pattern's majority in the data the
           commitment rests on refutes clean sensors (a clean pairing is deterministic) */
        if (has_minority(&v, base + best * W)) b->noise_seen[i] = 1;
    }
    if (reopen) {
        learner_forget(b, i, a);
        b->reopened[i * v.A + a] += 1;
        if (b->reopen_body)
            for (int64_t other = 0; other < v.A; other++)
                if (other != a) {
                    learner_forget(b, i, other);
                    learner_refresh(b, i, other, lp, 0);
                }
    }
    if (*block_samples >= b->window) {
        for (int64_t c = 0; c < C; c++) /* the block's 4 arrays: adjacent in each candidate */
            memset(v.array[L_BCOUNT] + base + c * W, 0, (size_t)(L_ARRAYS - L_BCOUNT) * P * 8);
        *block_samples = 0;
        if (b->prune_pairs) b->block_start[i * v.A + a] = b->history_length[i];
    }
    /* _refresh_cache: the MAP candidate of the (possibly forgotten) counts */
    learner_refresh(b, i, a, lp, !reopen);
}

/* trainers/experiments/dependencies.py's bookkeeping after a step: who is right, since when, wrong
   commitments (of the fired actuator, whose commitment changed from before), the curve. */
static void learner_track(const fq_batch *b, int64_t i, int64_t fired, int64_t before,
                          uint64_t steps) {
    const int64_t A = b->num_actuators;
    const int64_t *truth = b->truth + (i * 2 + (b->change_tick[i] >= 0)) * A;
    const int64_t *committed = b->committed + i * A, *samples = b->samples + i * A;
    int64_t *since = b->right_since + i * A;
    int all_right = 1;
    for (int64_t a = 0; a < A; a++) {
        const int64_t effective = committed[a] < 0 ? 0 : committed[a];
        const int right = effective == truth[a];
        since[a] = right ? (since[a] < 0 ? samples[a] : since[a]) : -1;
        all_right &= right;
        if (a == fired && committed[a] >= 0 && committed[a] != before && !right)
            b->wrong_commitments[i] += 1;
    }
    if (b->curve_every > 0 && steps % (uint64_t)b->curve_every == 0) {
        const uint64_t point = steps / (uint64_t)b->curve_every;
        if (point < (uint64_t)b->curve_length) b->curve[i * b->curve_length + point] = all_right;
    }
}

/* world.observe, then the agent's order (envs.permutation.PermuteSensors) when there is one:
   the order after the change from the first observation after change_tick on. */
static inline uint64_t agent_readings(const fq_batch *b, int64_t i, uint64_t raw, uint64_t tick) {
    if (b->orders == NULL) return raw;
    const int64_t K = b->num_sensors;
    const int64_t change = b->change_tick[i];
    const int64_t *order = (change >= 0 && tick > (uint64_t)change ? b->orders_after : b->orders) +
                           i * K;
    uint64_t readings = 0;
    for (int64_t j = 0; j < K; j++) readings |= ((raw >> order[j]) & 1u) << j;
    return readings;
}

/* Run experiment i of any body for up to budget steps; returns the episodes it completed. */
static inline int64_t run_experiment_body(const fq_batch *b, int64_t i, int64_t budget,
                                          const int algorithm) {
    const int64_t size = b->size, width = size + 2, num_cells = size * size;
    const int64_t goal = num_cells - 1, num_obstacles = b->num_obstacles;
    const int64_t max_steps = b->max_steps;
    const int64_t runs = b->runs;
    const int64_t period = b->periods[i];
    const int moving = period > 0 && num_obstacles > 0;
    const int64_t A = b->num_actuators, K = b->num_sensors, H = b->num_headings;
    const int64_t P = b->table_width;
    const uint64_t world_key = (uint64_t)b->world_keys[i];
    const uint64_t policy_key = (uint64_t)b->policy_keys[i];
    const uint64_t distractor_key = substream_key(world_key, SUBSTREAM_DISTRACTOR);
    const uint64_t noise_key = substream_key(world_key, SUBSTREAM_SENSOR_NOISE);
    const uint64_t actuator_key = substream_key(world_key, SUBSTREAM_ACTUATOR_NOISE);
    const uint64_t explore_threshold = (uint64_t)b->explore_threshold;
    const uint64_t slip_threshold = (uint64_t)b->actuator_noise_threshold;
    const int64_t num_states =
        algorithm == ALG_Q_LEARNING ? (num_cells * H) << K : num_cells * H;
    const float gamma = b->gamma, alpha = b->alpha, eta_factor = b->eta_factor, g_min = b->g_min;
    const int32_t *pad_of_cell = b->pad_of_cell;
    const int64_t move_pad[4] = {-width, -1, width, 1};
    const int64_t move_cell[4] = {-size, -1, size, 1};

    float *q = algorithm == ALG_RANDOM_WALK ? NULL : b->q + i * b->q_stride;
    float *rho = b->rho + i * b->rho_stride;
    int64_t *kappa = b->kappa + i * b->kappa_stride;
    uint8_t *grid = b->grid + i * b->grid_stride;
    int32_t *obstacle_pads = num_obstacles > 0 ? b->obstacle_pads + i * b->obstacle_stride : NULL;
    uint8_t *bump = b->bump + i * A;

    int64_t cell = b->cell[i], pos = pad_of_cell[cell], heading = b->heading[i];
    int64_t episode_step = b->episode_step[i], scatters = b->scatters[i];
    uint64_t tick = (uint64_t)b->ticks[i];
    uint64_t counter = (uint64_t)b->policy_counter[i];
    int64_t run = b->run[i], episode = b->episode[i];
    int64_t episode_collisions = b->episode_collisions[i];
    int64_t episode_greedy = b->episode_greedy_collisions[i];
    float episode_return = b->episode_task_return[i];
    int64_t last_bump = -2, last_action = 0;
    int64_t completed = 0;
    const int learning = b->learner != 0 && algorithm == ALG_FACTOR_Q;
    double scratch[LEARNER_SCRATCH];
    uint64_t readings =
        agent_readings(b, i, observe(b, grid, pos, heading, tick, distractor_key, noise_key), tick);

    for (; budget > 0 && run < runs; budget--) {
        /* --- act --- */
        const int64_t position = cell * H + heading;
        const int64_t state =
            algorithm == ALG_Q_LEARNING ? (position << K) + (int64_t)readings : position;
        float values[MAX_ACTUATORS], local[MAX_ACTUATORS], raw_local[MAX_ACTUATORS];
        int64_t action;
        int exploratory;
        if (algorithm == ALG_RANDOM_WALK) {
            action = (int64_t)((random_bits(policy_key, counter * POLICY_DRAWS + DRAW_ACTION) *
                                (uint64_t)A) >> 32);
            exploratory = 1;
        } else {
            if (algorithm == ALG_Q_LEARNING) {
                memcpy(values, q + state * A, (size_t)A * sizeof(float));
            } else {
                if (learning)
                    learner_predict(b, i, readings, local);
                else
                    project_local_body(b, rho, readings, local);
                if (b->risk_explore) memcpy(raw_local, local, (size_t)A * sizeof(float));
                if (b->risk_gate) significant_local_n(local, A, b->risk_threshold);
                combined_values_n(q + state * A, local, A, eta_factor, g_min, values);
            }
            exploratory =
                random_bits(policy_key, counter * POLICY_DRAWS + DRAW_EXPLORE) < explore_threshold;
            if (exploratory && algorithm == ALG_FACTOR_Q && b->risk_explore)
                action = safe_exploration_n(
                    raw_local, A, b->risk_threshold,
                    random_bits(policy_key, counter * POLICY_DRAWS + DRAW_ACTION));
            else if (exploratory)
                action = (int64_t)((random_bits(policy_key, counter * POLICY_DRAWS + DRAW_ACTION) *
                                    (uint64_t)A) >> 32);
            else
                action = greedy_action_n(values, A, policy_key, counter);
        }
        counter++;

        /* --- world step (grid_world.step_worlds): actuator noise, move or collide, turn --- */
        int64_t fired = action;
        if (slip_threshold > 0 &&
            random_bits(actuator_key, 2 * tick) < slip_threshold) {
            const int64_t other =
                (int64_t)((random_bits(actuator_key, 2 * tick + 1) * (uint64_t)(A - 1)) >> 32);
            fired = (action + 1 + other) % A;
        }
        int64_t learner_before = -1;
        const int64_t move = b->moves[fired];
        int collided = 0;
        if (move >= 0) {
            const int64_t direction = (move + heading) % 4;
            collided = grid[pos + move_pad[direction]];
            if (!collided) {
                pos += move_pad[direction];
                cell += move_cell[direction];
            }
        }
        heading = (heading + b->turns[fired]) % 4;
        last_bump = collided ? action : -1;
        last_action = action;
        episode_step++;
        const int terminated = cell == goal;
        const int truncated = !terminated && episode_step >= max_steps;
        const float task_reward = -1.0f + (float)terminated;
        const float local_reward = collided ? -1.0f : 0.0f; /* collision[action] */
        if (period > 0 && !terminated && episode_step % period == 0 && moving) {
            scatter(grid, obstacle_pads, pad_of_cell, num_cells, num_obstacles, world_key,
                    (uint64_t)scatters, cell);
            scatters++;
        }
        tick++;
        const uint64_t next_readings = agent_readings(
            b, i, observe(b, grid, pos, heading, tick, distractor_key, noise_key), tick);
        const int64_t next_position = cell * H + heading;

        /* --- learn --- */
        if (algorithm == ALG_Q_LEARNING) {
            const float reward = task_reward + local_reward;
            float *q_sa = q + state * A + action;
            float target = reward;
            const int64_t next_state = (next_position << K) + (int64_t)next_readings;
            if (!terminated) target = reward + gamma * max_n(q + next_state * A, A);
            *q_sa = *q_sa + alpha * (target - *q_sa);
        } else if (algorithm == ALG_FACTOR_Q) {
            float target = task_reward;
            if (!terminated) {
                float next_local[MAX_ACTUATORS], next_values[MAX_ACTUATORS];
                if (learning)
                    learner_predict(b, i, next_readings, next_local);
                else
                    project_local_body(b, rho, next_readings, next_local);
                if (b->risk_gate) significant_local_n(next_local, A, b->risk_threshold);
                combined_values_n(q + next_position * A, next_local, A, eta_factor, g_min,
                                  next_values);
                target = task_reward + gamma * max_n(next_values, A);
            }
            float *q_sa = q + state * A + action;
            *q_sa = *q_sa + alpha * (target - *q_sa);
            /* Eq. 5 for the chosen actuator at the pattern of its parents before acting. */
            if (learning) {
                learner_before = b->committed[i * A + action];
                learner_update(b, i, readings, action, local_reward, scratch);
            } else {
                const int64_t entry = action * P + local_pattern(b, action, readings);
                kappa[entry] += 1;
                rho[entry] = rho[entry] + (local_reward - rho[entry]) / (float)kappa[entry];
            }
        }

        /* --- episode bookkeeping (SPEC section 4) --- */
        episode_collisions += collided;
        episode_greedy += collided && !exploratory;
        episode_return = episode_return + task_reward;
        if (terminated || truncated) {
            end_episode(b, i, episode_step, &run, &episode, &episode_collisions, &episode_greedy,
                        &episode_return, q, (size_t)num_states * (size_t)A, grid, obstacle_pads,
                        moving, world_key, &scatters);
            completed++;
            /* grid_world.reset_worlds: start cell, heading north, a new observation */
            cell = 0;
            pos = pad_of_cell[0];
            heading = 0;
            episode_step = 0;
            last_bump = -1;
            tick++;
            readings = agent_readings(
                b, i, observe(b, grid, pos, heading, tick, distractor_key, noise_key), tick);
            /* the change (dependencies.py): from the observation after this reset on */
            if (b->orders != NULL && b->change_run > 0 && b->change_tick[i] < 0 &&
                run == b->change_run) {
                b->change_tick[i] = (int64_t)tick;
                if (learning)
                    for (int64_t a = 0; a < A; a++)
                        b->samples_at_change[i * A + a] = b->samples[i * A + a];
            }
        } else {
            readings = next_readings;
        }
        if (learning) learner_track(b, i, action, learner_before, counter);
    }
    (void)last_action;
    b->cell[i] = cell;
    b->heading[i] = heading;
    b->ticks[i] = (int64_t)tick;
    b->episode_step[i] = episode_step;
    b->scatters[i] = scatters;
    b->policy_counter[i] = (int64_t)counter;
    b->run[i] = run;
    b->episode[i] = episode;
    b->episode_collisions[i] = episode_collisions;
    b->episode_greedy_collisions[i] = episode_greedy;
    b->episode_task_return[i] = episode_return;
    if (last_bump != -2) {
        for (int64_t a = 0; a < A; a++) bump[a] = a == last_bump;
    }
    return completed;
}

static int64_t run_random_walk_body(const fq_batch *b, int64_t i, int64_t budget) {
    return run_experiment_body(b, i, budget, ALG_RANDOM_WALK);
}
static int64_t run_q_learning_body(const fq_batch *b, int64_t i, int64_t budget) {
    return run_experiment_body(b, i, budget, ALG_Q_LEARNING);
}
static int64_t run_factor_q_body(const fq_batch *b, int64_t i, int64_t budget) {
    return run_experiment_body(b, i, budget, ALG_FACTOR_Q);
}

/*
 * Advance every unfinished experiment by up to max_steps steps. Any number of threads may call
 * this at once with the same next_experiment counter (initially 0): each takes the next
 * experiment from it until none is left. Returns the episodes completed by this caller.
 */
/*
 * The state of experiment i as the loops index with it, checked on entry whatever its source (a
 * checkpoint is signed, not trusted): 0 when every index stays inside its buffer, else the code of
 * the first field out of range (loader.py's _STATE_FIELDS names them). Cheap: a few compares per
 * experiment per advance call, none in the step loop.
 */
int64_t fq_check_experiment(const fq_batch *b, int64_t i) {
    const int64_t num_cells = b->size * b->size, padded = (b->size + 2) * (b->size + 2);
    if (b->cell[i] < 0 || b->cell[i] >= num_cells) return 1;
    if (b->run[i] < 0 || b->run[i] > b->runs) return 2;
    if (b->episode[i] < 0 || b->episode[i] >= b->episodes) return 3;
    if (b->episode_step[i] < 0 || b->episode_step[i] >= b->max_steps) return 4;
    if (b->scatters[i] < 0) return 5;
    if (b->policy_counter[i] < 0) return 6;
    if (b->periods[i] < 0) return 7;
    for (int64_t k = 0; k < b->num_obstacles; k++) {
        const int32_t pad = b->obstacle_pads[i * b->obstacle_stride + k];
        if (pad < 0 || pad >= padded) return 8;
    }
    if (b->heading != NULL && (b->heading[i] < 0 || b->heading[i] >= b->num_headings)) return 9;
    if (b->ticks != NULL && b->ticks[i] < 0) return 10;
    if (b->algorithm == ALG_FACTOR_Q) {
        const int64_t entries = b->num_actuators * b->table_width;
        for (int64_t e = 0; e < entries; e++) {
            const int64_t kappa = b->kappa[i * b->kappa_stride + e];
            if (kappa < 0 || kappa > INT64_MAX / 2) return 11;
        }
    }
    if (b->episode_collisions[i] < 0 || b->episode_greedy_collisions[i] < 0) return 12;
    if (b->learner) {
        const int64_t A = b->num_actuators, C = b->num_candidates, M = b->lgamma_length;
        for (int64_t a = 0; a < A; a++) {
            const int64_t c = b->committed[i * A + a], map = b->map_cache[i * A + a];
            if (c < -1 || c >= C || map < 0 || map >= C) return 13;
            if (b->samples[i * A + a] < 0 || b->block_samples[i * A + a] < 0 ||
                b->block_samples[i * A + a] >= b->window)
                return 14;
        }
        const learner_view v = learner_of(b, i);
        const int64_t P = b->learner_patterns, entries = A * C * P;
        for (int64_t x = 0; x < entries; x++) /* candidate x / P, pattern x % P */
            for (int block = 0; block < 2; block++) {
                const int64_t e = (x / P) * v.W + x % P;
                const double n = v.array[block ? L_BCOUNT : L_COUNT][e];
                const double s = v.array[block ? L_BSUCC : L_SUCC][e];
                /* integral 0 <= s <= n, and n + 1 still inside the lgamma tables */
                if (!(n >= 0 && n + 1 < (double)M && s >= 0 && s <= n && n == (double)(int64_t)n &&
                      s == (double)(int64_t)s))
                    return 15;
            }
    }
    if (b->orders != NULL && b->change_tick[i] < -1) return 16;
    if (b->learner && b->prune_pairs) { /* the history an entering pair is rebuilt from */
        const int64_t A = b->num_actuators, C = b->num_candidates, L = b->history_capacity;
        const int64_t length = b->history_length[i];
        if (length < 0 || length > L) return 17;
        for (int64_t a = 0; a < A; a++) {
            const int64_t start = b->history_start[i * A + a], block = b->block_start[i * A + a];
            if (start < 0 || start > block || block > length) return 17;
            const uint8_t *active = b->active + (i * A + a) * C;
            for (int64_t c = 0; c < C; c++)
                if (active[c] > 1 || (b->candidate_sensors[2 * c + 1] < 0 && !active[c])) return 17;
            /* the list: the active candidates in increasing order, the committed one among them */
            const int16_t *list = b->active_list + (i * A + a) * C;
            const int64_t listed = b->active_count[i * A + a];
            int64_t flagged = 0;
            for (int64_t c = 0; c < C; c++) flagged += active[c];
            if (listed != flagged) return 17;
            for (int64_t m = 0; m < listed; m++)
                if (list[m] < 0 || list[m] >= C || !active[list[m]] || (m > 0 && list[m] <= list[m - 1]))
                    return 17;
            const int64_t held = b->committed[i * A + a];
            if (held >= 0 && !active[held]) return 17;
        }
        for (int64_t t = 0; t < length; t++) {
            const float reward = b->history_reward[i * L + t];
            /* an integral success (the lgamma tables' indices) */
            if (b->history_action[i * L + t] >= A || !(reward == 0.0f || reward == -1.0f))
                return 17;
        }
    }
    return 0;
}

/* Codes of fq_advance's refusals: -(1 + i * FQ_CHECK_CODES + code) for experiment i. */
#define FQ_CHECK_CODES 64

int64_t fq_advance(const fq_batch *b, int64_t max_steps, int64_t *next_experiment) {
    if (max_steps <= 0) return 0;
    int64_t (*run)(const fq_batch *, int64_t, int64_t) =
        b->generic ? (b->algorithm == ALG_Q_LEARNING ? run_q_learning_body
                      : b->algorithm == ALG_FACTOR_Q ? run_factor_q_body
                                                     : run_random_walk_body)
        : b->algorithm == ALG_Q_LEARNING ? run_q_learning
        : b->algorithm == ALG_FACTOR_Q   ? run_factor_q
                                         : run_random_walk;
    int64_t completed = 0;
    for (;;) {
        const int64_t i = __atomic_fetch_add(next_experiment, 1, __ATOMIC_RELAXED);
        if (i >= b->num_experiments) break;
        const int64_t code = fq_check_experiment(b, i);
        if (code != 0) return -(1 + i * FQ_CHECK_CODES + code); /* nothing of i was touched */
        if (b->run[i] < b->runs) completed += run(b, i, max_steps);
    }
    return completed;
}

/* --- Entry points for differential tests (tests/test_fast.py) against the Python sources --- */

/* Eq. 2-3 on n rows: g[r] = G and out[r] = C = Q + G rho, as functional.combined_values with
   functional.normaliser (q, rho [n, 4] float32). */
void fq_combined_values(const float *q, const float *rho, int64_t n, float eta_factor, float g_min,
                        float *g, float *out) {
    for (int64_t r = 0; r < n; r++) {
        const float *local = rho + r * NUM_ACTIONS;
        g[r] = normaliser(q + r * NUM_ACTIONS, local_spread(local), eta_factor, g_min);
        combine(q + r * NUM_ACTIONS, g[r], local, out + r * NUM_ACTIONS);
    }
}

/* world.scatter_obstacles for one world: blocked [size * size] uint8 (0/1). The caller gives
   pad_of_cell [N] and scratch space grid [(size + 2)^2] and obstacle_pads [num_obstacles]. */
void fq_scatter(int64_t size, int64_t num_obstacles, int64_t key, int64_t scatter_index,
                int64_t agent, const int32_t *pad_of_cell, uint8_t *grid, int32_t *obstacle_pads,
                uint8_t *blocked) {
    const int64_t width = size + 2, num_cells = size * size;
    memset(grid, 0, (size_t)(width * width));
    for (int64_t k = 0; k < num_obstacles; k++) obstacle_pads[k] = pad_of_cell[0];
    scatter(grid, obstacle_pads, pad_of_cell, num_cells, num_obstacles, (uint64_t)key,
            (uint64_t)scatter_index, agent);
    for (int64_t c = 0; c < num_cells; c++) blocked[c] = grid[pad_of_cell[c]];
}
