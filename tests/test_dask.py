"""Frame chunks on a Dask ``distributed`` cluster (``Executor(dask_scheduler=...)``): real
scheduler and worker processes on 127.0.0.1. The cluster gives the same trajectory as the local
path, survives a worker killed mid-run, and an unreachable scheduler is an input error."""

import os
import time

import numpy as np
import pytest

from retarget_core import execute
from retarget_core.clip.demo import make_demo_clip, source_rig
from retarget_core.errors import InputError
from retarget_core.execute import Executor
from retarget_core.inputs import RunInputs
from retarget_core.pairing.dense import pair_contacts
from retarget_core.pipeline import retarget
from retarget_core.rig.demo_hands import demo_hand
from retarget_core.solve.config import load_config
from retarget_core.transfer.propose import propose_annotations

distributed = pytest.importorskip("distributed")

from dask_cluster import Cluster, free_port  # noqa: E402

RES = 0.004
# few evaluations, a short refinement: fast, not accurate. No worker count here: it is the
# executor's (not the run configuration's), and the root-only pass is cut into fixed 60-frame
# runs (pipeline.ROOT_SEGMENT_FRAMES) whatever the worker count, so the local run (one process)
# and the cluster run give equal results without matching it.
FAST = {"solver.maxeval": 15, "solver.root_maxeval": 10, "refinement.max_iterations": 2}
N_WORKERS = 2


@pytest.fixture(scope="module")
def dask_cluster(tmp_path_factory):
    cluster = Cluster(tmp_path_factory.mktemp("dask"))
    try:
        cluster.start(N_WORKERS)
        yield cluster
    finally:  # runs on failure too: no process outlives the module
        cluster.close()


@pytest.fixture(scope="module")
def setup(dask_cluster):
    # the cluster processes (requested first) start up while the rigs and the clip are built
    source = source_rig(RES)
    target = demo_hand("human_alt", RES)
    clip = make_demo_clip("bottle_pick_place", time_scale=0.05, resolution=RES, rig=source)  # 46 frames
    annotations = propose_annotations(source, target)
    pairs = pair_contacts(clip)

    inputs = RunInputs.of(clip, source, target, annotations)
    config = load_config(None, "default", FAST)

    def run(progress=None, dask_scheduler=""):
        return retarget(inputs, config, Executor(dask_scheduler=dask_scheduler, progress=progress), pairs=pairs)

    return dict(run=run, n_frames=clip.n_frames, local=run())


@pytest.fixture
def client(dask_cluster):
    """A client of the module's cluster with N_WORKERS live workers (a worker an earlier test
    killed is replaced)."""
    client = dask_cluster.connect(0)
    missing = N_WORKERS - len(client.nthreads())
    for _ in range(missing):
        dask_cluster.add_worker()
    return dask_cluster.connect(N_WORKERS)


def _assert_same_run(got, expected):
    # the frame solves are deterministic: same code, same inputs, one BLAS thread per worker
    # (the nanny sets OMP_NUM_THREADS=1) and no state carried between frames, so chunking and
    # the process a chunk runs in change nothing
    np.testing.assert_array_equal(got.q, expected.q)
    np.testing.assert_array_equal(got.unresolved, expected.unresolved)
    got_passes, expected_passes = got.counts["passes"], expected.counts["passes"]
    for name in ("root", "full", "filter"):
        assert got_passes[name]["failed"] == [] and expected_passes[name]["failed"] == []
        assert got_passes[name]["evaluations"] == expected_passes[name]["evaluations"], name
    for c_got, c_expected in zip(got.curves, expected.curves, strict=True):  # the fit of equal q is equal
        np.testing.assert_array_equal(c_got.coeffs, c_expected.coeffs)
        np.testing.assert_array_equal(c_got.knots, c_expected.knots)


#: The stages that solve frames and report chunk by chunk as chunks complete.
FRAME_STAGES = ("root pass", "full pass", "filter re-solve", "refinement")


