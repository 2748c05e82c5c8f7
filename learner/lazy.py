"""Tensors that keep the parts they are made of and compute their values only when asked.

RDN's critic input on bane_vs_bane is [B*T, 24 agents x (4 x 336 + 30 + 24)] = 3,000 x 33,552
floats, 430 MB, almost all of it copies of the same observations (each sits in 4 windows) and
zeros (dead agents, padding). Built densely, it and the per-feature LRP relevance of it cost
more than the rest of the update together. A `LazyTensor` stands in for such a tensor: it has
the dense tensor's shape, dtype and device and behaves exactly like it under every torch
operation (the first operation that needs the values computes them once, via `materialise`,
and keeps them), while code that knows its structure (the critic's first layer, LRP's per-agent
sums; `learner.batch.AgentBlocks`, `learner.lrp.BlockRelevance`) reads the parts instead.

A LazyTensor never requires grad and is read-only: an in-place operation on it raises, since
it would change the dense copy but not the parts the structured code reads.
"""

from __future__ import annotations

from typing import Any

import torch
from torch.utils._pytree import tree_map


class LazyTensor(torch.Tensor):
    """Base class: subclasses pass the dense shape and a tensor `like` (dtype and device) to
    `__new__`, store their parts in `__init__` and implement `materialise()`.

    Calling loop::

        x = SomeLazy(parts...)        # shape known, values not computed
        fast = structured_code(x)     # reads x's parts
        y = x.sum()                   # any torch op: x.dense() is computed once, then used
    """

    __torch_function__ = torch._C._disabled_torch_function_impl

    @staticmethod
    def __new__(cls, shape: tuple[int, ...], like: torch.Tensor, *args: Any, **kwargs: Any):
        return torch.Tensor._make_wrapper_subclass(
            cls, shape, dtype=like.dtype, device=like.device, requires_grad=False
        )

    def __init__(self, shape: tuple[int, ...], like: torch.Tensor, *args: Any, **kwargs: Any):
        self._dense: torch.Tensor | None = None

    def materialise(self) -> torch.Tensor:
        """The dense values (called at most once, without grad)."""
        raise NotImplementedError

    def dense(self) -> torch.Tensor:
        """The dense tensor this stands for (computed on first use, then kept)."""
        if self._dense is None:
            with torch.no_grad():
                dense = self.materialise()
            if dense.shape != self.shape:
                raise RuntimeError(f"{type(self).__name__} materialised {dense.shape}")
            self._dense = dense
        return self._dense

    def __repr__(self) -> str:  # without computing the values
        return f"{type(self).__name__}(shape={tuple(self.shape)}, dtype={self.dtype})"

    def structured(self, func: Any, args: tuple, kwargs: dict) -> Any:
        """A subclass's own result for an operation it can do on its parts (e.g. a slice
        that stays lazy), or NotImplemented to get the dense tensor's."""
        return NotImplemented

    @classmethod
    def __torch_dispatch__(cls, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if args and isinstance(args[0], LazyTensor):
            out = args[0].structured(func, args, kwargs)
            if out is not NotImplemented:
                return out
        if func._schema.is_mutable:
            for arg, value in zip(func._schema.arguments, args, strict=False):
                if isinstance(value, LazyTensor) and arg.is_write:
                    raise RuntimeError(
                        f"{type(value).__name__} is read-only; {func} would write to it "
                        "(take .dense().clone() to get a writable copy)"
                    )

        def unwrap(a: Any) -> Any:
            return a.dense() if isinstance(a, LazyTensor) else a

        return func(*tree_map(unwrap, args), **tree_map(unwrap, kwargs))
