"""The duplex, whose two flats are each other's image under a half-turn in their doors, windows and walls, flown
with the rendered camera and the perception chain (slow): never localized on the image."""

from __future__ import annotations

import pytest


@pytest.mark.slow
@pytest.mark.data
def test_the_duplex_seed_2_is_not_taken_for_its_mirror_image() -> None:
    """Seed 2 in lock-step (docs/measurements.md, "The duplex's mirror image taken as the pose"): the walls took
    the half-turned image of the true pose, 2.84 m off, at 18.9 s; the true pose, which fits them as well, had
    not been weighed. Now it ends 'ambiguous' with its rivals drawn, or, localized, within cad_link_m of the
    truth."""
    from macroloc.cli.demo import DemoParams, run_demo
    from tests.conftest import shared_data

    building = shared_data("bim/webifc__duplex.ifc")
    result = run_demo(building, DemoParams(seed=2, lockstep=True, observations="perception"))
    assert result.outcome != "localized wrongly"
    if result.outcome == "ambiguous":
        assert len(result.rivals_xy) >= 2
    else:
        assert result.localized and result.pose_error_m <= 0.5
