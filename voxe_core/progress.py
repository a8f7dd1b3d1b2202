"""Callbacks shared by every long-running stage: progress, checkpoints, cancellation."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace
from typing import Callable


class StageCancelled(RuntimeError):
    """Raised inside a stage when its ``should_cancel`` callback answers True."""


@dataclass
class Progress:
    stage: str
    iteration: int  # iterations completed so far
    total: int
    losses: dict[str, float] = field(default_factory=dict)
    info: dict[str, object] = field(default_factory=dict)


@dataclass
class Callbacks:
    """Hooks a caller (CLI, worker, test) passes into a stage; all optional."""

    on_progress: Callable[[Progress], None] | None = None
    should_cancel: Callable[[], bool] | None = None
    on_checkpoint: Callable[[str], None] | None = None  # receives the checkpoint path
    on_warning: Callable[[str, str], None] | None = None  # receives the stage and what its user should know

    def progress(self, report: Progress) -> None:
        if self.on_progress is not None:
            self.on_progress(report)

    def check_cancel(self, stage: str) -> None:
        if self.should_cancel is not None and self.should_cancel():
            raise StageCancelled(f"{stage} canceled")

    def checkpoint_written(self, path: str) -> None:
        if self.on_checkpoint is not None:
            self.on_checkpoint(path)

    def warning(self, stage: str, text: str) -> None:
        """Tell the caller ``text`` about a stage that runs on but not as asked: to ``on_warning`` (the service's job,
        the CLI's stderr), else as a Python warning (never shown to a service's user, whom the job tells)."""
        if self.on_warning is not None:
            self.on_warning(stage, text)
        else:
            warnings.warn(f"{stage}: {text}", stacklevel=3)


def in_phases(callbacks: Callbacks, sizes: dict[str, int]) -> Callbacks:
    """``callbacks`` with the named sub-steps' reports counted on one scale of ``sum(sizes)`` units.

    A stage made of sub-steps (refine: attention maps, then the grids' fit, then the cut) would
    otherwise report each from 0 to its own total, and a job's progress would fall back at every
    new sub-step. A report keeps its sub-step's name as its ``stage``; other names pass unchanged.
    Its ``info["phase_units_left"]`` holds the units left in its sub-step and each later one: they may
    cost very different times per unit (an attention pass against a fitting step), which a time-left
    estimate weighs (the worker's ``StageCallbacks``).

    Examples:
        >>> seen = []
        >>> cb = in_phases(Callbacks(on_progress=lambda p: seen.append((p.stage, p.iteration, p.total))),
        ...                {"maps": 4, "fit": 10, "cut": 1})
        >>> cb.progress(Progress("maps", 4, 4)); cb.progress(Progress("fit", 5, 10)); cb.progress(Progress("cut", 1, 1))
        >>> seen
        [('maps', 4, 15), ('fit', 9, 15), ('cut', 15, 15)]
        >>> cb = in_phases(Callbacks(on_progress=lambda p: seen.append(p.info)), {"maps": 4, "fit": 10, "cut": 1})
        >>> cb.progress(Progress("fit", 5, 10, info={"stage": "fit"})); seen[-1]
        {'stage': 'fit', 'phase_units_left': {'fit': 5, 'cut': 1}}
    """
    offsets, total, order = {}, 0, list(sizes)
    for name, size in sizes.items():
        offsets[name], total = total, total + max(0, int(size))

    def report(progress: Progress) -> None:
        if progress.stage not in offsets:
            callbacks.progress(progress)
            return
        size = max(0, int(sizes[progress.stage]))
        done = size if progress.total <= 0 else round(size * min(progress.iteration, progress.total) / progress.total)
        later = {name: max(0, int(sizes[name])) for name in order[order.index(progress.stage) + 1:]}
        info = {**progress.info, "phase_units_left": {progress.stage: size - done, **later}}
        callbacks.progress(replace(progress, iteration=offsets[progress.stage] + done, total=total, info=info))

    return replace(callbacks, on_progress=report if callbacks.on_progress is not None else None)
