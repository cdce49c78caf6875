"""Loop closure: candidates by pose and overlap, verification by registration, rejection of false candidates."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from frontend_fixtures import T_W_C_REF, look_at, make_frame, make_room
from lrslam.errors import InputError
from lrslam.backend.loop_closure import LoopCloser, LoopClosureConfig
from lrslam.geometry import exp_se3, inv, pose_error


@pytest.fixture(scope="module")
def scene():
    """Keyframe 0 at the reference view, keyframes 1-5 looking elsewhere, keyframe 6 back near keyframe 0."""
    room = make_room()
    away = [look_at(np.array([x, -0.3, 0.0]), np.array([x + dx, 0.2, -2.0]))
            for x, dx in ((-1.0, 0.5), (-0.5, 1.0), (0.0, 0.3), (0.5, -1.0), (1.0, -0.5))]
    back = T_W_C_REF @ exp_se3(np.array([0.02, -0.05, 0.03, 0.08, -0.03, 0.05]))
    poses = [T_W_C_REF] + away + [back]
    return room, [make_frame(room, T, index=i) for i, T in enumerate(poses)]


def _closer(frames, cfg=LoopClosureConfig()) -> LoopCloser:
    closer = LoopCloser(cfg)
    for f in frames[:6]:
        closer.add_keyframe(f.index, f)
    return closer


def _poses(frames, T6):
    """The owner's keyframe poses: ground truth for the stored keyframes, ``T6`` for the new one."""
    return {f.index: f.T_w_c_gt for f in frames[:6]} | {6: T6}


def test_revisit_is_detected_and_verified(scene, caplog):
    caplog.set_level(logging.INFO, logger="lrslam.backend.loop_closure")
    _, frames = scene
    closer = _closer(frames)
    kf = frames[6]
    drift = exp_se3(np.array([0.01, 0.03, -0.02, 0.04, -0.02, 0.03]))  # ~5.4 cm, 2.1 deg of accumulated drift
    loops = closer.detect(6, kf, _poses(frames, kf.T_w_c_gt @ drift))
    assert [(c.i, c.j) for c in loops] == [(0, 6)]
    c = loops[0]
    assert c.correction_m == pytest.approx(pose_error(inv(frames[0].T_w_c_gt) @ kf.T_w_c_gt @ drift, c.T_i_j)[0])
    assert 0.03 < c.correction_m < 0.08  # the drift the loop corrects
    d_t, d_r = pose_error(c.T_i_j, inv(frames[0].T_w_c_gt) @ kf.T_w_c_gt)
    assert d_t < 0.003 and d_r < 0.3, (d_t, d_r)  # at half resolution (160x120)
    assert c.fitness > 0.5 and c.rmse < 0.015
    assert np.linalg.eigvalsh(c.information)[0] > 0
    assert "loop 0-6 accepted" in caplog.text
    # Stored keyframes keep their images only: nothing derived (pyramids, normals) piles up per keyframe.
    assert all(not kf.view.cache for kf in closer._kfs.values())
    from lrslam.pipeline.determinism import open3d_threads

    with open3d_threads(True):  # rebuilt, the same bit for bit (Open3D on one thread)
        first, second = (closer.detect(6, kf, _poses(frames, kf.T_w_c_gt @ drift)) for _ in range(2))
        assert np.array_equal(first[0].T_i_j, second[0].T_i_j)


def test_false_candidate_is_rejected_with_a_reason(scene, caplog):
    caplog.set_level(logging.INFO, logger="lrslam.backend.loop_closure")
    room, frames = scene
    closer = _closer(frames)
    # Drift claims this keyframe sits next to keyframe 0, but its images show another part of the room.
    elsewhere = make_frame(room, look_at(np.array([0.3, 0.0, 0.5]), np.array([2.0, 0.3, 1.0])), index=6)
    assert [i for i, _ in closer.candidates(6, elsewhere, _poses(frames, frames[0].T_w_c_gt))] == [0]
    loops = closer.detect(6, elsewhere, _poses(frames, frames[0].T_w_c_gt))
    assert loops == []
    assert [i for i, _ in closer.rejections] == [0] and closer.rejections[0][1]
    assert "loop 0-6 rejected" in caplog.text


