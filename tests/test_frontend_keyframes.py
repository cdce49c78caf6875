"""Keyframe policy and the view-overlap estimate (closed forms on a fronto-parallel plane)."""

from __future__ import annotations

import numpy as np
import pytest

from lrslam.camera import intrinsics_matrix
from lrslam.errors import InputError
from lrslam.frontend.keyframes import KeyframeConfig, KeyframePolicy, view_overlap
from lrslam.geometry import exp_se3, make_pose

H, W = 120, 160
K = intrinsics_matrix(100.0, 100.0, (W - 1) / 2, (H - 1) / 2)
PLANE = np.full((H, W), 2.0, dtype=np.float32)  # fronto-parallel wall 2 m ahead


def _shift(x: float) -> np.ndarray:
    return make_pose(np.eye(3), [x, 0.0, 0.0])


def test_overlap_closed_forms():
    assert view_overlap(PLANE, K, np.eye(4), K, np.eye(4), (H, W)) == 1.0
    # Moving sideways by half the field of view at 2 m: exactly the right half of view a stays inside b.
    half = 2.0 * (W / 2) / K[0, 0]
    assert view_overlap(PLANE, K, np.eye(4), K, _shift(half), (H, W), stride=1) == pytest.approx(0.5, abs=0.01)
    # Turned around: nothing in front of b.
    back = make_pose(np.diag([-1.0, 1.0, -1.0]), [0, 0, 0])
    assert view_overlap(PLANE, K, np.eye(4), K, back, (H, W)) == 0.0
    assert view_overlap(np.zeros((H, W)), K, np.eye(4), K, np.eye(4), (H, W)) == 0.0


def test_overlap_respects_occlusion():
    # b sees a closer wall (1 m) where a sees the 2 m wall: a's points are hidden from b.
    near = np.full((H, W), 1.0, dtype=np.float32)
    assert view_overlap(PLANE, K, np.eye(4), K, np.eye(4), (H, W), depth_b=near) == 0.0
    assert view_overlap(PLANE, K, np.eye(4), K, np.eye(4), (H, W), depth_b=PLANE) == 1.0


def _ask(policy, history, index, T, *args, **kw):
    """The pipeline's role: hand the policy the last keyframe's current pose (``history`` = the poses owner)."""
    last = policy.last_keyframe_index
    out = policy.is_keyframe(index, T, None if last is None else history[last], *args, **kw)
    if out[0] and kw.get("commit", True):
        history[index] = T
    return out


def test_policy_decisions():
    policy, h = KeyframePolicy(KeyframeConfig(min_translation=0.1, min_rotation=10.0, max_overlap=0.8,
                                              every_n=10)), {}
    assert _ask(policy, h, 0, np.eye(4)) == (True, "first keyframe")
    ok, why = _ask(policy, h, 1, _shift(0.05))
    assert not ok and "moved 0.050 m" in why
    ok, why = _ask(policy, h, 2, _shift(0.12))
    assert ok and "moved" in why and policy.last_keyframe_index == 2
    ok, why = _ask(policy, h, 3, _shift(0.12) @ exp_se3(np.array([0, np.radians(12), 0, 0, 0, 0])))
    assert ok and "turned" in why
    pose = _shift(0.12) @ exp_se3(np.array([0, np.radians(12), 0, 0, 0, 0]))
    ok, why = _ask(policy, h, 13, pose)
    assert ok and "10 frames" in why
    # commit=False only asks.
    assert _ask(policy, h, 20, pose @ _shift(0.5), commit=False)[0]
    assert policy.last_keyframe_index == 13
    # never sooner than min_frames after the last keyframe
    policy, h = KeyframePolicy(KeyframeConfig(min_translation=0.1, min_frames=3)), {}
    _ask(policy, h, 0, np.eye(4))
    ok, why = _ask(policy, h, 2, _shift(0.5))
    assert not ok and "< 3" in why
    assert _ask(policy, h, 3, _shift(0.5))[0]


def test_overlap_criterion_uses_the_given_keyframe_pose():
    policy, h = KeyframePolicy(KeyframeConfig(min_translation=0, min_rotation=0, max_overlap=0.8, every_n=0,
                                              overlap_stride=1)), {}
    _ask(policy, h, 0, np.eye(4), PLANE, K)
    # Sideways at 2 m, 1 cm = 0.5 px: 0.1 m keeps 1 - 5/160 of the view; 1 m keeps 1 - 50/160 = 0.69.
    ok, why = _ask(policy, h, 1, _shift(0.1), PLANE, K)
    assert not ok and "overlap 0.97" in why
    ok, why = _ask(policy, h, 2, _shift(1.0), PLANE, K)
    assert ok and "overlap 0.69" in why
    # The graph moved keyframe 2 onto frame 3's pose (in the owner): full overlap again, nothing to sync.
    h[2] = _shift(1.5)
    ok, why = _ask(policy, h, 3, _shift(1.5), PLANE, K)
    assert not ok and "overlap 1.00" in why
    with pytest.raises(InputError, match="rigid"):
        _ask(policy, h, 4, np.ones((4, 4)))
