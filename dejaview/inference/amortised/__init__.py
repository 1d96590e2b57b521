"""Amortised posteriors: a flow trained on simulations of a scene answers any observation of it.

``train(scene)`` -> ``AmortisedModel`` (``training``), saved and loaded as a safetensors file
(``model``); ``answer(scene, model)`` draws from it, weighs the draws by the exact likelihood and
falls back to the sampler where they show the flow does not fit (``answer``); ``live(...)``
answers from the flow alone in milliseconds (``answer``).
"""

from dejaview.inference.amortised.model import AmortisedModel, fingerprint
from dejaview.inference.amortised.training import train

__all__ = ["AmortisedModel", "fingerprint", "train"]
