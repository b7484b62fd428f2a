"""Partitioned training on Ray (trisplat.blocks), end to end on a tiny synthetic street: one connected surface out of
the merged blocks, a block whose worker is killed resumes from its checkpoint and ends exactly as if it had never
been killed, and a cluster of two Ray nodes on loopback spreads the blocks over both with the local run's result."""
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import pytest

ray = pytest.importorskip("ray")

from trisplat import run as layout  # noqa: E402
from trisplat.cli import main  # noqa: E402

STEPS = 40
TINY = ["--preset", "fast", "--steps", str(STEPS), "--sh-degree", "1", "--init-random-points", "200",
        "--init-max-points", "600", "--log-every", "1", "--eval-every", "0.5", "--eval-max-views", "1",
        "--num-renders", "1", "--eval-supersample", "1", "--texture-size", "0", "--quiet", "--blocks", "2",
        "--chunk-steps", "10"]


@pytest.fixture(scope="module")
def street(tmp_path_factory):
    from trisplat.synth.street import write_street_scene

    return write_street_scene(tmp_path_factory.mktemp("street") / "capture", n_objects=3, views_per_object=6,
                              width=48, height=32, samples_per_pixel=1, n_points=900)


@pytest.fixture(scope="module")
def local_run(street, tmp_path_factory):
    """The reference: 2 blocks on local Ray (2 CPUs), merged."""
    run = tmp_path_factory.mktemp("local") / "run"
    ray.shutdown()
    os.environ.pop("RAY_ADDRESS", None)
    try:
        assert main(["train", str(street), "--out", str(run), *TINY]) == 0
    finally:
        ray.shutdown()
    return run


def _mesh(run: Path):
    import trimesh

    return trimesh.load(run / "mesh.ply", process=False)


def _logged_steps(run: Path) -> list[int]:
    lines = (run / layout.HISTORY).read_text().splitlines()
    return [json.loads(x)["step"] for x in lines if x.strip() and "loss" in json.loads(x)]


def _block_positions(run: Path, name: str) -> np.ndarray:
    from trisplat.io import load_model_ply

    scene, _ = load_model_ply(run / "blocks" / name / layout.MODEL)
    return scene.positions.numpy()


def test_two_blocks_merge_into_one_connected_surface(local_run, street):
    from trisplat.blocks.partition import Plan
    from trisplat.mesh.stats import mesh_statistics

    m = json.loads((local_run / layout.METRICS).read_text())
    info = json.loads((local_run / "blocks.json").read_text())
    assert [r["steps"] for r in info["results"]] == [STEPS, STEPS]
    assert m["connected"] is True and m["blocks"]["count"] == 2
    mesh = _mesh(local_run)
    st = mesh_statistics(np.asarray(mesh.vertices), np.asarray(mesh.faces))
    assert st.largest_component_fraction >= 0.95
    assert st.non_manifold_edges == 0
    # the surface runs across the seam: faces with corners in both cells, in the scene's normalised frame
    plan = Plan.from_dict(info["plan"])
    from trisplat.io import load_model_ply

    scene, _ = load_model_ply(local_run / layout.MODEL)
    assert scene.linear_light  # a connected surface: rendered as a viewer shows its colours
    pos, faces = scene.positions.numpy().astype(np.float64), scene.faces.numpy()
    cell = plan.cell_of(pos)
    assert set(np.unique(cell)) == {0, 1}
    across = (cell[faces].min(1) == 0) & (cell[faces].max(1) == 1)
    assert across.sum() > 10
    # no face doubled in the margins: no two faces at the same place
    centroids = np.round(pos[faces].mean(1), 6)
    assert len(np.unique(centroids, axis=0)) == len(faces)
    # a normal run folder: eval and export work on it
    assert main(["eval", str(local_run), "--out", str(local_run.parent / "eval"), "--no-report"]) == 0
    assert json.loads((local_run.parent / "eval" / "metrics.json").read_text())["psnr"] > 10
    assert main(["export", str(local_run), "--out", str(local_run.parent / "exported")]) == 0
    assert any((local_run.parent / "exported").iterdir())


