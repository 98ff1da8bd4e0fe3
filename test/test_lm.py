"""Tests of coop_slam.optim.lm, the one damped least-squares loop of the numpy solvers."""

from __future__ import annotations

import numpy as np
import pytest

from coop_slam.errors import CoopSlamError
from coop_slam.optim.lm import GAUSS_NEWTON, LeastSquaresError, LmRules, damp, least_squares


class _Rosenbrock:
    """r = (10 (y - x^2), 1 - x): Gauss-Newton overshoots from (-1.2, 1), LM has to damp."""

    def __init__(self):
        self.costs = []

    @staticmethod
    def residuals(state):
        x, y = state
        return np.array([10.0 * (y - x * x), 1.0 - x]), np.array([[-20.0 * x, 10.0], [-1.0, 0.0]])

    def cost(self, state):
        r = self.residuals(state)[0]
        self.costs.append(0.5 * float(r @ r))
        return self.costs[-1]

    def linearize(self, state):
        r, J = self.residuals(state)
        return J.T @ J, J.T @ r

    @staticmethod
    def solve(linearization, lam):
        H, g = linearization
        return np.linalg.solve(damp(H, lam), -g)

    @staticmethod
    def predicted_decrease(linearization, step):
        H, g = linearization
        return -float(g @ step + 0.5 * step @ H @ step)

    @staticmethod
    def retract(state, step):
        return state + step


def test_levenberg_marquardt_reaches_the_minimum_from_the_classic_start():
    problem = _Rosenbrock()
    outcome = least_squares(
        problem, np.array([-1.2, 1.0]), LmRules(max_iterations=100, relative_tol=1e-12)
    )
    np.testing.assert_allclose(outcome.state, [1.0, 1.0], atol=1e-6)
    assert outcome.cost < 1e-12 and 0 < outcome.iterations < 100
    assert outcome.cost == min(problem.costs)  # the state returned is the best one evaluated


def test_gauss_newton_configuration_takes_every_step_without_a_cost():
    class Linear(_Rosenbrock):
        @staticmethod
        def residuals(state):
            A = np.array([[2.0, 1.0], [0.0, 3.0], [1.0, 1.0]])
            return A @ state - np.array([1.0, 2.0, 3.0]), A

    problem = Linear()
    outcome = least_squares(problem, np.zeros(2), GAUSS_NEWTON)
    A = Linear.residuals(np.zeros(2))[1]
    expected = np.linalg.lstsq(A, [1.0, 2.0, 3.0], rcond=None)[0]
    np.testing.assert_allclose(outcome.state, expected, rtol=1e-5)
    assert problem.costs == [] and np.isnan(outcome.cost)
    assert outcome.iterations < GAUSS_NEWTON.max_iterations  # stopped on a tiny step


def test_damping_is_marquardt_s_with_a_floor_on_one_matrix_or_a_stack():
    H = np.array([[4.0, 1.0], [1.0, 0.0]])
    np.testing.assert_allclose(damp(H, 0.5), [[6.0 + 1e-9, 1.0], [1.0, 1e-9]])
    assert H[0, 0] == 4.0  # a copy unless asked in place
    stack = np.stack([H, 2 * H])
    np.testing.assert_allclose(damp(stack, 1.0)[1], [[16.0 + 1e-9, 2.0], [2.0, 1e-9]])


def test_rules_that_cannot_move_are_refused():
    with pytest.raises(LeastSquaresError, match="lambda_factor"):
        LmRules(lambda_factor=1.0)
    with pytest.raises(LeastSquaresError, match="lambda_min"):
        LmRules(lambda_initial=1e6)
    assert issubclass(LeastSquaresError, CoopSlamError)
