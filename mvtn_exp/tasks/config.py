"""The task schema (``task=NAME``): the head's loss and its settings."""
from __future__ import annotations

from dataclasses import dataclass

from ..config.checks import fraction, one_of

TASKS = ("classification",)


@dataclass
class TaskConfig:
    """The task head and its loss. ``classification``: cross-entropy over the dataset's classes."""

    name: str = "classification"
    label_smoothing: float = 0.0

    def validate(self) -> "TaskConfig":
        one_of("task", self.name, TASKS)
        fraction("task.label_smoothing", self.label_smoothing)
        return self