def test_recent_and_distant_keyframes_are_not_candidates(scene):
    _, frames = scene
    kf = frames[6]
    # Everything recent: no candidate at all.
    closer = _closer(frames, LoopClosureConfig(exclude_last=6))
    assert closer.candidates(6, kf, _poses(frames, kf.T_w_c_gt)) == []
    # Estimated far from keyframe 0: no candidate.
    closer = _closer(frames)
    far = kf.T_w_c_gt.copy()
    far[:3, 3] += [3.0, 0.0, 0.0]
    assert closer.candidates(6, kf, _poses(frames, far)) == []
    assert [i for i, _ in closer.candidates(6, kf, _poses(frames, kf.T_w_c_gt))] == [0]


def test_poses_come_from_the_caller_and_bad_input(scene):
    _, frames = scene
    closer = _closer(frames)
    moved = frames[0].T_w_c_gt.copy()
    moved[:3, 3] += [5.0, 0.0, 0.0]
    poses = _poses(frames, frames[6].T_w_c_gt) | {0: moved, 99: np.eye(4)}  # unknown ids are ignored
    assert closer.candidates(6, frames[6], poses) == []
    with pytest.raises(InputError, match="added twice"):
        closer.add_keyframe(0, frames[0])
    with pytest.raises(InputError, match="rigid"):
        closer.detect(7, frames[6], {7: np.zeros((4, 4))})
    with pytest.raises(InputError, match="no pose given"):
        closer.detect(7, frames[6], {})


def test_orb_appearance_check(scene):
    room, frames = scene
    closer = _closer(frames, LoopClosureConfig(use_orb=True, min_orb_matches=30))
    assert [(c.i, c.j) for c in closer.detect(6, frames[6], _poses(frames, frames[6].T_w_c_gt))] == [(0, 6)]
    elsewhere = make_frame(room, look_at(np.array([0.3, 0.0, 0.5]), np.array([2.0, 0.3, 1.0])), index=6)
    assert closer.detect(6, elsewhere, _poses(frames, frames[0].T_w_c_gt)) == []
    assert "ORB matches" in closer.rejections[0][1]  # rejected before any registration


def test_verification_registration_keeps_the_loop_defaults():
    """Same numbers as before the split (an odometry config with 30/20/10 iterations and 0.5 m / 30 deg of
    correction); a partial section overrides those, not the generic defaults."""
    from lrslam.frontend.registration import RegistrationConfig, RegistrationGates

    c = LoopClosureConfig()
    assert c.registration == RegistrationConfig(iterations=(30, 20, 10))
    assert c.gates == RegistrationGates(max_translation=0.5, max_rotation=30.0)
    part = LoopClosureConfig.model_validate({"registration": {"refine_iterations": 5},
                                             "gates": {"max_rotation": 25.0}})
    assert part.registration == RegistrationConfig(iterations=(30, 20, 10), refine_iterations=5)
    assert part.gates == RegistrationGates(max_translation=0.5, max_rotation=25.0)
    with pytest.raises(ValueError):
        LoopClosureConfig.model_validate({"gates": {"method": "icp"}})


def test_seven_scenes_loops_are_registered_on_depth_alone(scene):
    """7-Scenes colour is registered to its depth only approximately: its presets register a loop on depth alone
    (ICP), so a colour image shifted 8 px against its depth (both keyframes, as a misplaced colour camera) leaves
    the loop as it was, while the RGB-D registration's photometric term pulls it off by more than twice as much."""
    from dataclasses import replace

    from lrslam.pipeline.config import build_config
    from lrslam.pipeline.determinism import open3d_threads

    _, frames = scene
    shifted = [replace(f, rgb=np.roll(f.rgb, 8, axis=1)) for f in frames]
    truth = inv(frames[0].T_w_c_gt) @ frames[6].T_w_c_gt
    drift = exp_se3(np.array([0.01, 0.03, -0.02, 0.04, -0.02, 0.03]))
    errors = {}
    with open3d_threads(True):
        for preset in ("7scenes-cpu", "7scenes", "tum-cpu"):
            cfg = build_config(preset).loop_closure
            for name, fs in (("registered", frames), ("shifted", shifted)):
                loops = _closer(fs, cfg).detect(6, fs[6], _poses(fs, fs[6].T_w_c_gt @ drift))
                assert [(c.i, c.j) for c in loops] == [(0, 6)], (preset, name)
                errors[preset, name] = pose_error(loops[0].T_i_j, truth)[0]
    for preset in ("7scenes-cpu", "7scenes"):
        assert errors[preset, "shifted"] == errors[preset, "registered"] < 0.003, errors
    assert errors["tum-cpu", "shifted"] > 2 * errors["7scenes-cpu", "shifted"], errors
