"""The held-out folds' trainings as few programs (:mod:`jaxinertia.training_group`): which
trainings of :func:`jaxinertia.app.folds.run_folds` meet in a group, by name."""

from __future__ import annotations

from dataclasses import dataclass

from jaxinertia.app.programs import side_by_side_workers
from jaxinertia.training_group import TrainingGroup

__all__ = ["FoldGroups", "branch_tags"]


def branch_tags(scale) -> list[str]:
    """The physical-model branches of a fold, by their model folders' suffix."""
    if not scale.finetune_samples:
        return []
    return [""] + (["_current"] if scale.current_input else []) + (
        ["_current_sessions"] if scale.current_input and scale.session_draws > 0 else [])


@dataclass(frozen=True)
class FoldGroups:
    """Every fold's trainings as few programs (:mod:`jaxinertia.training_group`): those
    from scratch (the paper network and each physical branch) in one group, the
    fine-tunings in another; members named ``fit_on/branch[/samples]``. Only where the
    folds and their branches run side by side (an accelerator): each member needs a
    thread of its own."""

    scratch: TrainingGroup
    finetune: TrainingGroup

    @classmethod
    def of(cls, names: list[str], scale) -> FoldGroups | None:
        if side_by_side_workers() <= 1:
            return None
        tags = branch_tags(scale)
        return cls(TrainingGroup([f"{n}/paper" for n in names]
                                 + [f"{n}/physical{t}" for n in names for t in tags]),
                   TrainingGroup([f"{n}/physical{t}/{k}" for n in names for t in tags
                                  for k in scale.finetune_samples]))

    def leave(self, prefix: str) -> None:
        """Every member under ``prefix`` trains no more (a branch or fold ended, perhaps
        by an exception): the others stop waiting for it."""
        for group in (self.scratch, self.finetune):
            group.leave([m for m in group.members if m == prefix or
                         m.startswith(prefix + "/")])
