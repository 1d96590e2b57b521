"""Inference: find the source's initial state that explains its observed end."""

from dejaview.inference.optimize import OPTIMIZERS, OptimizationResult, Progress, make_optimizer, optimize
from dejaview.inference.params import ParameterLayout, layout_from_scene
from dejaview.inference.problem import InferenceProblem
from dejaview.inference.result import SolveResult
from dejaview.inference.solve import default_gradient, solve

__all__ = ["OPTIMIZERS", "InferenceProblem", "OptimizationResult", "ParameterLayout", "Progress",
           "SolveResult", "default_gradient", "layout_from_scene", "make_optimizer", "optimize", "solve"]
