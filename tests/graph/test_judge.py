"""The null judge: without the model's surfaces no pose is checked, only the registrar's own answer counts."""

from __future__ import annotations

import numpy as np

from macroloc.graph.judge import NullJudge
from macroloc.graph.relocalize import Alignment


def test_the_null_judge_takes_the_registrars_answer_only() -> None:
    judge = NullJudge()
    judge.new_attempt()
    none = np.zeros((0, 3))
    assert not judge.can_check(10**6) and not judge.contradicts(np.eye(4), none, none)
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 0.0]
    taken = judge.choose(Alignment("localized", T), 0, none, none, [], lambda T_best, rivals: rivals)
    assert taken.T_cad_map is T and taken.registrars
    offered = judge.choose(Alignment("ambiguous", None, [], 1, [(T, 1)]), 0, none, none, [], lambda _, r: r)
    assert offered.T_cad_map is None and not offered.registrars
