"""Loop closure: a synthetic sequence once around the scene, back at its first pose, tracked by an odometry with
drift injected (every frame's relative motion is the true one times a fixed small error). Without loop closure the
end-to-start error exceeds 5 cm; with it the revisit is verified against the first keyframes with depth, the pose
graph is optimised and the poses and the map are corrected: end-to-start below 1 cm."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from trisplat.data.rgbd_stream import load_frame, open_stream
from trisplat.slam import system
from trisplat.slam.loop import Edge, LoopConfig, extract_features, optimise_pose_graph, verify
from trisplat.slam.system import SlamConfig, run_slam
from trisplat.slam.track import TrackResult
from trisplat.slam.trajectory import read_tum_trajectory

N_LOOP = 25


@pytest.fixture(scope="module")
def loop_capture(tmp_path_factory):
    from tests.slam.rgbd_scene import write_loop_sequence

    return write_loop_sequence(tmp_path_factory.mktemp("synth_loop"), n=N_LOOP)


def _drift() -> np.ndarray:
    D = np.eye(4)
    D[:3, :3] = Rotation.from_rotvec(np.radians(0.3) * np.array([0.2, 1.0, 0.1]) / np.linalg.norm([0.2, 1.0, 0.1])
                                     ).as_matrix()
    D[:3, 3] = [0.004, -0.002, 0.003]
    return D


def _drifting_odometry(monkeypatch, stream) -> None:
    """Replace tracking by an odometry: frame n's pose = frame n-1's current estimate (after any loop correction)
    x the true relative motion x a fixed drift."""
    ref = [f.reference_c2w for f in stream.frames]
    D = _drift()

    def odometry(state, pyr, cfg, n, label, log, **kw):
        c2w = state.c2w[n - 1] @ np.linalg.inv(ref[n - 1]) @ ref[n] @ D
        return TrackResult(np.linalg.inv(c2w), 0.0, 1, True, 1.0, 0.0), False

    monkeypatch.setattr(system, "track_with_relocalisation", odometry)


def _end_to_start(est: np.ndarray, ref: np.ndarray) -> float:
    """Translation error (metres) of the last frame relative to the first, against the reference."""
    E = np.linalg.inv(est[0]) @ est[-1]
    R = np.linalg.inv(ref[0]) @ ref[-1]
    return float(np.linalg.norm((np.linalg.inv(R) @ E)[:3, 3]))


def _run(stream, out, loop: bool, lines: list[str]):
    cfg = SlamConfig(downscale=1, final_iters=0, checkpoint_every=0, eval_every=6, mesh="delaunay",
                     loop=LoopConfig(enabled=loop))
    from trisplat.slam.mapping import MapConfig

    cfg.mapping = MapConfig(iters=10, first_iters=30)
    m = run_slam(stream, out, cfg, log=lambda *a, **k: lines.append(" ".join(map(str, a))))
    _, est = read_tum_trajectory(out / "trajectory.txt")
    return m, est


def _map_error(out, est, stream, born_after: int) -> float:
    """Median distance (metres) to the true mesh of the map's vertices spawned at keyframes >= born_after, moved
    into the reference world by the first frame's pose."""
    import trimesh

    from trisplat.slam.system import load_checkpoint
    from trisplat.synth.scenes import demo_mesh

    st, _ = load_checkpoint(out / "checkpoint.pt")
    faces = st.smap.scene.faces.long()[st.smap.birth >= born_after]
    v = st.smap.scene.positions[faces.reshape(-1)].double().numpy()
    to_world = stream.frames[0].reference_c2w @ np.linalg.inv(est[0])
    v = v @ to_world[:3, :3].T + to_world[:3, 3]
    _, dist, _ = trimesh.proximity.closest_point(demo_mesh(seed=0), v[:: max(1, len(v) // 2000)])
    return float(np.median(dist))


def test_loop_closure_removes_injected_drift(loop_capture, tmp_path, monkeypatch):
    stream = open_stream(loop_capture)
    assert len(stream) == N_LOOP
    ref = np.array([f.reference_c2w for f in stream.frames])
    assert np.allclose(ref[0], ref[-1])  # the path returns to its start
    _drifting_odometry(monkeypatch, stream)

    lines_off: list[str] = []
    m_off, est_off = _run(stream, tmp_path / "off", False, lines_off)
    err_off = _end_to_start(est_off, ref)
    assert err_off > 0.05, err_off
    assert m_off["loop_closures"] == [] and not any("loop closed" in line for line in lines_off)

    lines: list[str] = []
    m_on, est_on = _run(stream, tmp_path / "on", True, lines)
    err_on = _end_to_start(est_on, ref)
    assert err_on < 0.01, (err_on, m_on["loop_closures"])
    closures = m_on["loop_closures"]
    assert closures and any(line.startswith("frame ") and "loop closed" in line for line in lines), lines
    # every accepted loop joins frames that do see the same place: at most ~30 degrees apart on the circle
    assert all(0 < j - i and min(j - i, N_LOOP - 1 - (j - i)) <= 2 for i, j in closures), closures
    # the whole trajectory, not only its end: the drift spread over the loop by the pose graph
    from trisplat.slam.trajectory import ate_rmse

    ate_on, ate_off = ate_rmse(est_on, ref)[0], ate_rmse(est_off, ref)[0]
    assert ate_on < 0.5 * ate_off, (ate_on, ate_off)
    # the map moved with the poses: what the last keyframes spawned lies on the true surface
    late = m_on["keyframes"] - 4
    map_on, map_off = _map_error(tmp_path / "on", est_on, stream, late), _map_error(tmp_path / "off", est_off, stream, late)
    assert map_on < 0.4 * map_off, (map_on, map_off)


def test_verify_accepts_a_true_revisit_and_rejects_a_far_one(loop_capture):
    """Two views 15 degrees apart are verified with the true relative pose (mm); the view from the other side of
    the symmetric scene (whose checkered floor also matches) is refused by the correction gate."""
    stream = open_stream(loop_capture)
    K = stream.K_at(1)
    fr = {i: load_frame(stream, i, 1) for i in (0, 1, 12)}
    F = {i: extract_features(*fr[i], K) for i in fr}
    ref = [stream.frames[i].reference_c2w for i in range(len(stream))]
    rng = np.random.default_rng(0)
    cfg = LoopConfig()
    true = np.linalg.inv(ref[0]) @ ref[1]
    guess = true @ _drift() @ _drift()
    Z, rep = verify(F[0], F[1], fr[0][1], fr[1][1], K, cfg, rng, estimate=guess)
    assert Z is not None, rep
    assert np.linalg.norm(Z[:3, 3] - true[:3, 3]) < 0.005
    far = np.linalg.inv(ref[0]) @ ref[12]
    Z, rep = verify(F[0], F[12], fr[0][1], fr[12][1], K, cfg, rng, estimate=far @ _drift())
    assert Z is None, rep


def test_pose_graph_spreads_a_loop_error_and_keeps_the_first_pose():
    """A square of 4 odometry edges whose chain misses the start by centimetres, closed by an exact loop edge:
    the optimised last pose meets the loop edge, the first keeps its place."""
    bad = np.eye(4)  # a unit square's step with 1 degree too much turn and 1 cm of climb
    bad[:3, :3] = Rotation.from_euler("z", 91, degrees=True).as_matrix()
    bad[:3, 3] = [1.0, 0.0, 0.01]
    poses = [np.eye(4)]
    for _ in range(4):
        poses.append(poses[-1] @ bad)
    edges = [Edge(k, k + 1, bad, False) for k in range(4)] + [Edge(0, 4, np.eye(4), True)]
    out, rep = optimise_pose_graph(poses, edges, LoopConfig())
    assert np.linalg.norm(poses[4][:3, 3]) > 0.05
    assert np.allclose(out[0], np.eye(4))
    assert np.linalg.norm(out[4][:3, 3]) < 0.002 and rep["cost_after"] < rep["cost_before"]


def test_pose_graph_jacobian_matches_finite_differences():
    """The analytic Jacobian of the pose graph's residuals against central differences, away from x = 0 (large
    rotations included), with odometry and loop edges and edges to the fixed first node both ways round."""
    from trisplat.slam.loop import _Graph, _jacobian, _residuals

    rng = np.random.default_rng(3)
    n = 6
    poses = []
    for _ in range(n):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(rng.normal(0, 1.0, 3)).as_matrix()
        T[:3, 3] = rng.normal(0, 1.0, 3)
        poses.append(T)
    edges = []
    for i, j, loop in [(0, 1, False), (1, 2, False), (2, 3, False), (3, 4, False), (4, 5, False), (0, 4, True),
                       (2, 5, True), (5, 0, True)]:
        Z = np.eye(4)
        Z[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.8, 3)).as_matrix()
        Z[:3, 3] = rng.normal(0, 0.5, 3)
        edges.append(Edge(i, j, Z, loop))
    g = _Graph.of(np.array(poses), edges, {False: (0.02, 0.03), True: (0.05, 0.1)})
    x = rng.normal(0, 0.4, 6 * (n - 1))
    J = _jacobian(x, g).toarray()
    h = 1e-6
    num = np.stack([(_residuals(x + h * e, g) - _residuals(x - h * e, g)) / (2 * h) for e in np.eye(len(x))], 1)
    assert J.shape == num.shape
    np.testing.assert_allclose(J, num, rtol=1e-5, atol=1e-5 * np.abs(num).max())
    assert not np.allclose(J, 0)


def test_frames_between_keyframes_follow_their_two_keyframes_corrections():
    """apply_pose_correction: a frame between keyframes k and k + 1 gets the correction interpolated by its place in
    between (translation linearly, rotation along the geodesic); one after the newest keyframe gets that keyframe's;
    the keyframes land exactly on their new poses."""
    from types import SimpleNamespace

    from trisplat.slam.mapping import Keyframe

    def pose(x, yaw_deg=0.0):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
        T[0, 3] = x
        return T

    c2w = [pose(0.1 * n) for n in range(8)]  # frames 0..7 along x; keyframes at 0, 3 and 6
    kf_ids = [0, 3, 6]
    state = SimpleNamespace(c2w=[m.copy() for m in c2w], keyframe_ids=kf_ids, smap=SimpleNamespace(num_faces=0))
    keyframes = [Keyframe(n, None, None, c2w[n].copy()) for n in kf_ids]
    # corrections: none at keyframe 0, +3 cm in y and 6 degrees of yaw about the frame's centre at keyframe 3,
    # +6 cm in y and 12 degrees at keyframe 6
    new = []
    for k, n in enumerate(kf_ids):
        C = pose(0.0, 6.0 * k)
        C[:3, 3] = c2w[n][:3, 3] - C[:3, :3] @ c2w[n][:3, 3] + np.array([0.0, 0.03 * k, 0.0])
        new.append(C @ c2w[n])
    system.apply_pose_correction(state, keyframes, new, move_map=False)
    for k, n in enumerate(kf_ids):
        np.testing.assert_allclose(state.c2w[n], new[k], atol=1e-12)
        np.testing.assert_allclose(keyframes[k].c2w, new[k], atol=1e-12)
    for n in (1, 2, 4, 5):
        yaw = np.degrees(Rotation.from_matrix(state.c2w[n][:3, :3]).as_euler("zyx")[0])
        assert yaw == pytest.approx(2.0 * n, abs=1e-9), n  # 6 degrees per 3 frames
    # translation: the interpolated correction moves frame 1 a third of the way to keyframe 3's correction
    C0, C1 = new[0] @ np.linalg.inv(c2w[0]), new[1] @ np.linalg.inv(c2w[3])
    half = system.interpolate_correction(C0, C1, 1 / 3)
    np.testing.assert_allclose(state.c2w[1], half @ c2w[1], atol=1e-12)
    np.testing.assert_allclose(state.c2w[7], (new[2] @ np.linalg.inv(c2w[6])) @ c2w[7], atol=1e-12)
    # the ends of the interpolation are the corrections themselves
    np.testing.assert_allclose(system.interpolate_correction(C0, C1, 0.0), C0, atol=1e-12)
    np.testing.assert_allclose(system.interpolate_correction(C0, C1, 1.0), C1, atol=1e-12)
