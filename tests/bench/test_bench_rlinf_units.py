"""What ``bench/bench_rlinf.py --mjwarp`` decides before any GPU work, checked here: the slots'
task mix and reset ids (RLinf's own reset-id mapping judges them, on LIBERO's own suite), the
``mjwarp`` pod's job (vecsim's RLinf env must place every slot on it), the pod's environment,
the best-over-best ratio, and the task list read from exported scenes."""

from __future__ import annotations


import pytest
from support import ROOT
from support.bench_scripts import bench_import

from vecsim.client.routing import RoutedEnv
from vecsim.engine.mjwarp.scene import ROOT_ENV, export_scene
from vecsim.trainers.rlinf import place_slots

SUITE = "libero_10"
TASKS = [0, 1, 4, 6, 7]


@pytest.fixture(scope="module")
def bench():
    with bench_import("bench_rlinf") as module:
        yield module


@pytest.mark.libero
def test_reset_ids_give_each_slot_its_task_in_rlinf_s_own_mapping(bench):
    """RLinf's ``LiberoEnv`` maps reset ids to (task, trial) from LIBERO's suite and validates its
    ``task_id_filter``; its own methods run here on a bare instance (no env processes)."""
    pytest.importorskip("rlinf")
    from vecsim.engine.tasks import ensure_config

    ensure_config()
    from libero.libero import benchmark
    from rlinf.envs.libero.libero_env import LiberoEnv

    theirs = object.__new__(LiberoEnv)
    theirs.task_suite = benchmark.get_benchmark_dict()[SUITE]()
    theirs.task_id_filter = TASKS
    theirs._compute_total_num_group_envs()
    ids = bench.reset_ids(1024, TASKS)
    tasks, trials = theirs._get_task_and_trial_ids_from_reset_state_ids(ids)
    assert tasks.tolist() == bench.slot_tasks(1024, TASKS)
    assert trials.min() >= 0 and trials.max() < 50
    # The first 50 slots of each task start from distinct init states.
    first = ids[: 50 * len(TASKS)]
    assert len(set(first.tolist())) == first.size


def test_the_mjwarp_job_holds_an_env_for_every_slot(bench):
    slots = bench.slot_tasks(1024, TASKS)
    job = bench.mjwarp_assignment(SUITE, slots, 256)
    assert job.engine == "mjwarp" and job.libero == bench.PROTOCOL and job.num_envs == 1024
    assert [b.task_id for b in job.tasks] == [f"{SUITE}/{t}" for t in TASKS]
    envs = [
        RoutedEnv(job.pod, block.env_start + i, block.task_id, 0) for block in job.tasks for i in range(block.num_envs)
    ]
    placed = place_slots(envs, {}, {slot: f"{SUITE}/{task}" for slot, task in enumerate(slots)}, 0)
    assert len({(e.pod, e.env_index) for e in placed.values()}) == len(slots)
    assert all(placed[slot].task_id == f"{SUITE}/{task}" for slot, task in enumerate(slots))


def test_the_mjwarp_pod_runs_this_checkout_on_its_own_stack(bench):
    assert bench.mjwarp_pod_env("/tmp/site-mjw:/tmp/site") == {"PYTHONPATH": f"{ROOT}:/tmp/site-mjw:/tmp/site"}


def test_best_over_best_sets_each_contender_s_best_slot_count_beside_the_other(bench):
    def row(slots, **medians):
        return {"slots": slots, "env_steps_per_s": {k: {"median": v} for k, v in medians.items()}}

    rows = [row(12, rlinf=150.0, vecsim=300.0), row(24, rlinf=180.0, vecsim=500.0), row(1024, vecsim=4500.0)]
    best = bench.best_over_best(rows)
    assert best["rlinf"] == {"slots": 24, "median": 180.0}
    assert best["vecsim"] == {"slots": 1024, "median": 4500.0}
    assert best["ratio"] == pytest.approx(4500.0 / 180.0)


def test_task_ids_are_the_given_ones(bench):
    assert bench.task_ids("3,5", SUITE) == [3, 5]


def test_without_served_scenes_the_bench_says_how_to_export_them(bench, tmp_path, monkeypatch):
    monkeypatch.setenv(ROOT_ENV, str(tmp_path))
    with pytest.raises(SystemExit, match="python -m vecsim.engine.mjwarp.scene libero_10/0"):
        bench.task_ids(None, SUITE)


@pytest.mark.libero
@pytest.mark.slow
def test_task_ids_default_to_the_scenes_exported_under_rlinf_s_protocol(bench, tmp_path, monkeypatch):
    export_scene(f"{SUITE}/0", bench.PROTOCOL, root=tmp_path)
    monkeypatch.setenv(ROOT_ENV, str(tmp_path))
    assert bench.task_ids(None, SUITE) == [0]
