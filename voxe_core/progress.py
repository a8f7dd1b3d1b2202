"""Callbacks shared by every long-running stage: progress, checkpoints, cancellation."""

from __future__ import annotations

from dataclasses import dataclass, field
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

    def progress(self, report: Progress) -> None:
        if self.on_progress is not None:
            self.on_progress(report)

    def check_cancel(self, stage: str) -> None:
        if self.should_cancel is not None and self.should_cancel():
            raise StageCancelled(f"{stage} canceled")

    def checkpoint_written(self, path: str) -> None:
        if self.on_checkpoint is not None:
            self.on_checkpoint(path)
