"""Where a camera can have walked (services.relocalize.reach): the floor plan of a scan and walks through free space."""

import numpy as np

from services.relocalize.reach import FloorPlan


def _aisles(gap_at: float | None = None) -> np.ndarray:
    """A scan of a floor (z = 0, 20 x 12 m) with two rack rows 2.2 m high along x at y = 4 and y = 8 (0.4 m deep),
    from x = 0 to 20 unless ``gap_at`` leaves a 2 m cross-aisle there; a ceiling lamp 3 m up over the first aisle."""
    rng = np.random.default_rng(0)
    floor = np.column_stack([rng.uniform(0, 20, 60000), rng.uniform(0, 12, 60000), np.zeros(60000)])
    racks = []
    for y in (4.0, 8.0):
        p = np.column_stack([rng.uniform(0, 20, 40000), rng.uniform(y - 0.2, y + 0.2, 40000), rng.uniform(0, 2.2, 40000)])
        if gap_at is not None:
            p = p[np.abs(p[:, 0] - gap_at) > 1.0]
        racks.append(p)
    lamp = np.column_stack([rng.uniform(9, 11, 500), rng.uniform(1.5, 2.5, 500), np.full(500, 3.0)])
    return np.concatenate([floor, *racks, lamp])


def test_the_next_aisle_is_further_on_foot_than_in_a_straight_line():
    plan = FloorPlan.from_points(_aisles())
    a, same, next_ = np.array([10.0, 2.0, 1.5]), np.array([16.0, 2.0, 1.5]), np.array([10.0, 6.0, 1.5])
    assert plan.walkable_within(a, same, 7.0)  # along its own aisle, under the lamp (above head height)
    assert not plan.walkable_within(a, same, 5.0)  # further than the camera can have gone
    assert not plan.walkable_within(a, next_, 7.0)  # 4 m in a straight line, but the racks are in the way
    # round the end of the rows at x = 20 and back: ~20.7 m
    assert not plan.walkable_within(a, next_, 19.0) and plan.walkable_within(a, next_, 23.0)
    # through a cross-aisle at x = 13-15, round the rack end at x = 13: ~7.4 m
    plan = FloorPlan.from_points(_aisles(gap_at=14.0))
    assert plan.walkable_within(a, next_, 8.0) and not plan.walkable_within(a, next_, 6.0)


def test_survey_coordinates_keep_their_precision_and_unscanned_parts_are_free():
    """A scan in UTM-like coordinates (xyz relative to its origin, as services.io.scan.Scan holds them): the plan works
    in world coordinates without float32 rounding; and where the scan saw nothing, the camera may walk."""
    xyz = _aisles().astype(np.float32)
    origin = np.array([512_000.0, 5_402_000.0, 300.0])
    plan = FloorPlan.from_points(xyz, origin)
    a, next_ = origin + [10.0, 2.0, 1.5], origin + [10.0, 6.0, 1.5]
    assert not plan.walkable_within(a, next_, 7.0)
    assert plan.walkable_within(a, origin + [10.0, -5.0, 1.5], 7.5)  # beyond the scan's edge: unknown, so free
    # a camera right beside a rack still starts its walk
    assert plan.walkable_within(origin + [10.0, 3.75, 1.5], a, 2.5)
