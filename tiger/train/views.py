"""Which views a step trains on: epochs of a seeded random permutation."""
from __future__ import annotations

from typing import Optional, Sequence, Union

import torch


class ViewSampler:
    """Draws view indices without replacement within an epoch, a new random permutation per epoch.

    Each epoch is ``torch.randperm(len(items), generator=generator)``, consumed from its end (the
    order INRIA's trainer uses). The generator may be shared with other draws of the loop (it is
    checkpointed by the loop, see :func:`tiger.train.rng_state`); :meth:`state_dict` holds the rest
    of the current epoch, so a loaded sampler continues the same sequence.

    Args:
        items: the number of views V (indices 0..V-1) or the view indices to draw from.
        generator: the CPU generator of the permutations (default: a new one seeded 0).
    """

    def __init__(self, items: Union[int, Sequence[int]], generator: Optional[torch.Generator] = None) -> None:
        self.items = list(range(items)) if isinstance(items, int) else [int(i) for i in items]
        if not self.items:
            raise ValueError("tiger.train.ViewSampler: no views to sample from")
        self.generator = generator if generator is not None else torch.Generator().manual_seed(0)
        self._order: list[int] = []

    def __len__(self) -> int:
        return len(self.items)

    def next(self) -> int:
        """The next view index."""
        if not self._order:
            self._order = [self.items[k] for k in torch.randperm(len(self.items), generator=self.generator).tolist()]
        return self._order.pop()

    def take(self, k: int) -> list[int]:
        """The next ``min(k, V)`` view indices (an epoch boundary may fall inside them)."""
        return [self.next() for _ in range(min(int(k), len(self.items)))]

    def peek(self, k: int) -> list[int]:
        """The next ``min(k, V)`` indices without taking them (e.g. to prefetch their data). Draws
        the next epoch early when needed: the sequence is the same as long as nothing else draws
        from the generator in between."""
        k = min(int(k), len(self.items))
        while len(self._order) < k:
            epoch = [self.items[j] for j in torch.randperm(len(self.items), generator=self.generator).tolist()]
            self._order = epoch + self._order  # taken from the end: after the current epoch
        return self._order[::-1][:k]

    def state_dict(self) -> dict:
        """{"order": the views left in the current epoch}; the generator is saved by the loop."""
        return {"order": list(self._order)}

    def load_state_dict(self, state: dict) -> None:
        order = [int(i) for i in state.get("order", [])]
        unknown = sorted(set(order) - set(self.items))
        if unknown:
            raise ValueError(f"tiger.train.ViewSampler: saved order names views {unknown[:5]} outside the "
                             f"{len(self.items)} being sampled")
        self._order = order


__all__ = ["ViewSampler"]