def test_killed_block_worker_resumes_from_its_checkpoint(local_run, street, tmp_path):
    run = tmp_path / "run"
    progress = run / "blocks" / "block_00" / "progress.json"
    ray.shutdown()
    rc: list[int] = []
    job = threading.Thread(target=lambda: rc.append(main(["train", str(street), "--out", str(run), *TINY,
                                                          "--max-retries", "2"])))
    job.start()
    killed = None
    t0 = time.time()
    try:
        while job.is_alive() and time.time() - t0 < 300:
            try:
                p = json.loads(progress.read_text())
            except (OSError, ValueError):
                p = None
            if p and 10 <= p["step"] < STEPS - 10 and not p["finished"]:
                killed = p
                os.kill(p["pid"], signal.SIGKILL)  # the block's Ray worker, mid-run
                break
            time.sleep(0.05)
        job.join(timeout=400)
    finally:
        ray.shutdown()
    assert killed is not None, "block_00 never reached the step at which it was to be killed"
    assert rc == [0]
    block = run / "blocks" / "block_00"
    attempts = [json.loads(x) for x in (block / "attempts.jsonl").read_text().splitlines()]
    assert len(attempts) == 2 and attempts[0]["pid"] == killed["pid"] and attempts[1]["pid"] != killed["pid"]
    assert attempts[1]["resumed"] and 0 < attempts[1]["start_step"] <= killed["step"]
    assert json.loads((block / "block_result.json").read_text())["attempt"] == 2
    # every step logged exactly once, though some were computed twice; the run finished
    assert _logged_steps(block) == list(range(1, STEPS + 1))
    assert json.loads((block / layout.STATE).read_text())["finished"] is True
    other = [json.loads(x) for x in (run / "blocks" / "block_01" / "attempts.jsonl").read_text().splitlines()]
    assert len(other) == 1
    # nothing lost or duplicated: the killed block ends where the uninterrupted one did
    np.testing.assert_allclose(_block_positions(run, "block_00"), _block_positions(local_run, "block_00"), atol=1e-5)
    assert len(_mesh(run).faces) == len(_mesh(local_run).faces)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _kill_left_over(marker: str) -> None:
    """SIGKILL the processes this test's Ray nodes started (their command lines name its temp folder) that outlived
    `ray start --block`, by pid."""
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit() or int(proc.name) == os.getpid():
            continue
        try:
            if marker.encode() in (proc / "cmdline").read_bytes():
                os.kill(int(proc.name), signal.SIGKILL)
        except (OSError, ProcessLookupError):
            pass


@pytest.mark.slow
def test_two_ray_nodes_on_loopback_spread_the_blocks_and_match_the_local_run(local_run, street, tmp_path):
    ray_bin = shutil.which("ray") or str(Path(sys.executable).with_name("ray"))
    port = _free_port()
    # short (Ray's socket paths under it must stay below 108 bytes); every process of this little cluster names it
    # on its command line: how they are found and ended at the end
    temp = Path(tempfile.mkdtemp(prefix="trisplat-ray-"))
    common = ["--num-cpus", "1", "--node-ip-address", "127.0.0.1", "--block", "--disable-usage-stats"]
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}
    log = open(tmp_path / "ray_start.log", "w")
    head = subprocess.Popen([ray_bin, "start", "--head", "--port", str(port), "--include-dashboard", "false",
                             "--temp-dir", str(temp), *common], env=env, start_new_session=True, stdout=log, stderr=log)
    worker = None
    ray.shutdown()
    try:
        address = f"127.0.0.1:{port}"
        deadline = time.time() + 300  # a loaded machine starts a node slowly
        while True:  # the head answers
            r = subprocess.run([ray_bin, "status", "--address", address], env=env, capture_output=True)
            if r.returncode == 0:
                break
            assert time.time() < deadline and head.poll() is None, \
                f"the Ray head node did not start:\n{(tmp_path / 'ray_start.log').read_text()[-3000:]}"
            time.sleep(1)
        worker = subprocess.Popen([ray_bin, "start", "--address", address, "--temp-dir", str(temp), *common], env=env,
                                  start_new_session=True, stdout=log, stderr=log)
        deadline = time.time() + 300
        while True:  # two nodes
            r = subprocess.run([ray_bin, "status", "--address", address], env=env, capture_output=True, text=True)
            if r.returncode == 0 and r.stdout.count("node_") >= 2:
                break
            assert time.time() < deadline and worker.poll() is None, f"the worker node did not join:\n{r.stdout}"
            time.sleep(1)
        run = tmp_path / "run"
        assert main(["train", str(street), "--out", str(run), *TINY, "--cluster", address]) == 0
    finally:
        ray.shutdown()
        for proc in (worker, head):
            if proc is not None:
                try:
                    os.killpg(proc.pid, signal.SIGTERM)
                except ProcessLookupError:
                    pass
        for proc in (worker, head):
            if proc is not None:
                try:
                    proc.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    os.killpg(proc.pid, signal.SIGKILL)
        _kill_left_over(str(temp))
        log.close()
        shutil.rmtree(temp, ignore_errors=True)
    results = json.loads((run / "blocks.json").read_text())["results"]
    assert len({r["node"] for r in results}) == 2  # one block on each node
    for name in ("block_00", "block_01"):
        np.testing.assert_allclose(_block_positions(run, name), _block_positions(local_run, name), atol=1e-5)
    a, b = _mesh(run), _mesh(local_run)
    assert np.array_equal(np.asarray(a.faces), np.asarray(b.faces))
    np.testing.assert_allclose(np.asarray(a.vertices), np.asarray(b.vertices), atol=1e-4)
