"""Loss values and gradients in forward or reverse mode.

Both functions take a loss function ``fn`` mapping parameters ``x`` of shape
``(..., P)`` to losses of shape ``(...)``, where every leading index is an
independent problem (a candidate of the batch). They return the losses and
the gradient ``d loss[...] / d x[..., :]`` of shape ``(..., P)``.

- Reverse mode: one rollout recording the graph, one backward pass; memory
  grows with the rollout length unless the rollout checkpoints.
- Forward mode: ``torch.func.jvp`` along each of the P basis directions,
  vmapped so the P tangents run as one batched rollout (what ``jacfwd`` does,
  but over the parameter axis only, so a batch of B candidates costs P
  tangents, not B * P). No graph is stored: memory does not grow with the
  number of steps. Best when P is small (the ~12 parameters of one object).
"""

from __future__ import annotations

from collections.abc import Callable

import torch

GRADIENT_MODES = ("forward", "reverse")


def reverse_value_and_grad(fn: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor
                           ) -> tuple[torch.Tensor, torch.Tensor]:
    """Losses and gradients by autograd.

    Args:
        fn: (..., P) -> (...) losses, independent along leading dimensions.
        x: (..., P) parameters.
    Returns:
        losses (...) detached, gradient (..., P).
    """
    with torch.enable_grad():
        xr = x.detach().requires_grad_(True)
        loss = fn(xr)
        (grad,) = torch.autograd.grad(loss.sum(), xr)
    return loss.detach(), grad


def forward_value_and_grad(fn: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor,
                           chunk_size: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Losses and gradients by forward-mode AD (``torch.func.jvp`` vmapped over the basis).

    Args:
        fn: (..., P) -> (...) losses, independent along leading dimensions. Must
            be free of data-dependent Python branches (it runs under vmap).
        x: (..., P) parameters.
        chunk_size: vmap chunk size over the P directions (None: all at once).
    Returns:
        losses (...), gradient (..., P).
    """
    x = x.detach()
    p = x.shape[-1]
    basis = torch.eye(p, dtype=x.dtype, device=x.device)
    tangents = basis.reshape(p, *([1] * (x.dim() - 1)), p).expand(p, *x.shape)

    def directional(t):
        return torch.func.jvp(fn, (x,), (t,))

    with torch.no_grad():
        value, jac = torch.func.vmap(directional, out_dims=(None, 0), chunk_size=chunk_size)(tangents)
    return value, jac.movedim(0, -1)


def value_and_grad(fn: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor,
                   mode: str = "forward") -> tuple[torch.Tensor, torch.Tensor]:
    """Dispatch to ``forward_value_and_grad`` or ``reverse_value_and_grad`` by name."""
    if mode == "forward":
        return forward_value_and_grad(fn, x)
    if mode == "reverse":
        return reverse_value_and_grad(fn, x)
    raise ValueError(f"unknown gradient mode {mode!r}; choose one of {', '.join(GRADIENT_MODES)}")
