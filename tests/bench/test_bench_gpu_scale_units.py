"""Parts of the GPU benches that their runs depend on, checked here: from ``bench/lib`` (what
``bench/bench_gpu_scale.py`` is built of), which CPUs pods get on a machine with hyperthreads, the
slowest-pod figures of a stage call, ``--stage-layout`` and the CUDA-graph sizes a loop's
batches run in; and the chunks bench's ceiling processes (``lib.ceiling``), which stay up between
rounds and fail a run naming their error.

``bench/lib`` is imported with ``bench/`` on ``sys.path``, as a bench script imports it.
"""

from __future__ import annotations


import pytest
from support.bench_scripts import bench_importable

from vecsim.rollout import RolloutStats


@pytest.fixture(scope="module")
def lib():
    with bench_importable():
        import lib.ceiling
        import lib.jobs
        import lib.machine
        import lib.measure
        import lib.policies
        import lib.stats

        yield lib


def topology(siblings: dict[int, int]) -> dict:
    """A machine whose CPU n sits on physical core siblings[n]."""
    per_cpu = {str(cpu): {"package": "0", "core": str(core), "siblings": ""} for cpu, core in siblings.items()}
    return {"per_cpu": per_cpu}


def test_pods_get_one_thread_of_every_physical_core_before_any_hyperthread_sibling(lib):
    # 8 vCPUs on 4 cores, siblings numbered n and n+4 (the common Linux layout)
    order = lib.machine.cores_first(topology({n: n % 4 for n in range(8)}))
    assert order == [0, 1, 2, 3, 4, 5, 6, 7]
    # siblings adjacent (0,1), (2,3), ...: the first thread of each core comes first
    order = lib.machine.cores_first(topology({n: n // 2 for n in range(8)}))
    assert order == [0, 2, 4, 6, 1, 3, 5, 7]


def test_the_policy_is_graphed_for_every_multiple_of_a_pods_envs_and_pads_other_batches(lib):
    assert lib.policies.pod_multiples(5, 40) == [5, 10, 15, 20, 25, 30, 35, 40]
    assert lib.policies.pod_multiples(10, 25, extra=[12]) == [10, 12, 20, 25]
    # Padding picks the smallest captured size above a batch; with nothing above, or without
    # padding, the batch's own size (captured when first met).
    graphs = dict.fromkeys([5, 10, 40])
    padded = lib.policies.GraphedPolicy(None, None, "cpu", [], pad=True)
    padded.graphs = graphs
    assert [padded.graph_size(n) for n in (1, 5, 6, 11, 40, 41)] == [5, 5, 10, 40, 40, 41]
    plain = lib.policies.GraphedPolicy(None, None, "cpu", [])
    plain.graphs = graphs
    assert [plain.graph_size(n) for n in (1, 6, 41)] == [1, 6, 41]


def test_the_trainer_gets_the_cpus_the_pods_do_not_and_shares_only_when_there_are_too_few(lib):
    assert lib.machine.split_cores([0, 2, 4, 6, 1, 3, 5, 7], 4) == (["0", "2", "4", "6"], [1, 3, 5, 7])
    assert lib.machine.split_cores([0, 1], 2) == (["1", "1"], [0])


def test_the_slowest_pod_of_each_call_is_measured_against_the_calls_mean(lib):
    calls = [
        ("sim-0", "reset", 0.0, 5.0),  # resets are not step calls
        ("sim-0", "step", 0.0, 0.100),
        ("sim-1", "step", 0.0, 0.300),
        ("sim-0", "step", 1.0, 1.200),
        ("sim-1", "step", 1.0, 1.100),
    ]
    counters = dict.fromkeys(lib.measure.POD_COUNTERS, 0.0)
    per_pod = {
        "sim-0": {**counters, "vecsim_pod_step_seconds_sum": 0.2, "vecsim_pod_step_seconds_count": 2},
        "sim-1": {**counters, "vecsim_pod_step_seconds_sum": 0.3, "vecsim_pod_step_seconds_count": 2},
    }
    run = lib.measure.Measured(RolloutStats(), counters, per_pod, calls, {"sim-0": 0, "sim-1": 0})
    figures = lib.stats.slowest_pod([run])
    assert figures["calls"] == 2
    assert figures["pod_round_trip_mean_ms"] == pytest.approx(175.0)  # median of the calls' means 200, 150
    assert figures["pod_round_trip_slowest_ms"] == pytest.approx(250.0)  # median of 300, 200
    assert figures["wait_for_slowest_ms"] == pytest.approx(75.0)  # median of 100, 50
    assert figures["slowest_pod_counts"] == {"sim-1": 1, "sim-0": 1}
    assert figures["pod_step_ms_by_pod"] == {"sim-0": 100.0, "sim-1": 150.0}


def test_the_handoff_splits_a_stages_turn_around_its_pods_requests(lib):
    # Stage 0's policy at 0-1 s sends two step calls (at 1.1 and 1.3 s; their HTTP requests take
    # 1.3 and 1.4 s inside them), which are in at 2.5 and 2.8 s; its next policy call starts at
    # 3.0 s. Stage 1's policy runs 1-2 s and 2.9-2.95 s, so 0.05 s of the 0.2 s handoff the GPU
    # was busy with the other stage.
    timeline = [("policy", 0, 0.0, 1.0), ("policy", 1, 1.0, 2.0), ("policy", 1, 2.9, 2.95), ("policy", 0, 3.0, 4.0)]
    pod_calls = [(0, "sim-0", 1.1, 2.5, 0, 5), (0, "sim-1", 1.3, 2.8, 0, 5), (0, "sim-1", 0.0, 0.5, 5, 0)]
    requests = [("sim-0", "step", 101.15, 102.45), ("sim-1", "step", 101.35, 102.75), ("sim-1", "reset", 100.0, 100.4)]
    counters = dict.fromkeys(lib.measure.POD_COUNTERS, 0.0)
    stats = RolloutStats(timeline=timeline, pod_calls=pod_calls)
    split = lib.stats.handoff([lib.measure.Measured(stats, counters, {}, requests, {}, started=100.0)])
    assert split == pytest.approx(
        {
            "send": 200.0,
            "send_spread": 200.0,
            "call_beyond_request": 100.0,
            "last_answer_to_policy": 200.0,
            "last_answer_to_policy_idle": 150.0,
        }
    )
    # Without the loop's clock origin the requests cannot be lined up: that figure is left out.
    assert lib.stats.handoff([lib.measure.Measured(stats, counters, {}, requests, {})])["call_beyond_request"] is None


def test_pods_of_different_stages_are_not_compared_within_one_call(lib):
    calls = [("sim-0", "step", 0.0, 0.1), ("sim-1", "step", 0.0, 0.5)]
    counters = dict.fromkeys(lib.measure.POD_COUNTERS, 0.0)
    run = lib.measure.Measured(RolloutStats(), counters, {}, calls, {"sim-0": 0, "sim-1": 1})
    figures = lib.stats.slowest_pod([run])
    assert figures["calls"] == 2 and figures["wait_for_slowest_ms"] == 0


def test_memory_above_the_limit_stops_the_run_with_a_memory_error(lib):
    import time

    with pytest.raises(MemoryError, match="--max-memory-gib"):
        with lib.machine.MemoryWatch(limit_gib=0.0, every_s=0.05):
            for _ in range(200):  # the watched run, 10 s at most: the watch trips within its first sample
                time.sleep(0.05)


def test_memory_below_the_limit_lets_the_run_finish_and_keeps_the_peak(lib):
    with lib.machine.MemoryWatch(limit_gib=1e6, every_s=0.05) as watch:
        pass
    assert watch.tripped is None and watch.peak_gib > 0


def test_the_slices_view_puts_every_pod_in_both_stages_with_its_envs_alternating(lib):
    from vecsim.config import RoutedPod, RoutedStage, RoutingTable, TaskBlock

    pods = [
        RoutedPod(
            pod=f"sim-{i}",
            url=f"http://127.0.0.1:{8100 + i}",
            num_envs=3,
            tasks=(TaskBlock(task_id="a", env_start=0, num_envs=2), TaskBlock(task_id="b", env_start=2, num_envs=1)),
        )
        for i in range(2)
    ]
    table = RoutingTable(
        generation=1,
        job_id="j",
        ready=True,
        stages=tuple(RoutedStage(stage_id=i, pods=(p,)) for i, p in enumerate(pods)),
    )
    sliced = lib.jobs.regroup_slices(table, ["sim-0", "sim-1"], 2)
    assert [[p.pod for p in stage.pods] for stage in sliced.stages] == [["sim-0", "sim-1"]] * 2
    envs = {(s.stage_id, p.pod): [(b.task_id, b.env_start) for b in p.tasks] for s in sliced.stages for p in s.pods}
    assert envs[(0, "sim-0")] == [("a", 0), ("b", 2)] and envs[(1, "sim-0")] == [("a", 1)]
    # The alternation runs on into the next pod: its first env is on stage 1, so stages stay even.
    assert envs[(1, "sim-1")] == [("a", 0), ("b", 2)] and envs[(0, "sim-1")] == [("a", 1)]
    assert [stage.num_envs for stage in sliced.stages] == [3, 3]
    # Request i on stage i % 2: stage 0's a, b, a against stage 1's a, a, b.
    assert [task for task, _ in lib.jobs.requests_for(sliced)] == ["a", "a", "b", "a", "a", "b"]


def test_a_chunked_policy_repeats_its_action_k_times(lib):
    import torch

    policy = lib.measure.Chunked(lambda obs, instructions, task_ids: torch.arange(6.0).view(3, 2), 4)
    chunks = policy({}, [""] * 3, [""] * 3)
    assert chunks.shape == (3, 4, 2) and torch.equal(chunks[:, 3], torch.arange(6.0).view(3, 2))
    assert lib.measure.Chunked(lambda *a: torch.ones(3, 2), 1)({}, [], []).shape == (3, 2)


def test_stage_layouts_come_in_order_each_once_and_an_unknown_one_is_named(lib):
    assert lib.jobs.parse_stage_layouts("pods,slices,pods") == ("pods", "slices")
    assert lib.jobs.parse_stage_layouts("slices") == ("slices",)
    with pytest.raises(SystemExit, match="'pods,rows'"):
        lib.jobs.parse_stage_layouts("pods,rows")
    with pytest.raises(SystemExit, match="comma-separated"):
        lib.jobs.parse_stage_layouts(",")


def _plan(lib, tasks: tuple[str, ...]):
    return lib.jobs.Plan(
        mode="scaling",
        tasks=tasks,
        size=8,
        envs_per_task=1,
        pods=1,
        pod_counts=(1,),
        pipeline_cores=1,
        horizon=4,
        service_steps=4,
        rounds=1,
        device="cpu",
        dtype="float32",
        vit_width=0,
        vit_max_depth=0,
        max_memory_gib=100.0,
        deadline_s=60.0,
    )


@pytest.mark.timeout(120)
def test_the_ceiling_processes_measure_every_k_on_demand_and_stay_up_between_rounds(lib):
    with lib.ceiling.CeilingProcesses(["0"], _plan(lib, ("gym/HalfCheetah-v5",)), [1, 4], 0.2, 3, 60.0) as top:
        first, second = top.measure(), top.measure()
        assert all(proc.is_alive() for proc in top._procs)
    for figures in (first, second):
        assert set(figures) == {"K=1", "K=1/reset_every_3", "K=4", "K=4/reset_every_3"}
        assert all(run["env_steps_per_s"] > 0 for run in figures.values())
    assert not any(proc.is_alive() for proc in top._procs)


@pytest.mark.timeout(120)
def test_a_ceiling_process_that_cannot_build_its_envs_fails_the_run_naming_its_error(lib):
    top = lib.ceiling.CeilingProcesses(["0"], _plan(lib, ("gym/NoSuchEnv-v0",)), [1], 0.2, 0, 60.0)
    with pytest.raises(RuntimeError, match="pinned process 0 failed"):
        top.__enter__()
    assert not any(proc.is_alive() for proc in top._procs)
