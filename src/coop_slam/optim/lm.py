"""The one damped least-squares loop of coop_slam's numpy solvers (Levenberg-Marquardt, and
Gauss-Newton for the tracking hot path).

Three solvers minimise a sum of (robust, IRLS-weighted) squared residuals in numpy: two-view
bundle adjustment (:mod:`coop_slam.registration.ba`: camera B's pose and the points, the points
eliminated by a Schur complement), Sim(3) refinement (:mod:`coop_slam.registration.sim3_refine`:
7 parameters) and motion-only pose optimization (:mod:`coop_slam.vo.pose_opt`: 6 parameters,
twice per tracked frame). Their problems differ -- how the normal equations are built and
solved, how a step moves the state, what a state costs -- but not the control flow, which is
:func:`least_squares`: linearize, damp, solve, retract, accept or reject, adapt the damping,
converge. A problem brings the rest (:class:`LeastSquaresProblem`).

The rules (:class:`LmRules`), one set for BA and Sim(3):

* damping: Marquardt's, ``H + lam diag(H)`` (plus a 1e-9 floor, :func:`damp`). It does not
  depend on the parameters' units, where Levenberg's ``lam I`` does: a monocular map's Sim(3)
  has a translation in that map's arbitrary unit next to radians and a log-scale, and the BA's
  points are metres at 1-20 m depth next to the pose's radians, so one ``lam`` would damp some
  directions hardly at all and others to a standstill. Nor does ``lam I`` know the size of ``H``:
  the BA's pose block, in whitened pixels, is ~1e7, and on a synthetic two-view problem (250
  points, 20 % outliers) ``lam I`` up to its cap of 1e5 never damped enough for a step to be
  accepted -- 0 iterations, 1 inlier -- where ``lam diag(H)`` converged (194 inliers, 0.8 px).
* acceptance: the gain ratio -- the actual decrease over the one the linearised model predicts
  -- above 1e-3 (Madsen, Nielsen & Tingleff 2004; GTSAM's minModelFidelity). A step that
  decreases the cost by a sliver of what was predicted says the model is not to be trusted that
  far; accepting it on a plain decrease (Sim(3)'s former rule) then *lowered* the damping.
* ``lam`` starts at 1e-5, x10 on a rejection, /10 on an acceptance, within [1e-12, 1e5]: with
  ``lam`` above 1e5 the step is a vanishing gradient step, no better one exists -- converged.
* convergence: a decrease below ``relative_tol`` of the cost (or 1e-9), ``max_iterations``
  accepted steps, or no acceptable step.

The Gauss-Newton configuration (:data:`GAUSS_NEWTON`, pose optimization): fixed damping, every
step taken without evaluating the cost, stop on a step below ``min_step`` or a singular or
non-finite solve, as ORB-SLAM's PoseOptimization: tracking runs it twice per frame, its rounds
re-weight and re-classify the residuals anyway, and a cost per step would be one more residual
evaluation per iteration on the hot path.

Why not SciPy or GTSAM: ``scipy.optimize.least_squares`` has no Schur complement (the BA's
Jacobian would be a dense 3 K + 6 columns for K points) and no way to re-weight between rounds
without starting anew; GTSAM builds one factor per residual in Python (thousands per
verification, which :mod:`coop_slam.registration.ba` replaced for that) and its Python wrapper
has no Sim(3) factors.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from ..errors import CoopSlamError


class LeastSquaresError(CoopSlamError):
    """Invalid rules for the least-squares loop (a damping schedule that cannot move)."""


@dataclass(frozen=True)
class LmRules:
    """How :func:`least_squares` iterates: the damping schedule, when to accept a step and when
    to stop. The defaults are Levenberg-Marquardt's rules (the module docstring says why)."""

    max_iterations: int = 30  # accepted steps (LM) or steps (Gauss-Newton)
    relative_tol: float = 1e-3  # stop when a step decreases the cost by less than this fraction
    absolute_tol: float = 1e-9  # ... or by less than this
    lambda_initial: float = 1e-5
    lambda_factor: float = 10.0
    lambda_min: float = 1e-12
    lambda_max: float = 1e5
    min_gain_ratio: float = 1e-3  # accept a step whose decrease is above this x the predicted one
    # Gauss-Newton configuration: damp with lambda_initial throughout, take every step, never
    # evaluate the cost, stop when the largest step component is below min_step.
    gauss_newton: bool = False
    min_step: float = 0.0

    def __post_init__(self) -> None:
        if self.max_iterations < 0 or not self.lambda_factor > 1.0:
            raise LeastSquaresError("need max_iterations >= 0 and lambda_factor > 1")
        if not 0.0 <= self.lambda_min <= self.lambda_initial <= self.lambda_max:
            raise LeastSquaresError("need 0 <= lambda_min <= lambda_initial <= lambda_max")
        if self.relative_tol < 0 or self.absolute_tol < 0:
            raise LeastSquaresError("relative_tol and absolute_tol must be >= 0")


