"""Test-wide settings."""

import torch

# many small ops: one intra-op thread is faster and deterministic (see dejaview.cli.options)
torch.set_num_threads(1)
