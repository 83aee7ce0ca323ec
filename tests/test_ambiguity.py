"""When a relocalization is refused (services.relocalize.ambiguity, shared by Render & Match and the P&L client).
The tracker-level cases (a site of look-alike copies, a rival turned on the spot) are in test_render_match.py."""

import numpy as np

from services.geometry.se3 import Pose, rotvec_to_rotmat
from services.relocalize.ambiguity import rival

HERE = Pose(np.eye(3), np.zeros(3))


def at(x: float, yaw_deg: float = 0.0) -> Pose:
    return Pose(rotvec_to_rotmat([0.0, 0.0, np.radians(yaw_deg)]), np.array([x, 0.0, 0.0]))


def test_a_second_place_about_as_good_is_a_rival_and_the_same_place_is_not():
    assert rival(HERE, 100, [(at(0.3, 5), 95, None)]) is None  # the same place, estimated twice
    assert rival(HERE, 100, [(at(6.0), 79, None)]) is None
    assert "6.0 m" in rival(HERE, 100, [(at(6.0), 80, None)])


def test_with_no_recent_pose_several_look_alikes_far_away_make_a_repetitive_site():
    far = [(at(13.0), 23, None), (at(21.0), 21, None), (at(34.0), 20, None)]  # the warehouse's frame 2, against 39
    assert rival(HERE, 39, far) is None  # near a recent pose the old margin: not ambiguous
    assert "places" in rival(HERE, 39, far, far_ambiguity=0.5)
    assert rival(HERE, 55, [(at(7.3, 180), 28, None)], far_ambiguity=0.5) is None  # one alone can be chance
    # two "look-alikes" at one place count once
    assert rival(HERE, 39, [(at(13.0), 23, None), (at(13.2, 3), 22, None)], far_ambiguity=0.5) is None


def test_a_rival_within_two_metres_is_asked_about_not_counted():
    turned = [(at(0.4, 91), 32, "turned on the spot")]  # office frame 90: 32 inliers against 38
    assert rival(HERE, 38, turned) is not None  # counted, it refuses the frame
    asked = []
    assert rival(HERE, 38, turned, verify=lambda tag: asked.append(tag) or False) is None
    assert asked == ["turned on the spot"]
    assert "verified" in rival(HERE, 38, turned, verify=lambda tag: True)
    # beyond 2 m nobody is asked
    assert rival(HERE, 38, [(at(3.0), 32, None)], verify=lambda tag: 1 / 0) is not None


def test_a_far_rival_is_asked_about_only_by_who_can_render_there():
    """Office seed 90's cold frames 151 and 156: 56 and 44 coarse inliers at a place 6 m / 90-100 deg away, against 64
    and 53. Refused unseen without ``verify_far``; with it, refused only when the place is confirmed there (the
    warehouse's wrong aisle was: a look-alike), and a chance fit no render confirms leaves the best place standing."""
    far = [(at(6.1, 92), 56, "6 m away")]
    assert rival(HERE, 64, far, verify=lambda tag: False) is not None  # (``verify`` is for near rivals only)
    asked = []
    assert rival(HERE, 64, far, verify_far=lambda tag: asked.append(tag) or False) is None
    assert asked == ["6 m away"]
    assert "verified too" in rival(HERE, 64, far, verify_far=lambda tag: True)
    near = [(at(0.4, 91), 55, "near")]
    assert rival(HERE, 64, near, verify_far=lambda tag: 1 / 0) is not None  # (and ``verify_far`` for far ones only)
