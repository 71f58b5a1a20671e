"""A run folder written before a task-spec field existed resumes under today's config when
the field is left at its default (issue 29 added ``max_blind``)."""

from __future__ import annotations

from geonav.experiments.runner import _same_part, _same_spec


def test_a_field_added_later_at_its_default_does_not_block_resuming():
    old = {"scene": "A", "kind": "meta", "count": 1, "max_random_walk": 0.05}
    now = dict(old, max_blind=None)
    assert _same_spec(old, now)
    assert not _same_spec(old, dict(old, max_blind=0.3))      # set: a different task set
    assert not _same_spec(old, dict(old, count=2))
    before = {"tasks": {"A_one": old}, "stages": {}, "scenes": {}, "convergence": None}
    assert _same_part(before, {"tasks": {"A_one": now}, "stages": {}, "scenes": {},
                               "convergence": None})
    assert not _same_part(before, {"tasks": {"A_one": dict(now, max_blind=0.3)},
                                   "stages": {}, "scenes": {}, "convergence": None})
