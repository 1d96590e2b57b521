"""Inference: find the source's initial state that explains its observed end.

Three objects a researcher composes (docs/inference.md, "Composing the inference"):
``Posterior.from_scene(scene)`` (the density), ``MapSearch(SearchParams()).run(posterior)``
(its most probable past) and ``Sampler(SamplerParams()).sample(posterior, modes, n)`` (its
samples); ``fit_locally`` runs the seed's local optimisers; ``solve`` composes them as a scene asks.
"""

from dejaview.backends.params import ParameterLayout, layout_from_scene
from dejaview.inference.local import LocalParams, fit_locally
from dejaview.inference.optimize import OPTIMIZERS, OptimizationResult, Progress, make_optimizer, optimize
from dejaview.inference.params import SamplerParams, SearchParams
from dejaview.inference.posterior import Posterior, PosteriorSettings
from dejaview.inference.result import SolveResult
from dejaview.inference.sampling import PosteriorSamples, Sampler
from dejaview.inference.search import MapSearch, SearchResult
from dejaview.inference.solve import SolveParams, solve

__all__ = ["OPTIMIZERS", "LocalParams", "MapSearch", "OptimizationResult", "ParameterLayout",
           "Posterior", "PosteriorSamples", "PosteriorSettings", "Progress", "SamplerParams", "Sampler",
           "SearchParams", "SearchResult", "SolveParams", "SolveResult", "fit_locally", "layout_from_scene", "make_optimizer",
           "optimize", "solve"]
