"""Re-exports ``dejaview.backends.params``: the parameter layout is shared by every backend, so it
sits below ``dejaview.inference``; this module keeps ``dejaview.inference.params`` imports working."""

from dejaview.backends.params import BLOCKS, DEFAULT_SCALE, ParameterLayout, layout_from_scene

__all__ = ["BLOCKS", "DEFAULT_SCALE", "ParameterLayout", "layout_from_scene"]
