"""The virtual lab executes a given probe path: kinematics follow it, the truth presses
where it presses, and bad paths are refused before anything is written."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from core.io import read_session, read_truth
from core.lab import Intrinsics, LabConfig, LabError, generate_session
from core.lab.probing import penetration_depth, plan_from_path

SIZE = np.array([0.0687, 0.0393, 0.0358])
R = 0.005

# 2 sequences at 5 Hz, 160 x 120, coarse truth; sequence_durations are replaced by the paths
LAB = LabConfig(
    sequence_durations=(1.0, 1.0),
    sequence_roles=("train", "test"),
    camera_rate_hz=5.0,
    kinematics_rate_hz=100.0,
    intrinsics=Intrinsics.from_fov(160, 120, 64.0),
    grid=(10, 5, 5),
    dt=1.0 / 60.0,
    newton_iterations=1,
    reference_frames=1,
    workers=0,
)


def top_press(depth=0.005, x=0.035, y=0.02, duration=5.0, rate=50.0):
    """A path sampled at ``rate`` Hz: 1 s clear above the top, down to ``depth`` below the
    rest surface by 2 s, held to 3.5 s, back up by 4.5 s; (t, centres, pressing mask)."""
    t = np.arange(0.0, duration + 1e-9, 1.0 / rate)
    z_clear, z_pressed = SIZE[2] + R + 0.005, SIZE[2] + R - depth
    z = np.interp(t, [0.0, 1.0, 2.0, 3.5, 4.5, duration], [z_clear, z_clear, z_pressed, z_pressed, z_clear, z_clear])
    centres = np.stack([np.full_like(t, x), np.full_like(t, y), z], axis=1)
    return t, centres


def slide(duration=4.0):
    """Pressed 3 mm into the top while sliding 10 mm along x."""
    t = np.linspace(0.0, duration, 81)
    x = np.interp(t, [0.0, 1.0, 3.0, duration], [0.025, 0.025, 0.035, 0.035])
    z = np.interp(t, [0.0, 0.8, 1.0, 3.0, 3.2, duration],
                  [SIZE[2] + R + 0.004, SIZE[2] + R + 0.004, SIZE[2] + R - 0.003, SIZE[2] + R - 0.003,
                   SIZE[2] + R + 0.004, SIZE[2] + R + 0.004])
    return t, np.stack([x, np.full_like(t, 0.02), z], axis=1)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    paths = [top_press(), slide()]
    out = generate_session(tmp_path_factory.mktemp("paths") / "s", preset=LAB, seed=4, with_force=True,
                           effects=[{"kind": "gravity"}], paths=paths)
    return out, paths


def test_kinematics_reproduce_the_given_path(session):
    path, paths = session
    s = read_session(path)
    truth = read_truth(path)
    T = np.asarray(truth["T_phantom_robot"])
    sigma = truth["kinematics"]["encoder_noise"]
    for q, tq, (t, c) in zip(s.sequences.values(), truth["sequences"], paths):
        assert tq["duration"] == t[-1] and tq["pokes"] == []
        k = q.kinematics
        assert k.t[-1] == pytest.approx(t[-1])
        p = k.position @ T[:3, :3].T + T[:3, 3]
        expected = np.stack([np.interp(k.t, t, c[:, j]) for j in range(3)], axis=1)  # linear in between
        err = p - expected
        # only the encoder noise (per axis, rotation-invariant): 6 sigma bounds every sample
        assert np.abs(err).max() < 6 * sigma
        assert err.std() == pytest.approx(sigma, rel=0.1)
        # tool: shaft tilted 25 degrees from vertical, pointing away from the camera
        z_tool = T[:3, :3] @ Rotation.from_quat(k.quaternion[0]).as_matrix()[:, 2]
        assert -z_tool[2] == pytest.approx(np.cos(np.radians(25.0)), abs=1e-9)
        cam = np.asarray(truth["T_phantom_camera"])[:2, 3] - SIZE[:2] / 2
        assert float(-z_tool[:2] @ cam) < 0.0


def test_truth_force_is_there_while_the_path_presses_the_top(session):
    path, paths = session
    s = read_session(path)
    truth = read_truth(path)
    T = np.asarray(truth["T_phantom_robot"])
    noise = truth["kinematics"]["force_noise"]
    for q, (t, c) in zip(s.sequences.values(), paths):
        k = q.kinematics
        f = np.linalg.norm(k.force @ T[:3, :3].T, axis=1)
        depth = penetration_depth(np.stack([np.interp(k.t, t, c[:, j]) for j in range(3)], axis=1), SIZE, R)
        pressing = depth > 0.002
        clear = depth < -0.002
        assert pressing.sum() > 50 and clear.sum() > 50
        # 3-5 mm into a 5 kPa gel: ~0.2-0.5 N; clear of it: only the noise (|3 x N(0, s)| < 5 s)
        assert np.median(f[pressing]) > 0.1
        assert np.median(f[clear]) < 3 * noise
        assert np.max(f[clear]) < 6 * noise
        # the top is pressed downwards: the force on the phantom points down
        fz = (k.force @ T[:3, :3].T)[:, 2]
        assert np.median(fz[pressing]) < -0.1
    assert all(q["max_contact_force"] > 0.1 for q in truth["sequences"])


def test_bad_paths_are_refused_before_anything_is_written(tmp_path):
    out = tmp_path / "x"
    good = top_press()
    cases = [
        ([good], "2 sequences"),
        ([good, (good[0], good[1][:, :2])], "centres must be"),
        ([good, (good[0][:, None], good[1])], r"times must be \(K,\)"),
        ([good, (good[0][::-1].copy(), good[1])], "strictly increasing"),
        ([good, top_press(depth=0.016)], "16.0 mm deep"),
        ([good, (good[0], np.where(np.isfinite(good[1]), good[1], 0) * np.nan)], "finite"),
        ([good, good[0]], "pair"),
    ]
    for paths, message in cases:
        with pytest.raises(LabError, match=message):
            generate_session(out, preset=LAB, seed=0, paths=paths)
    assert not out.exists()


def test_plan_from_path_checks_the_segments_between_points():
    """Two points clear of the box whose straight segment cuts 17 mm deep through an edge
    (the centre passes 12 mm inside at the middle)."""
    t = np.array([0.0, 1.0])
    c = np.array([[-0.006, 0.02, SIZE[2] - 0.03], [0.03, 0.02, SIZE[2] + 0.006]])
    assert penetration_depth(c, SIZE, R).max() < 0.0
    with pytest.raises(ValueError, match="17.0 mm deep"):
        plan_from_path(t, c, size=SIZE, radius=R, tool_azimuth=0.0)
    plan = plan_from_path(t, c + [0, 0, 0.02], size=SIZE, radius=R, tool_azimuth=0.0)
    assert plan.pokes == () and plan.duration == 1.0
    np.testing.assert_allclose(plan.trajectory(np.array([0.5]))[0], c.mean(0) + [0, 0, 0.02])  # linear
