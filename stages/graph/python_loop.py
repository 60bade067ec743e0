"""Levenberg-Marquardt and Gauss-Newton driven from Python, for graphs with Python factors.

The stage no longer uses it: graphs with the shared tag scale are solved with native factors
(:mod:`stages.graph.scale_solve`); this loop solves the ``CustomFactor`` model directly and is the reference
the tests check that solve against.

GTSAM's own optimisers call a ``gtsam.CustomFactor``'s Python error function with the optimiser's
internal ``Values``. pybind11 cannot hand that C++ object to Python by reference (it is not a
registered Python instance), so it copies the whole ``Values`` for every factor on every
linearisation and error evaluation: the cost grows with poses x measurements (a Victoria-Park-sized
graph with the shared tag scale: about 15 s per iteration instead of 0.1 s). Driven from Python, the
values are Python objects, so the callbacks get them by reference and the same step costs what a
native graph's does.

The loop follows GTSAM's ``LevenbergMarquardtOptimizer`` with its default parameters: damping
``lambda I`` on every variable (a unary factor ``sqrt(lambda) I`` per key, not the diagonal of the
Hessian), lambda from 1e-5, times 10 after a rejected step and divided by 10 after an accepted one,
stop when lambda reaches 1e5, when the error falls by less than the relative or absolute tolerance,
or after ``max_iterations`` linearisations.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

LAMBDA_INITIAL = 1e-5
LAMBDA_FACTOR = 10.0
LAMBDA_UPPER = 1e5


@dataclass(frozen=True)
class LoopResult:
    """Solution of :func:`optimise_in_python`."""

    values: gtsam.Values
    iterations: int


def _converged(old: float, new: float, relative_tol: float, absolute_tol: float) -> bool:
    if new <= 0.0:
        return True
    decrease = old - new
    return decrease < absolute_tol or (old > 0 and decrease / old < relative_tol)


def optimise_in_python(
    graph: gtsam.NonlinearFactorGraph,
    initial: gtsam.Values,
    dims: dict[int, int],
    method: str = "lm",
    max_iterations: int = 100,
    relative_tol: float = 1e-6,
    absolute_tol: float = 1e-9,
) -> LoopResult:
    """Minimise ``graph.error`` from ``initial`` (``method``: ``lm`` or ``gn``); ``dims`` maps every key to its
    tangent dimension. GTSAM's exceptions (an indeterminant system) propagate unchanged."""
    if method not in ("lm", "gn"):
        raise ValueError(f"unknown method {method!r}; use lm or gn")
    ordering = graph.orderingCOLAMD()
    values = gtsam.Values(initial)
    error = float(graph.error(values))
    lam = LAMBDA_INITIAL
    sizes = set(dims.values())
    zeros = {d: np.zeros(d) for d in sizes}
    iterations = 0
    while iterations < max_iterations:
        iterations += 1
        linear = graph.linearize(values)
        while True:
            if method == "lm":
                damped = linear.clone()
                block = {d: np.sqrt(lam) * np.eye(d) for d in sizes}
                for key, d in dims.items():
                    damped.add(key, block[d], zeros[d])
                delta = damped.optimize(ordering)
            else:
                delta = linear.optimize(ordering)
            candidate = values.retract(delta)
            new_error = float(graph.error(candidate))
            if method == "gn" or new_error <= error:
                break
            lam *= LAMBDA_FACTOR
            if lam >= LAMBDA_UPPER:  # no damping makes the error fall: at the minimum
                return LoopResult(values, iterations)
        if not new_error <= error:  # Gauss-Newton overshot (or a non-finite error): keep the better point
            return LoopResult(values, iterations)
        done = _converged(error, new_error, relative_tol, absolute_tol)
        values, error = candidate, new_error
        lam = max(lam / LAMBDA_FACTOR, 1e-16)
        if done:
            break
    return LoopResult(values, iterations)
