"""A per-stage memo of the last inputs and result, so an unchanged stage is not recomputed."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor


def _same(a: tuple[Tensor | None, ...], b: tuple[Tensor | None, ...]) -> bool:
    if len(a) != len(b):
        return False
    for x, y in zip(a, b, strict=True):
        if x is None or y is None:
            if x is not y:
                return False
        elif x.shape != y.shape or x.dtype != y.dtype or x.device != y.device:
            return False
        elif not torch.equal(x, y):
            return False
    return True


def _needs_grad(values: Any) -> bool:
    items = values if isinstance(values, tuple) else (values,)
    return any(isinstance(v, Tensor) and v.requires_grad for v in items)


class StageCache:
    """Remembers, per stage name, the last key tensors and the value computed from them.

    Values that carry an autograd graph are never stored: reusing a graph across backward
    passes would fail or be wrong, so differentiable calls always recompute.
    """

    def __init__(self, enabled: bool = True) -> None:
        self.enabled = enabled
        self.hits: Counter[str] = Counter()
        self.misses: Counter[str] = Counter()
        self._entries: dict[str, tuple[tuple[Tensor | None, ...], Any]] = {}

    def get(self, stage: str, key: tuple[Tensor | None, ...], compute: Callable[[], Any]) -> Any:
        if not self.enabled or (torch.is_grad_enabled() and _needs_grad(key)):
            return compute()
        entry = self._entries.get(stage)
        if entry is not None and _same(entry[0], key):
            self.hits[stage] += 1
            return entry[1]
        self.misses[stage] += 1
        value = compute()
        if not _needs_grad(value):
            self._entries[stage] = (tuple(None if k is None else k.detach().clone() for k in key),
                                    value)
        return value

    def clear(self) -> None:
        self._entries.clear()
        self.hits.clear()
        self.misses.clear()