def _checked_progress(calls):
    """(stage, done, total) calls -> {stage: [done, ...]}, checking each stage counts up."""
    by_stage = {}
    for stage, done, total in calls:
        by_stage.setdefault((stage, total), []).append(done)
    for (stage, total), done in by_stage.items():
        assert done == sorted(done) and 0 <= done[0] and done[-1] <= total, stage
        # the frame stages report a finished chunk each time; the executor now also announces
        # the other stages of the whole run (transfer, spline fit) with a (stage, 0, 1) start
        frame_stage = stage.split(" round ")[0] in FRAME_STAGES  # refinement rounds after the first are named
        assert done[0] > 0 if frame_stage else done[0] == 0, (stage, done)
    return by_stage


def _cached_runs(client) -> dict:
    """Worker address -> the runs (tokens) whose solver objects its one task thread holds."""
    # a lambda travels by value; execute is imported by name on the worker
    return {w: client.submit(lambda: list(getattr(execute._DASK_LOCAL, "states", {})), workers=[w],
                             pure=False).result()
            for w in client.nthreads()}


def test_cluster_gives_the_local_trajectory(setup, client, dask_cluster):
    before = _cached_runs(client)
    calls = []
    got = setup["run"](progress=lambda *a: calls.append(a), dask_scheduler=dask_cluster.address)
    _assert_same_run(got, setup["local"])
    n = setup["n_frames"]
    by_stage = _checked_progress(calls)
    assert by_stage["root pass", n][-1] == n
    # chunk by chunk as they complete: the 46 frames of the full pass in 11 chunks of 4 and one of 2
    # (execute.FrameRunner.solve: max(4, 46 // (2 cluster threads * 8) + 1) = 4 frames a chunk)
    assert len(by_stage["full pass", n]) == 12 and by_stage["full pass", n][-1] == n
    # both workers solved chunks, each with solver objects built for this run and kept for it
    new = {w: [t for t in tokens if t not in before.get(w, [])] for w, tokens in _cached_runs(client).items()}
    assert len(new) == N_WORKERS and all(len(t) == 1 for t in new.values()), new
    assert len({t[0] for t in new.values()}) == 1


def test_a_worker_killed_mid_run_changes_nothing(setup, client, dask_cluster):
    pids = client.run(os.getpid)  # worker address -> pid of its worker process
    groups = {proc.pid: proc for proc in dask_cluster.workers}
    killed = {}

    def progress(stage, done, total):
        if stage == "full pass" and not killed:
            # a worker holding chunks of this pass (running or queued on it) dies
            busy = [w for w, keys in client.processing().items() if keys]
            assert busy, "no chunk in flight"
            victim = busy[0]
            killed.update(address=victim, keys=list(client.processing()[victim]), done=done, total=total)
            dask_cluster.kill(groups[os.getpgid(pids[victim])])

    got = setup["run"](progress=progress, dask_scheduler=dask_cluster.address)
    assert killed and killed["done"] < killed["total"] and killed["keys"]
    _assert_same_run(got, setup["local"])
    # the scheduler noticed, and the dead worker's chunks were computed elsewhere
    assert killed["address"] not in client.nthreads() and len(client.nthreads()) == N_WORKERS - 1
    # the chunks the scheduler had given it were taken back when it left and computed by another
    # worker (client.story rows: (who, key, start, finish, ...); the scheduler's rows carry the
    # stimulus id after the recommendations, "handle-worker-cleanup-..." for a lost worker). Not
    # necessarily all of them: one may have finished in the instant before the kill.
    story = client.story(*killed["keys"])
    taken_back = {r[1] for r in story if r[0] == "scheduler" and r[2:4] == ("processing", "released")
                  and str(r[5]).startswith("handle-worker-cleanup")}
    assert taken_back, story
    for key in taken_back:
        assert any(r[1] == key and r[0] not in ("scheduler", killed["address"]) and r[2:4] == ("executing", "memory")
                   for r in story), story


def test_unreachable_scheduler_is_an_input_error(setup, monkeypatch):
    monkeypatch.setattr(execute, "DASK_CONNECT_TIMEOUT", 2.0)
    address = f"tcp://127.0.0.1:{free_port()}"  # nothing listens there
    t0 = time.monotonic()
    with pytest.raises(InputError, match="dask_scheduler") as err:
        setup["run"](dask_scheduler=address)
    assert time.monotonic() - t0 < 15.0
    assert err.value.element == "executor.dask_scheduler" and address in str(err.value)
