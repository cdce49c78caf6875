"""Frame-to-frame / frame-to-keyframe odometry: accuracy on a synthetic sequence, failure fallback, corrections."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from frontend_fixtures import T_W_C_REF, make_frame, make_room
from run_fixtures import assert_same
from lrslam.errors import InputError
from lrslam.frame import Frame
from lrslam.frontend.model_tracking import ModelTrackingConfig
from lrslam.frontend.odometry import Odometry, OdometryConfig
from lrslam.frontend.registration import RegistrationConfig, RegistrationGates, fallback_information
from lrslam.geometry import exp_se3, inv, pose_error


# With the point-to-plane polish each registration is good to ~0.3 mm on the synthetic room, so tight pose
# thresholds check the odometry's bookkeeping (composition, references, fallbacks), not Open3D's bias.
ACCURATE = {"registration": RegistrationConfig(refine_iterations=10)}


def _trajectory(n: int) -> list[np.ndarray]:
    """Smooth camera motion: ~2.4 cm and ~0.7 deg per frame."""
    return [T_W_C_REF @ exp_se3(np.array([0.0, 0.01, 0.004, 0.01, 0.005, 0.02]) * i) for i in range(n)]


@pytest.fixture(scope="module")
def sequence():
    room = make_room()
    return [make_frame(room, T, index=i) for i, T in enumerate(_trajectory(8))]


def _blank(frame: Frame, with_depth: bool) -> Frame:
    depth = np.full_like(frame.depth, 2.0) if with_depth else np.zeros_like(frame.depth)
    return Frame(frame.index, frame.timestamp, np.full_like(frame.rgb, 90), depth, frame.K)


@pytest.mark.parametrize("mode", ["frame", "keyframe"])
def test_tracks_synthetic_sequence(mode, sequence):
    f0 = sequence[0]
    odo = Odometry(OdometryConfig(mode=mode, reference_max_translation=0.05, **ACCURATE), f0.K, f0.height, f0.width)
    odo.reset(f0.T_w_c_gt)  # start in the ground-truth world so errors are absolute
    refs = set()
    for f in sequence:
        r = odo.track(f)
        assert r.ok, r.reason
        d_t, d_r = pose_error(r.T_w_c, f.T_w_c_gt)
        assert d_t < 0.002 and d_r < 0.2, (f.index, d_t, d_r)
        # The relative pose is consistent with the reference it names.
        ref_pose = sequence[r.ref_index].T_w_c_gt
        d_t, d_r = pose_error(r.T_ref_c, inv(ref_pose) @ f.T_w_c_gt)
        assert d_t < 0.002 and d_r < 0.2
        refs.add(r.ref_index)
    if mode == "frame":
        assert refs == set(range(len(sequence) - 1)) | {0}
    else:
        assert 1 < len(refs) < len(sequence) - 1  # the reference switches, but not every frame


@pytest.mark.parametrize("with_depth", [False, True])
def test_unusable_frame_falls_back_to_constant_velocity(with_depth, sequence, caplog):
    caplog.set_level(logging.INFO, logger="lrslam.frontend.odometry")
    f0 = sequence[0]
    odo = Odometry(OdometryConfig(**ACCURATE), f0.K, f0.height, f0.width)
    odo.reset(f0.T_w_c_gt)
    for f in sequence[:3]:
        assert odo.track(f).ok
    predicted = odo.predict()
    bad = odo.track(_blank(sequence[3], with_depth))
    assert not bad.ok and bad.reason
    assert "constant-velocity prediction" in caplog.text
    np.testing.assert_allclose(bad.T_w_c, predicted)
    np.testing.assert_array_equal(bad.information, fallback_information(RegistrationGates()))
    assert bad.ref_index == 2  # the blank frame never becomes the reference
    # The next good frame registers against the last good one and recovers.
    good = odo.track(sequence[4])
    assert good.ok and good.ref_index == 2
    d_t, d_r = pose_error(good.T_w_c, sequence[4].T_w_c_gt)
    assert d_t < 0.002 and d_r < 0.2


def test_first_frame_and_missing_reference(sequence):
    f0 = sequence[0]
    odo = Odometry(OdometryConfig(), f0.K, f0.height, f0.width)
    T0 = exp_se3(np.array([0.1, 0.2, 0.3, 1.0, 2.0, 3.0]))
    first = odo.reset(T0, _blank(f0, with_depth=False))
    assert not first.ok and "first frame" in first.reason
    np.testing.assert_array_equal(first.T_w_c, T0)
    second = odo.track(sequence[1])  # nothing to register to: becomes the reference at the prediction
    assert not second.ok and "no reference" in second.reason
    assert odo.reference_index == 1
    np.testing.assert_allclose(second.T_w_c, T0)
    assert odo.track(sequence[2]).ok


def test_motion_increment_chains_to_the_frontend_pose(sequence):
    f0 = sequence[0]
    odo = Odometry(OdometryConfig(), f0.K, f0.height, f0.width)
    T0 = exp_se3(np.array([0.1, 0.2, 0.3, 1.0, 2.0, 3.0]))
    odo.reset(T0, f0)
    T = T0
    for f in sequence[1:4]:
        r = odo.track(f)
        assert r.ok and r.attempt == "velocity"
        T = T @ r.T_prev_c   # the pipeline's seed: its last pose times the frontend's own increment
        np.testing.assert_allclose(T, r.T_w_c, atol=1e-9)
    np.testing.assert_allclose(odo.last_pose, T, atol=1e-9)
    assert not hasattr(odo, "correct")   # nothing outside writes the frontend's own estimate


def test_failed_velocity_guess_is_retried(sequence):
    """A constant-velocity guess far off (the camera stopped) fails the registration's correction gate; the
    zero-motion retry recovers the frame."""
    f0 = sequence[0]
    cfg = OdometryConfig(gates=RegistrationGates(max_translation=0.05, max_rotation=3.0))
    odo = Odometry(cfg, f0.K, f0.height, f0.width)
    odo.reset(np.eye(4), f0)
    odo._T_w_prev = exp_se3(np.array([0.0, 0.0, 0.0, -0.2, 0.0, 0.0]))  # a 20 cm "velocity" that is not there
    r = odo.track(sequence[1])
    assert r.ok and r.attempt == "zero-motion", (r.attempt, r.reason)
    no_retry = Odometry(cfg.model_copy(update={"retry": False}), f0.K, f0.height, f0.width)
    no_retry.reset(np.eye(4), f0)
    no_retry._T_w_prev = exp_se3(np.array([0.0, 0.0, 0.0, -0.2, 0.0, 0.0]))
    assert not no_retry.track(sequence[1]).ok


def test_repeated_failures_reanchor_the_reference(sequence):
    f0 = sequence[0]
    # every registration fails its gate
    cfg = OdometryConfig(max_consecutive_failures=1, gates=RegistrationGates(min_fitness=0.999))
    odo = Odometry(cfg, f0.K, f0.height, f0.width)
    odo.track(sequence[0])
    assert not odo.track(sequence[1]).ok and odo.reference_index == 0
    assert not odo.track(sequence[2]).ok and odo.reference_index == 2


def test_wrong_frames_are_input_errors(sequence):
    f0 = sequence[0]
    odo = Odometry(OdometryConfig(), f0.K, f0.height, f0.width)
    small = Frame(0, 0.0, f0.rgb[:120], f0.depth[:120], f0.K)
    with pytest.raises(InputError, match="expected 320x240"):
        odo.track(small)
    with pytest.raises(InputError, match="principal point"):
        Odometry(OdometryConfig(), f0.K, 100, 100)


def test_pipeline_can_choose_the_reference(sequence):
    """In keyframe mode with internal switching disabled, the reference changes only when told."""
    f0 = sequence[0]
    cfg = OdometryConfig(mode="keyframe", reference_max_translation=10.0, reference_max_rotation=180.0,
                         reference_min_fitness=0.0, **ACCURATE)
    odo = Odometry(cfg, f0.K, f0.height, f0.width)
    odo.reset(f0.T_w_c_gt)
    for f in sequence[:3]:
        assert odo.track(f).ref_index == 0
    assert odo.use_last_as_reference() and odo.reference_index == 2
    r = odo.track(sequence[3])
    assert r.ok and r.ref_index == 2
    d_t, d_r = pose_error(r.T_w_c, sequence[3].T_w_c_gt)
    assert d_t < 0.002 and d_r < 0.2
    odo.track(_blank(sequence[4], with_depth=False))
    assert not odo.use_last_as_reference() and odo.reference_index == 2


# The flat OdometryConfig before it was split into registration / gates / odometry (34 fields, its defaults).
FLAT_DEFAULTS = {
    "method": "rgbd", "mode": "frame", "depth_min": 0.1, "depth_max": 4.0, "iterations": (20, 10, 5),
    "relative_rmse": 1e-06, "relative_fitness": 1e-06, "depth_outlier_trunc": 0.07, "depth_huber_delta": 0.05,
    "intensity_huber_delta": 0.1, "refine_iterations": 0, "voxel_size": 0.02, "icp_estimation": "point_to_plane",
    "icp_distance_factor": 2.5, "kiss_levels": 4, "kiss_max_points_per_voxel": 20, "kiss_max_iterations": 100,
    "max_correspondence_distance": 0.05, "information_sigma": 0.01, "min_fitness": 0.3, "max_inlier_rmse": 0.03,
    "max_translation": 0.3, "max_rotation": 20.0, "min_valid_depth_fraction": 0.05, "min_intensity_std": 0.01,
    "min_normal_spread": 0.01, "fallback_sigma_translation": 0.2, "fallback_sigma_rotation": 10.0,
    "reference_max_translation": 0.3, "reference_max_rotation": 15.0, "reference_min_fitness": 0.6,
    "max_consecutive_failures": 3, "retry": True, "retry_method": "icp",
}


def test_split_config_keeps_every_flat_default_once():
    d = OdometryConfig().model_dump()
    registration, gates = d.pop("registration"), d.pop("gates")
    assert d.pop("model") == ModelTrackingConfig().model_dump()   # a section added later, not from the flat config
    assert gates.pop("trusted_fitness") == 0.55                     # a gate added later
    assert not (registration.keys() & gates.keys() or registration.keys() & d.keys() or gates.keys() & d.keys())
    assert registration | gates | d == FLAT_DEFAULTS
    assert RegistrationConfig().model_dump() == registration
    assert RegistrationGates().model_dump() == gates | {"trusted_fitness": 0.55}


@pytest.mark.parametrize("model, key", [(OdometryConfig, "min_fitness"), (OdometryConfig, "refine_iterations"),
                                        (RegistrationConfig, "max_translation"), (RegistrationConfig, "retry"),
                                        (RegistrationGates, "method"), (RegistrationGates, "mode"),
                                        (RegistrationGates, "min_fitnes")])
def test_split_configs_reject_keys_of_the_other_sections(model, key):
    with pytest.raises(ValueError, match="Extra inputs are not permitted"):
        model(**{key: FLAT_DEFAULTS.get(key, 0.3)})


def test_odometry_sections_are_typed():
    cfg = OdometryConfig.model_validate({"registration": {"refine_iterations": 10}, "gates": {"min_fitness": 0.4}})
    assert cfg.registration == RegistrationConfig(refine_iterations=10)
    assert cfg.gates == RegistrationGates(min_fitness=0.4)
    with pytest.raises(ValueError, match="Extra inputs are not permitted"):
        OdometryConfig(registration={"min_fitness": 0.3})
    with pytest.raises(ValueError, match="depth_min"):
        OdometryConfig(registration={"depth_min": 5.0})


def test_a_weak_registration_is_kept_but_not_trusted(sequence):
    """``gates.trusted_fitness``: a registration that passes the gates but whose fitness is below it is the
    frontend's estimate all the same (same pose, bit for bit on one Open3D thread) and carries ``trusted`` False;
    the first frame is trusted."""
    from lrslam.pipeline.determinism import open3d_threads

    poses = {}
    for trusted_fitness in (0.0, 1.0):
        odo = Odometry(OdometryConfig(gates=RegistrationGates(trusted_fitness=trusted_fitness)), sequence[0].K,
                       *sequence[0].depth.shape)
        with open3d_threads(True):
            first = odo.reset(T_W_C_REF, sequence[0])
            res = [odo.track(f) for f in sequence[1:4]]
        assert first.trusted
        assert all(r.ok for r in res) and all(0 < r.fitness < 1 for r in res)
        assert all(r.trusted is (trusted_fitness == 0.0) for r in res)
        poses[trusted_fitness] = [r.T_w_c for r in res]
    np.testing.assert_array_equal(poses[0.0], poses[1.0])


def test_a_recorded_pass_is_replayed_without_registering(sequence, monkeypatch):
    """An odometry replaying a recorded pass (the bound pre-pass's, in a fused run) returns the recorded results
    without registering anything and ends in the state registering would have left (bit for bit: the same
    results on one Open3D thread)."""
    import lrslam.frontend.odometry as odometry_module
    from lrslam.pipeline.determinism import open3d_threads

    f0, cfg = sequence[0], OdometryConfig()
    with open3d_threads(True):
        rec = Odometry(cfg, f0.K, f0.height, f0.width, record=True)
        recorded = [rec.reset(T_W_C_REF, f0)] + [rec.track(f) for f in sequence[1:]]
    trace = rec.trace()
    assert [s.result for s in trace.steps] == recorded and all(s.problem is None for s in trace.steps)

    def no_registration(*args, **kwargs):
        raise AssertionError("a replayed frame was registered")

    with monkeypatch.context() as m:
        m.setattr(odometry_module, "register_rgbd", no_registration)
        m.setattr(odometry_module, "frame_problem", no_registration)
        replay = Odometry(cfg, f0.K, f0.height, f0.width, replay=trace)
        replayed = [replay.reset(T_W_C_REF, f0)] + [replay.track(f) for f in sequence[1:]]
    assert replay.replayed == len(sequence)
    assert replayed == recorded
    assert_same(replay.state_dict(), rec.state_dict())
    with pytest.raises(RuntimeError, match="record=True"):
        replay.trace()


def test_a_replay_registers_from_the_first_frame_that_differs(sequence, caplog):
    """A frame whose images are not the recorded ones (or a different config or first pose) ends the replay:
    from there on every frame is registered, with the same results as an odometry that never replayed."""
    from lrslam.pipeline.determinism import open3d_threads

    caplog.set_level(logging.INFO, logger="lrslam.frontend.odometry")
    f0, cfg = sequence[0], OdometryConfig()
    changed = list(sequence)
    changed[4] = _blank(sequence[4], with_depth=True)
    with open3d_threads(True):
        rec = Odometry(cfg, f0.K, f0.height, f0.width, record=True)
        for i, f in enumerate(sequence):
            rec.reset(T_W_C_REF, f) if i == 0 else rec.track(f)
        plain = Odometry(cfg, f0.K, f0.height, f0.width)
        expected = [plain.reset(T_W_C_REF, f0)] + [plain.track(f) for f in changed[1:]]
        replay = Odometry(cfg, f0.K, f0.height, f0.width, replay=rec.trace())
        got = [replay.reset(T_W_C_REF, f0)] + [replay.track(f) for f in changed[1:]]
    assert replay.replayed == 4 and "frame 4 is not the recorded pass's next frame" in caplog.text
    assert not got[4].ok
    for a, b in zip(got, expected):
        np.testing.assert_array_equal(a.T_w_c, b.T_w_c)
        assert (a.ok, a.ref_index, a.reason) == (b.ok, b.ref_index, b.reason)
    assert_same(replay.state_dict(), plain.state_dict())
    for other_cfg, T0 in ((OdometryConfig(retry=False), T_W_C_REF), (cfg, np.eye(4))):
        odo = Odometry(other_cfg, f0.K, f0.height, f0.width, replay=rec.trace())
        odo.reset(T0, f0)
        odo.track(sequence[1])
        assert odo.replayed == 0