# ORB-SLAM's pose optimization: a nearly undamped Gauss-Newton step, 1e-6 diag(H) + 1e-9 I.
GAUSS_NEWTON = LmRules(max_iterations=10, lambda_initial=1e-6, gauss_newton=True, min_step=1e-6)
# The damping's floor, DAMPING_FLOOR * I: a direction no residual observes (a zero column of the
# Jacobian, e.g. a point behind both cameras) leaves the damped system solvable.
DAMPING_FLOOR = 1e-9


class LeastSquaresProblem(Protocol):
    """What a problem supplies to :func:`least_squares`; a step is a 1-D array."""

    def linearize(self, state: Any) -> Any:
        """The normal equations (or whatever :meth:`solve` needs) at ``state``."""

    def solve(self, linearization: Any, lam: float) -> np.ndarray:
        """The step of the system damped by ``lam`` (with :func:`damp`); raises
        ``np.linalg.LinAlgError`` when it is singular."""

    def retract(self, state: Any, step: np.ndarray) -> Any:
        """The state moved by ``step`` (a new object: a rejected step leaves ``state`` as it is)."""

    def cost(self, state: Any) -> float:
        """The objective at ``state`` (Levenberg-Marquardt only)."""

    def predicted_decrease(self, linearization: Any, step: np.ndarray) -> float:
        """``-(g.step + step.H.step / 2)`` of the undamped model (Levenberg-Marquardt only)."""


@dataclass
class LmOutcome:
    state: Any
    iterations: int  # steps taken
    cost: float  # at ``state``; NaN in the Gauss-Newton configuration (never evaluated)


def damp(H: np.ndarray, lam: float, *, in_place: bool = False) -> np.ndarray:
    """``H + lam diag(H) + DAMPING_FLOOR I`` of one (k, k) matrix or a stack (..., k, k) of them
    (e.g. the diagonal blocks of a Schur complement: damping the whole system's diagonal is
    damping each block's)."""
    A = H if in_place else H.copy()
    diagonal = np.einsum("...ii->...i", A)  # a writable view: no index arrays on the hot path
    diagonal += DAMPING_FLOOR + lam * diagonal
    return A


def least_squares(problem: LeastSquaresProblem, state: Any, rules: LmRules) -> LmOutcome:
    """Minimise ``problem``'s cost from ``state`` under ``rules``."""
    if rules.gauss_newton:
        return _gauss_newton(problem, state, rules)
    cost = problem.cost(state)
    lam, iterations = rules.lambda_initial, 0
    while iterations < rules.max_iterations:
        linearization = problem.linearize(state)
        accepted = False
        while lam <= rules.lambda_max:
            try:
                step = problem.solve(linearization, lam)
            except np.linalg.LinAlgError:
                step = None
            if step is not None and np.all(np.isfinite(step)):
                candidate = problem.retract(state, step)
                cost_new = problem.cost(candidate)
                predicted = problem.predicted_decrease(linearization, step)
                if predicted > 0 and (cost - cost_new) / predicted > rules.min_gain_ratio:
                    accepted = True
                    break
            lam *= rules.lambda_factor
        if not accepted:
            break
        decrease = cost - cost_new
        state, cost, iterations = candidate, cost_new, iterations + 1
        lam = max(lam / rules.lambda_factor, rules.lambda_min)
        if decrease <= rules.relative_tol * (cost + decrease) or decrease <= rules.absolute_tol:
            break
    return LmOutcome(state, iterations, cost)


def _gauss_newton(problem: LeastSquaresProblem, state: Any, rules: LmRules) -> LmOutcome:
    iterations = 0
    while iterations < rules.max_iterations:
        try:
            step = problem.solve(problem.linearize(state), rules.lambda_initial)
        except np.linalg.LinAlgError:
            break
        if not np.all(np.isfinite(step)):
            break
        state, iterations = problem.retract(state, step), iterations + 1
        if np.abs(step).max() < rules.min_step:
            break
    return LmOutcome(state, iterations, np.nan)
