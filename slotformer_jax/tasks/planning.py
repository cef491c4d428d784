"""PHYRE-style planning: rank candidate actions, count attempts, AUCCESS.

PHYRE (Bakhtin et al., 2019) lets an agent try actions on a task one after
another until one solves it; the score is AUCCESS, the area under the
"fraction of tasks solved within k attempts" curve for k = 1..100 with weights
log(k + 1) - log(k), which favours solving early. This module computes it
exactly as ``phyre.metrics.compute_metrics`` + ``normalize_metrics`` do:

* invalid actions (the ball overlaps a body) are simulated but never counted
  as attempts (``Evaluator.maybe_log_attempt`` drops them);
* a task's attempt count is the number of valid actions tried up to and
  including its first success; a task solved after more than 100 valid
  attempts (or never) counts as unsolved;
* AUCCESS = sum_k w_k s_k / sum_k w_k with s_k the fraction of tasks solved
  within k attempts (reported x 100 in the paper).

Planning with a success classifier ranks every candidate of a task by its
predicted success probability (ties keep the candidate order) and walks down
that list.

Outcomes are int arrays with one entry per candidate action:
SOLVED (1), NOT_SOLVED (0) or INVALID (-1).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

MAX_TEST_ATTEMPTS = 100
SOLVED, NOT_SOLVED, INVALID = 1, 0, -1


def attempt_weights(max_attempts: int = MAX_TEST_ATTEMPTS) -> np.ndarray:
  """float64 [max_attempts]: w_k = log(k + 1) - log(k) for k = 1..max."""
  k = np.arange(1, max_attempts + 1, dtype=np.float64)
  return np.log(k + 1) - np.log(k)


def attempts_to_solve(outcomes_in_order: Sequence[int] | np.ndarray,
                      max_attempts: int = MAX_TEST_ATTEMPTS) -> int | None:
  """Valid attempts used until the first success (None if not within max).

  Args:
    outcomes_in_order: int [num_candidates], outcomes in the order tried.
  """
  outcomes = np.asarray(outcomes_in_order)
  if outcomes.ndim != 1 or not np.isin(outcomes,
                                       (SOLVED, NOT_SOLVED, INVALID)).all():
    raise ValueError('outcomes must be a 1-D array of SOLVED (1), '
                     'NOT_SOLVED (0) or INVALID (-1)')
  valid = outcomes[outcomes != INVALID]
  solved = np.flatnonzero(valid == SOLVED)
  if solved.size == 0 or solved[0] + 1 > max_attempts:
    return None
  return int(solved[0]) + 1


def solved_by_curve(attempts: Sequence[int | None],
                    max_attempts: int = MAX_TEST_ATTEMPTS) -> np.ndarray:
  """float64 [max_attempts + 1]: s_k, fraction solved within k attempts.

  Index 0 is 0 attempts (always 0), as phyre's ``independent_solved_by``.
  """
  if not len(attempts):
    raise ValueError('need at least one task')
  solved = np.array([a for a in attempts if a is not None], np.int64)
  k = np.arange(max_attempts + 1)
  return (solved[None, :] <= k[:, None]).sum(1) / len(attempts)


def auccess(attempts: Sequence[int | None],
            max_attempts: int = MAX_TEST_ATTEMPTS) -> float:
  """AUCCESS in [0, 1] from each task's attempts to solve (None: unsolved)."""
  weights = attempt_weights(max_attempts)
  curve = solved_by_curve(attempts, max_attempts)[1:]
  return float(weights @ curve / weights.sum())


def rank_actions(scores: np.ndarray) -> np.ndarray:
  """Candidate indices from the highest score down (stable on ties)."""
  return np.argsort(-np.asarray(scores, np.float64), kind='stable')


def plan_auccess(scores: Sequence[np.ndarray], outcomes: Sequence[np.ndarray],
                 max_attempts: int = MAX_TEST_ATTEMPTS) -> float:
  """AUCCESS of trying each task's candidates in descending-score order.

  Args:
    scores: per task, float [num_candidates] (e.g. predicted success
      probability). Higher is tried first.
    outcomes: per task, int [num_candidates] simulated outcomes.
  """
  if len(scores) != len(outcomes):
    raise ValueError(f'{len(scores)} score arrays vs {len(outcomes)} tasks')
  attempts = []
  for task_scores, task_outcomes in zip(scores, outcomes):
    task_outcomes = np.asarray(task_outcomes)
    if np.shape(task_scores) != task_outcomes.shape:
      raise ValueError(f'scores {np.shape(task_scores)} vs outcomes '
                       f'{task_outcomes.shape}')
    order = rank_actions(task_scores)
    attempts.append(attempts_to_solve(task_outcomes[order], max_attempts))
  return auccess(attempts, max_attempts)


def random_scores(outcomes: Sequence[np.ndarray], seed: int
                  ) -> list[np.ndarray]:
  """The random-ranking baseline: i.i.d. uniform scores per candidate."""
  rng = np.random.default_rng(seed)
  return [rng.random(np.shape(o)) for o in outcomes]


def oracle_scores(outcomes: Sequence[np.ndarray]) -> list[np.ndarray]:
  """The oracle: simulated labels as scores (a solving action goes first)."""
  return [(np.asarray(o) == SOLVED).astype(np.float64) for o in outcomes]
