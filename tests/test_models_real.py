"""Which recipe ``models_real`` follows (``models_real.recipe_of``): the default without
folds, the folds' single best, or the mass's and the COM's apart where that scores better.
(How ``models_real`` is then made of the folds' own folders: tests/test_folds.py; the
default recipe's models, without folds: tests/test_learning.py's tiny end to end.)"""

from __future__ import annotations

from types import SimpleNamespace

from jaxinertia.app import models_real as M
from jaxinertia.app import recipe as R

MASS = R._recipe(R.ENSEMBLE, 0.0, ["paper network, simulator only",
                                   "physical, simulator only"], attention=False)
COM = R._recipe("physical with the current input, sessions drawn, simulator only", 1.0)
BEST = {**R._recipe("physical, simulator only", 0.5), "score": 1.2}


def _folds(part_score: float, mass=MASS, com=COM) -> dict:
    return {"recipe": {**BEST, "scores": [BEST], "by_part": {
        "mass": mass, "com": com, "score": part_score}}}


def test_without_folds_the_default_recipe():
    assert M.recipe_of(None, SimpleNamespace(recipe_by_part=True)) == M.DEFAULT_RECIPE


def test_the_parts_apart_where_they_score_better_else_the_single_best():
    by_part = SimpleNamespace(recipe_by_part=True)
    r = M.recipe_of(_folds(0.9), by_part)
    assert {k: r[k] for k in MASS} == MASS and r["com"] == COM and r["score"] == 0.9
    assert r["single_model_recipe"] == BEST and "apart" in r["chosen_by"]
    for folds, scale in ((_folds(1.3), by_part),  # the parts apart score worse
                         (_folds(0.9), SimpleNamespace(recipe_by_part=False)),
                         (_folds(0.9, com=MASS), by_part)):  # both parts the same choice
        r = M.recipe_of(folds, scale)
        assert "com" not in r and r["candidate"] == BEST["candidate"]
        assert r["chosen_by"] == "held-out folds"
