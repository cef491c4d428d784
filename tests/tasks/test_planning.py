"""AUCCESS and ranking, against hand computations."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slotformer_jax.tasks import planning

S, F, I = planning.SOLVED, planning.NOT_SOLVED, planning.INVALID


def test_attempts_skip_invalid_actions():
  assert planning.attempts_to_solve([S, F]) == 1
  assert planning.attempts_to_solve([I, I, F, S, S]) == 2
  assert planning.attempts_to_solve([F, F, I]) is None
  # Success at valid attempt 101 is outside the budget; invalid ones before it
  # do not use it up.
  late = [I] * 50 + [F] * 100 + [S]
  assert planning.attempts_to_solve(late) is None
  assert planning.attempts_to_solve([I] * 50 + [F] * 99 + [S]) == 100
  with pytest.raises(ValueError):
    planning.attempts_to_solve([2])


def test_auccess_by_hand():
  # Task A solved at attempt 1, B never, C at valid attempt 2 after two
  # invalid actions. s_1 = 1/3, s_k = 2/3 for k >= 2; sum_k w_k = log(101).
  attempts = [planning.attempts_to_solve(o) for o in
              ([S, F, F], [F, F, F, I], [I, I, F, S])]
  assert attempts == [1, None, 2]
  w1, total = math.log(2), math.log(101)
  expected = (w1 * 1 / 3 + (total - w1) * 2 / 3) / total
  assert planning.auccess(attempts) == pytest.approx(expected, abs=1e-12)
  assert planning.auccess([1, 1]) == pytest.approx(1.0)
  assert planning.auccess([None, None]) == 0.0
  # Solved at exactly attempt 100: only the last weight counts.
  assert planning.auccess([100]) == pytest.approx(
      (math.log(101) - math.log(100)) / total)


def test_plan_auccess_ranks_by_score_and_baselines():
  outcomes = [np.array([F, I, S, F]), np.array([F, F, F, F])]
  scores = [np.array([0.9, 0.95, 0.5, 0.1]), np.array([0.3, 0.2, 0.1, 0.0])]
  # Task 1 order: invalid (skipped), F, S -> 2 attempts; task 2 never.
  w1, total = math.log(2), math.log(101)
  assert planning.plan_auccess(scores, outcomes) == pytest.approx(
      0.5 * (total - w1) / total)
  assert planning.plan_auccess(planning.oracle_scores(outcomes),
                               outcomes) == pytest.approx(0.5)
  with pytest.raises(ValueError):
    planning.plan_auccess(scores[:1], outcomes)
  # Random ranking over many tasks with 1 solution in 10 valid actions:
  # the expected solved-by-k is k/10 up to k = 10, so the expected AUCCESS is
  # (sum_{k<=10} w_k k/10 + log(101/11)) / log(101)
  #   = (log 11 - log(10!)/10 + log(101/11)) / log(101) ~ 0.673.
  many = [np.array([S] + [F] * 9) for _ in range(400)]
  value = planning.plan_auccess(planning.random_scores(many, seed=0), many)
  expected = (math.log(11) - math.log(math.factorial(10)) / 10
              + math.log(101 / 11)) / total
  assert value == pytest.approx(expected, abs=0.02)
