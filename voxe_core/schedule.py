"""Time-step annealing for SDS (paper §3.2, SPEC §2).

``t ~ U[t_min, k_i]·T`` where the upper fraction ``k`` is ``k0 = 0.98`` until
iteration ``i_start = 4000``; then ``k ← k·0.75`` every ``f_a = 600``
iterations, floored at 0.35 (paper) or 0.22 (authors' code,
:data:`AUTHORS_FLOOR`).

The appendix's rule, k_i = k_{i-1}·γ when i ≥ i_start and i % f_a = 0, on the authors' step
count (1-based: ``sd.py``'s ``train_step`` decays when ``step >= start and step % freq == 0``). With
i_start = 4000 (not a multiple of 600) the first decay is at step 4200, the 0-based iteration 4199:
k(4198) = 0.98, k(4199) = 0.735, k(4798) = 0.735, k(4799) = 0.55125, ... In general, with
step = iteration + 1 ≥ i_start, ``k = max(floor, k0 · factor^(step // every − (i_start − 1) // every))``
(the multiples of ``every`` in [i_start, step]). An earlier version decayed at i_start itself, 200
iterations early.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import torch

from voxe_core.tensorio import check_numbers

PAPER_FLOOR = 0.35
AUTHORS_FLOOR = 0.22


@dataclass
class TimestepSchedule:
    """Annealed upper bound of the SDS time-step range; defaults are the paper's."""

    k0: float = 0.98
    t_min: float = 0.02
    i_start: int = 4000
    every: int = 600
    factor: float = 0.75
    floor: float = PAPER_FLOOR

    def __post_init__(self):
        # A NaN i_start had passed the range checks and annealed to the floor from iteration 0 (a NaN every from
        # i_start on), silently: max(floor, NaN) is the floor.
        for name in ("i_start", "every"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Integral):
                raise ValueError(f"{name} takes whole numbers (iterations), got {value!r}")
        # (a string or None had been a TypeError from the comparisons below, naming no setting; True had run as 1)
        check_numbers(self, ("k0", "t_min", "factor", "floor"))
        if not 0.0 <= self.t_min < self.floor <= self.k0 <= 1.0:
            raise ValueError(
                f"need 0 <= t_min < floor <= k0 <= 1, got t_min={self.t_min}, floor={self.floor}, k0={self.k0}"
            )
        if self.every < 1:
            raise ValueError(f"every must be >= 1, got {self.every}")
        if self.i_start < 0:
            raise ValueError(f"i_start must be >= 0, got {self.i_start}")
        if not 0.0 < self.factor <= 1.0:
            raise ValueError(f"factor must be in (0, 1], got {self.factor}")

    @classmethod
    def authors(cls, **overrides) -> "TimestepSchedule":
        """The authors' code: floor 0.22 instead of the paper's 0.35."""
        return cls(**{"floor": AUTHORS_FLOOR, **overrides})

    def max_fraction(self, iteration: int) -> float:
        """Upper bound ``k`` (fraction of T) at ``iteration`` (0-based; the module docstring has the rule).

        Examples:
            >>> schedule = TimestepSchedule()
            >>> [schedule.max_fraction(i) for i in (4198, 4199, 4798, 4799)]
            [0.98, 0.735, 0.735, 0.55125]
        """
        if iteration < 0:
            raise ValueError(f"iteration must be >= 0, got {iteration}")
        step = int(iteration) + 1  # the authors' count
        if step < self.i_start:
            return float(self.k0)
        decays = step // self.every - (max(self.i_start, 1) - 1) // self.every  # multiples in [i_start, step]
        return float(max(self.floor, self.k0 * self.factor**decays))

    def bounds(self, iteration: int, num_train_timesteps: int = 1000) -> tuple[int, int]:
        """Inclusive integer range ``[floor(t_min·T), min(floor(k·T), T−1)]`` of time steps."""
        T = int(num_train_timesteps)
        lo = int(math.floor(self.t_min * T + 1e-9))
        hi = min(int(math.floor(self.max_fraction(iteration) * T + 1e-9)), T - 1)
        return lo, max(lo, hi)

    def sample(
        self,
        iteration: int,
        n: int = 1,
        num_train_timesteps: int = 1000,
        generator: torch.Generator | None = None,
        device: torch.device | str | None = None,
    ) -> torch.Tensor:
        """``n`` time steps, uniform over the integers of :meth:`bounds` (LongTensor ``(n,)``).

        Drawn on the generator's device (CPU by default), then moved to ``device``.
        """
        lo, hi = self.bounds(iteration, num_train_timesteps)
        gen_device = generator.device if generator is not None else torch.device("cpu")
        t = torch.randint(lo, hi + 1, (int(n),), generator=generator, device=gen_device, dtype=torch.long)
        return t if device is None else t.to(device)
